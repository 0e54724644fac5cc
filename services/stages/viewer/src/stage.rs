//! The viewer as a [`Stage`]: its inputs drained on every wake-up into what it shows, and the
//! Foxglove channels logged when a client subscribes to them and their rate allows.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Duration, Instant};

use ::foxglove::messages::{Grid, Log, PointCloud, Pose, PoseInFrame, PosesInFrame};
use ::foxglove::{Channel, Context, WebSocketServerHandle};
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Input, Output, ProcessContext, Runtime, StageError, Wake};
use shared_types::foxglove::{self as fx, FRAME, pose as pose_of, stamp};
use shared_types::services::{self, CONTROL_QOS};
use shared_types::voxel_stream::{VoxelKey, apply};
use shared_types::*;

use crate::ViewerSettings;

/// A rate limit: `due` at most once per `period`.
struct Every {
    period: Duration,
    last: Option<Instant>,
}

impl Every {
    fn hz(hz: f64) -> Self {
        Self { period: Duration::from_secs_f64(1.0 / hz), last: None }
    }

    fn due(&mut self) -> bool {
        let now = Instant::now();
        if self.last.is_some_and(|t| now - t < self.period) {
            return false;
        }
        self.last = Some(now);
        true
    }
}

use crate::summary::{ChannelCounts as Counts, ViewerPart, ViewerSummary};

/// One trajectory: its poses, thinned when full, and its channel.
struct Path {
    poses: Vec<Pose>,
    last_ns: u64,
    channel: Channel<PosesInFrame>,
    dirty: bool,
    thinned: u64,
}

impl Path {
    fn push(&mut self, ns: u64, pose: Pose, max: usize) {
        if self.poses.len() >= max {
            // Every second pose of the older half: the shape stays, the length is bounded.
            let half = self.poses.len() / 2;
            let mut kept: Vec<Pose> = self.poses[..half].iter().step_by(2).copied().collect();
            self.thinned += (half - kept.len()) as u64;
            kept.extend_from_slice(&self.poses[half..]);
            self.poses = kept;
        }
        self.poses.push(pose);
        self.last_ns = ns;
        self.dirty = true;
    }
}

/// `<out_dir>/ground_truth.tum` read as the source writes it (whole lines, as it learns the
/// truth; a restarted source truncates it and the path starts over).
struct TruthTail {
    path: std::path::PathBuf,
    offset: u64,
    partial: String,
    /// The file's first bytes as last read: a file written anew (a stale one from an earlier run
    /// replaced by this run's source) starts differently.
    head: Vec<u8>,
    /// Lines that are not a TUM pose (counted).
    bad_lines: u64,
}

impl TruthTail {
    /// The poses (stamp ns, pose) written since the last call; `reset` is set when the file
    /// was truncated.
    fn read_new(&mut self, reset: &mut bool) -> Vec<(u64, Pose)> {
        use std::io::{Read, Seek, SeekFrom};
        let Ok(mut f) = std::fs::File::open(&self.path) else { return vec![] };
        let len = f.metadata().map(|m| m.len()).unwrap_or(0);
        let mut head = vec![0u8; len.min(64) as usize];
        if f.read_exact(&mut head).is_err() {
            return vec![];
        }
        let same = head.iter().zip(&self.head).all(|(a, b)| a == b);
        self.head = head;
        if len < self.offset || !same {
            *reset = true;
            self.offset = 0;
            self.partial.clear();
        }
        if len == self.offset || f.seek(SeekFrom::Start(self.offset)).is_err() {
            return vec![];
        }
        let mut text = String::new();
        let Ok(n) = f.take(len - self.offset).read_to_string(&mut text) else { return vec![] };
        self.offset += n as u64;
        self.partial.push_str(&text);
        let Some(end) = self.partial.rfind('\n') else { return vec![] };
        let complete: String = self.partial.drain(..=end).collect();
        let mut out = vec![];
        for line in complete.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
            let v: Vec<f64> = line.split_whitespace().filter_map(|x| x.parse().ok()).collect();
            if v.len() != 8 || v.iter().any(|x| !x.is_finite()) || v[0] < 0.0 {
                self.bad_lines += 1;
                continue;
            }
            out.push(((v[0] * 1e9).round() as u64, pose_of([v[1], v[2], v[3]], [v[4], v[5], v[6], v[7]])));
        }
        out
    }
}

/// The `viewer` stage.
pub struct ViewerStage {
    settings: ViewerSettings,
    server: Option<WebSocketServerHandle>,
    port: u16,
    /// The TLS and token gate in front of the server (with `tls`).
    gate: Option<crate::gate::Gate>,
    _context: Arc<Context>,
    slam_pose: Option<Input<PoseEstimate, MsgHeader>>,
    buoy_fix: Option<Input<BuoyFix, MsgHeader>>,
    fused_pose: Option<Input<FusedPose, MsgHeader>>,
    grid_pose: Option<Input<PoseEstimate, MsgHeader>>,
    cloud: Option<Input<[CloudPoint], CloudHeader>>,
    fusion_map: Option<Input<[Landmark], LandmarkMapHeader>>,
    slam_landmarks: Option<Input<[Landmark], LandmarkMapHeader>>,
    voxels: Option<Input<[Voxel], VoxelSetHeader>>,
    grid: Option<Input<[OccupancyCell], OccupancyGridHeader>>,
    traversability: Option<Input<[TraversabilityCell], OccupancyGridHeader>>,
    heartbeats: Option<Input<Heartbeat, MsgHeader>>,
    /// Asks the octree mapper for a full voxel set when a client watches `/octree` and none is held.
    commands: Option<Output<ControlCommand, MsgHeader>>,
    snapshot_asked: Option<Instant>,
    snapshots_asked: u64,
    /// Inputs that could not be opened (the service full, say), with why.
    not_shown: BTreeMap<String, String>,
    paths: BTreeMap<&'static str, Path>,
    truth: TruthTail,
    fused_now: Channel<PoseInFrame>,
    cloud_ch: Channel<PointCloud>,
    landmarks_ch: Channel<PointCloud>,
    octree_ch: Channel<PointCloud>,
    grid_ch: Channel<Grid>,
    traversability_ch: Channel<Grid>,
    /// The newest traversability grid, shown again to a client that starts watching after it
    /// came (the mapper sends one at the end of its run, or one every so often).
    traversability_latest: Option<Grid>,
    traversability_watched: bool,
    processes_ch: Channel<Log>,
    counts: BTreeMap<&'static str, Counts>,
    cloud_every: Every,
    landmarks_every: Every,
    /// A fused global map with at least one landmark has come: `/landmarks` shows fusion's map
    /// from then on.
    fused_landmarks: bool,
    octree_every: Every,
    grid_every: Every,
    path_every: Every,
    processes_every: Every,
    /// The octree as the voxel stream says (held only while someone watches `/octree`).
    octree: HashMap<VoxelKey, Voxel>,
    octree_full: bool,
    octree_dirty: bool,
    octree_stamp: u64,
    /// Deltas that came before a full set (the map is shown from the next full set).
    octree_waiting: u64,
    /// Latest heartbeat per process.
    processes: BTreeMap<String, Heartbeat>,
    clients_max: usize,
    /// The SDK's "outbox for client ... full" log events (it dropped the oldest messages for a
    /// slow client; it reports that at most every 30 s and does not say how many).
    sdk_outbox_full: std::sync::Arc<std::sync::atomic::AtomicU64>,
    sdk_outbox_full_warned: u64,
    started: Instant,
}

/// Opens an input, or says why not (the viewer shows the rest).
fn open<T>(
    not_shown: &mut BTreeMap<String, String>,
    service: &str,
    r: Result<T, pipeline_runtime::runtime::RuntimeError>,
) -> Option<T> {
    match r {
        Ok(i) => Some(i),
        Err(e) => {
            tracing::warn!(service, "not shown: {e}");
            not_shown.insert(service.into(), e.to_string());
            None
        }
    }
}

impl ViewerStage {
    fn count(&mut self, channel: &'static str) -> &mut Counts {
        self.counts.entry(channel).or_default()
    }

    /// Whether a message for `channel` is to be converted now: someone subscribes and its rate
    /// allows. Counts the skip otherwise.
    fn wanted(counts: &mut Counts, watched: bool, every: &mut Every) -> bool {
        counts.received += 1;
        if !watched {
            counts.skipped_unwatched += 1;
            false
        } else if !every.due() {
            counts.skipped_rate += 1;
            false
        } else {
            counts.logged += 1;
            true
        }
    }

    fn drain_poses(&mut self) -> Result<(), StageError> {
        let max = self.settings.path_max_poses;
        let add =
            |paths: &mut BTreeMap<&'static str, Path>, counts: &mut BTreeMap<&'static str, Counts>, name, ns, pose| {
                counts.entry(name).or_default().received += 1;
                if let Some(p) = paths.get_mut(name) {
                    p.push(ns, pose, max);
                }
            };
        if let Some(i) = &self.slam_pose {
            while let Some(s) = i.receive()? {
                let p = s.payload();
                add(
                    &mut self.paths,
                    &mut self.counts,
                    "/slam/path",
                    s.user_header().stamp_ns,
                    pose_of(p.position_m, p.orientation_xyzw),
                );
            }
        }
        if let Some(i) = &self.grid_pose {
            while let Some(s) = i.receive()? {
                let p = s.payload();
                add(
                    &mut self.paths,
                    &mut self.counts,
                    "/grid_slam/path",
                    s.user_header().stamp_ns,
                    pose_of(p.position_m, p.orientation_xyzw),
                );
            }
        }
        if let Some(i) = &self.buoy_fix {
            while let Some(s) = i.receive()? {
                let p = s.payload();
                add(
                    &mut self.paths,
                    &mut self.counts,
                    "/buoy/path",
                    s.user_header().stamp_ns,
                    pose_of(p.position_m, [0.0, 0.0, 0.0, 1.0]),
                );
            }
        }
        let mut reset = false;
        for (ns, pose) in self.truth.read_new(&mut reset) {
            add(&mut self.paths, &mut self.counts, "/ground_truth/path", ns, pose);
        }
        if reset && let Some(p) = self.paths.get_mut("/ground_truth/path") {
            p.poses.clear(); // the source restarted: its ground truth starts over
        }
        if let Some(i) = &self.fused_pose {
            let mut latest = None;
            while let Some(s) = i.receive()? {
                let p = s.payload();
                // The mapper's choice: refined poses (and those never predicted) make the path;
                // the live pose is the newest of any kind.
                let pose = pose_of(p.pose.position_m, p.pose.orientation_xyzw);
                latest = Some((s.user_header().stamp_ns, pose));
                if p.flags & FUSED_PREDICTED == 0 {
                    add(&mut self.paths, &mut self.counts, "/fused/path", s.user_header().stamp_ns, pose);
                }
            }
            if let Some((ns, pose)) = latest {
                let c = self.counts.entry("/fused/pose").or_default();
                c.received += 1;
                if self.fused_now.has_sinks() {
                    c.logged += 1;
                    self.fused_now.log(&fx::pose_in_frame(ns, pose));
                } else {
                    c.skipped_unwatched += 1;
                }
            }
        }
        if self.path_every.due() {
            for (name, p) in &mut self.paths {
                if !p.dirty {
                    continue;
                }
                p.dirty = false;
                if p.channel.has_sinks() {
                    self.counts.entry(name).or_default().logged += 1;
                    p.channel.log(&PosesInFrame {
                        timestamp: stamp(p.last_ns),
                        frame_id: FRAME.into(),
                        poses: p.poses.clone(),
                    });
                }
            }
        }
        Ok(())
    }

    fn drain_cloud(&mut self) -> Result<(), StageError> {
        let Some(i) = &self.cloud else { return Ok(()) };
        let watched = self.cloud_ch.has_sinks();
        let mut latest = None;
        while let Some(s) = i.receive()? {
            let c = self.counts.entry("/cloud").or_default();
            if Self::wanted(c, watched, &mut self.cloud_every) {
                latest = Some(fx::cloud(s.user_header(), s.payload()));
            }
        }
        if let Some(m) = latest {
            self.cloud_ch.log(&m);
        }
        Ok(())
    }

    fn drain_landmarks(&mut self) -> Result<(), StageError> {
        let watched = self.landmarks_ch.has_sinks();
        // The fused global map once it holds a landmark, else SLAM's best particle's map (an
        // empty fused map, before fusion's first local map is done, hides nothing: it is not
        // shown or counted for the channel).
        for (fused, input) in [(true, &self.fusion_map), (false, &self.slam_landmarks)] {
            let Some(input) = input else { continue };
            let mut latest = None;
            while let Some(s) = input.receive()? {
                if fused && !self.fused_landmarks {
                    if s.payload().is_empty() {
                        continue;
                    }
                    self.fused_landmarks = true;
                }
                let c = self.counts.entry("/landmarks").or_default();
                if Self::wanted(c, watched, &mut self.landmarks_every) {
                    latest = Some(fx::landmarks(s.user_header(), s.payload()));
                }
            }
            if let Some(m) = latest {
                self.landmarks_ch.log(&m);
            }
            if fused && self.fused_landmarks {
                // Once the fused map has landmarks, SLAM's is not shown (it is drained all the same).
                if let Some(i) = &self.slam_landmarks {
                    while i.receive()?.is_some() {}
                }
                break;
            }
        }
        Ok(())
    }

    fn drain_octree(&mut self) -> Result<(), StageError> {
        let Some(i) = &self.voxels else { return Ok(()) };
        let watched = self.octree_ch.has_sinks();
        while let Some(s) = i.receive()? {
            let c = self.counts.entry("/octree").or_default();
            c.received += 1;
            if !watched {
                // Nobody looks: hold nothing (the view starts from the next full set).
                c.skipped_unwatched += 1;
                self.octree.clear();
                self.octree_full = false;
                continue;
            }
            let h = *s.user_header();
            if apply(&mut self.octree, &mut self.octree_full, h.kind, s.payload()) {
                self.octree_dirty = true;
                self.octree_stamp = h.msg.stamp_ns;
            } else {
                self.octree_waiting += 1;
            }
        }
        if watched && !self.octree_full && self.snapshot_asked.is_none_or(|t| t.elapsed() > Duration::from_secs(5)) {
            // A client came (or the held map was dropped while nobody looked): ask for a full set
            // now rather than wait for the mapper's next periodic one.
            if let Some(out) = &mut self.commands {
                let now = pipeline_runtime::monotonic_ns();
                out.send_value(
                    MsgHeader { stamp_ns: now, origin_ns: now, ..Default::default() },
                    ControlCommand { target: [0; 32], command: COMMAND_VOXEL_SNAPSHOT, _reserved: 0, arg: 0 },
                )?;
                self.snapshot_asked = Some(Instant::now());
                self.snapshots_asked += 1;
            }
        }
        if self.octree_dirty && watched && self.octree_every.due() {
            self.octree_dirty = false;
            self.count("/octree").logged += 1;
            let m = fx::voxels(self.octree_stamp, self.octree.values());
            self.octree_ch.log(&m);
        }
        Ok(())
    }

    fn drain_grid(&mut self) -> Result<(), StageError> {
        let Some(i) = &self.grid else { return Ok(()) };
        let watched = self.grid_ch.has_sinks();
        let mut latest = None;
        while let Some(s) = i.receive()? {
            let c = self.counts.entry("/grid").or_default();
            if Self::wanted(c, watched, &mut self.grid_every) {
                latest = Some(fx::grid(s.user_header(), s.payload()));
            }
        }
        if let Some(m) = latest {
            self.grid_ch.log(&m);
        }
        Ok(())
    }

    /// The newest traversability grid, logged when it comes and again when a client starts
    /// watching `/traversability` (the mapper sends it rarely: at its end, or every
    /// `traversability_interval_s`).
    fn drain_traversability(&mut self) -> Result<(), StageError> {
        let Some(i) = &self.traversability else { return Ok(()) };
        let watched = self.traversability_ch.has_sinks();
        let mut fresh = false;
        while let Some(s) = i.receive()? {
            let c = self.counts.entry("/traversability").or_default();
            c.received += 1;
            self.traversability_latest = Some(fx::traversability(s.user_header(), s.payload()));
            fresh = true;
        }
        let newly_watched = watched && !self.traversability_watched;
        self.traversability_watched = watched;
        if let Some(m) = &self.traversability_latest
            && watched
            && (fresh || newly_watched)
        {
            self.counts.entry("/traversability").or_default().logged += 1;
            self.traversability_ch.log(m);
        } else if fresh && !watched {
            self.counts.entry("/traversability").or_default().skipped_unwatched += 1;
        }
        Ok(())
    }

    fn drain_processes(&mut self) -> Result<(), StageError> {
        if let Some(i) = &self.heartbeats {
            while let Some(s) = i.receive()? {
                let hb = *s.payload();
                self.processes.insert(name_from32(&hb.process), hb);
            }
        }
        if self.processes_every.due() && self.processes_ch.has_sinks() {
            let now = pipeline_runtime::monotonic_ns();
            for (name, hb) in &self.processes {
                let state = match hb.state {
                    1 => "starting",
                    2 => "ready",
                    3 => "stopping",
                    _ => "unknown",
                };
                self.processes_ch.log(&Log {
                    timestamp: stamp(now),
                    level: 2, // INFO
                    message: format!(
                        "{name}: {state}, up {:.1} s, {} messages in, {} out (pid {})",
                        hb.uptime_ns as f64 / 1e9,
                        hb.messages_in,
                        hb.messages_out,
                        hb.pid
                    ),
                    name: name.clone(),
                    file: String::new(),
                    line: 0,
                });
                self.counts.entry("/processes").or_default().logged += 1;
            }
        }
        Ok(())
    }
}

/// Starts the Foxglove WebSocket server: on `host:port`, or with TLS and a token on loopback
/// behind the gate (crate::gate) that listens on `host:port`. Returns the server, the gate and the
/// port clients connect to.
fn start_server(
    context: &Arc<Context>,
    ctx: &ProcessContext,
    settings: &ViewerSettings,
) -> Result<(WebSocketServerHandle, Option<crate::gate::Gate>, u16), StageError> {
    // With TLS, the SDK's server listens on loopback only, behind the gate (crate::gate).
    let secured = settings.tls.as_ref().zip(settings.token_file.as_ref());
    let (sdk_host, sdk_port) = match secured {
        Some(_) => ("127.0.0.1".to_string(), 0),
        None => (settings.host.clone(), settings.port),
    };
    let server = context
        .websocket_server()
        .name(format!("slam pipeline: {}", ctx.name))
        .bind(sdk_host.clone(), sdk_port)
        .message_backlog_size(settings.client_backlog)
        .start_blocking()
        .map_err(|e| {
            StageError::msg(format!(
                "the Foxglove WebSocket server cannot listen on {sdk_host}:{sdk_port} (processes.{}.settings.host / \
                     port): {e}",
                ctx.name
            ))
        })?;
    let mut port = server.port();
    let gate = match secured {
        None => None,
        Some((tls, token_file)) => {
            let name = &ctx.name;
            let config = crate::gate::tls_config(&tls.certificate, &tls.private_key)
                .map_err(|e| StageError::Settings(format!("processes.{name}.settings.tls: {e}")))?;
            let token = crate::read_token(token_file)
                .map_err(|e| StageError::Settings(format!("processes.{name}.settings.token_file: {e}")))?;
            let ip: std::net::IpAddr = settings
                .host
                .parse()
                .map_err(|e| StageError::Settings(format!("processes.{name}.settings.host: {e}")))?;
            let upstream = std::net::SocketAddr::from(([127, 0, 0, 1], port));
            let gate = crate::gate::start((ip, settings.port).into(), upstream, config, token).map_err(|e| {
                StageError::msg(format!("the live view's TLS gate (processes.{name}.settings.host / port): {e}"))
            })?;
            port = gate.addr().port();
            Some(gate)
        }
    };
    if settings.insecure
        && gate.is_none()
        && !settings.host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
    {
        tracing::warn!(host = %settings.host, port,
                "insecure: the live view has no authentication or encryption, and anyone who reaches this address watches the run");
    }
    match &gate {
        None => tracing::info!(
            url = %format!("ws://{}:{port}", settings.host),
            "live view: in Foxglove, Open connection → Foxglove WebSocket → ws://<this host>:{port}"
        ),
        Some(_) => tracing::info!(
            url = %format!("wss://{}:{port}/?token=<token>", settings.host),
            "live view over TLS with a token: in Foxglove, Open connection → Foxglove WebSocket → \
             wss://<this host>:{port}/?token=<the token in token_file> (the CA, certs/ca.pem, trusted by the browser)"
        ),
    }
    Ok((server, gate, port))
}

impl Stage for ViewerStage {
    type Settings = ViewerSettings;

    fn open(ctx: &ProcessContext, settings: ViewerSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let context = Context::new();
        let mut not_shown = BTreeMap::new();
        let ns = &mut not_shown;
        let slam_pose = open(ns, services::SLAM_POSE, rt.input(services::SLAM_POSE));
        let buoy_fix = open(ns, services::BUOY_FIX, rt.input(services::BUOY_FIX));
        let fused_pose = open(ns, services::FUSION_POSE, rt.input(services::FUSION_POSE));
        let grid_pose = open(ns, services::GRID_SLAM_POSE3D, rt.input(services::GRID_SLAM_POSE3D));
        let cloud = open(ns, services::CLOUD, rt.input(services::CLOUD));
        let fusion_map = open(ns, services::FUSION_MAP, rt.input(services::FUSION_MAP));
        let slam_landmarks = open(ns, services::SLAM_LANDMARKS, rt.input(services::SLAM_LANDMARKS));
        let voxels = open(ns, services::MAP_VOXELS, rt.input(services::MAP_VOXELS));
        let grid = open(ns, services::GRID_SLAM_GRID, rt.input(services::GRID_SLAM_GRID));
        let traversability = open(ns, services::MAP_TRAVERSABILITY, rt.input(services::MAP_TRAVERSABILITY));
        let heartbeats = open(ns, services::HEARTBEAT, rt.input_with_qos(services::HEARTBEAT, &CONTROL_QOS));
        let commands = match &voxels {
            Some(_) => open(ns, services::COMMAND, rt.output::<ControlCommand, MsgHeader>(services::COMMAND)),
            None => None,
        };
        let path = |topic: &str| Path {
            poses: vec![],
            last_ns: 0,
            channel: context.channel_builder(topic).build(),
            dirty: false,
            thinned: 0,
        };
        let paths = BTreeMap::from([
            ("/slam/path", path("/slam/path")),
            ("/buoy/path", path("/buoy/path")),
            ("/fused/path", path("/fused/path")),
            ("/grid_slam/path", path("/grid_slam/path")),
            ("/ground_truth/path", path("/ground_truth/path")),
        ]);
        let fused_now = context.channel_builder("/fused/pose").build();
        let cloud_ch = context.channel_builder("/cloud").build();
        let landmarks_ch = context.channel_builder("/landmarks").build();
        let octree_ch = context.channel_builder("/octree").build();
        let grid_ch = context.channel_builder("/grid").build();
        let traversability_ch = context.channel_builder("/traversability").build();
        let processes_ch = context.channel_builder("/processes").build();
        let (server, gate, port) = start_server(&context, ctx, &settings)?;
        Ok(Self {
            cloud_every: Every::hz(settings.cloud_max_hz),
            landmarks_every: Every::hz(settings.map_max_hz),
            fused_landmarks: false,
            octree_every: Every::hz(settings.map_max_hz),
            grid_every: Every::hz(settings.map_max_hz),
            path_every: Every::hz(settings.path_max_hz),
            processes_every: Every::hz(1.0),
            settings,
            server: Some(server),
            port,
            gate,
            _context: context,
            slam_pose,
            buoy_fix,
            fused_pose,
            grid_pose,
            cloud,
            fusion_map,
            slam_landmarks,
            voxels,
            grid,
            traversability,
            heartbeats,
            commands,
            snapshot_asked: None,
            snapshots_asked: 0,
            not_shown,
            paths,
            truth: TruthTail {
                path: ctx.out_dir.join("ground_truth.tum"),
                offset: 0,
                partial: String::new(),
                head: vec![],
                bad_lines: 0,
            },
            fused_now,
            cloud_ch,
            landmarks_ch,
            octree_ch,
            grid_ch,
            traversability_ch,
            traversability_latest: None,
            traversability_watched: false,
            processes_ch,
            counts: BTreeMap::new(),
            octree: HashMap::new(),
            octree_full: false,
            octree_dirty: false,
            octree_stamp: 0,
            octree_waiting: 0,
            processes: BTreeMap::new(),
            clients_max: 0,
            sdk_outbox_full: pipeline_runtime::logging::count_events("foxglove", "outbox for client"),
            sdk_outbox_full_warned: 0,
            started: Instant::now(),
        })
    }

    fn end_after(&self) -> EndAfter {
        if self.settings.end_after.is_empty() {
            EndAfter::Itself // shows the run until it is stopped
        } else {
            EndAfter::All(self.settings.end_after.clone())
        }
    }

    fn tick(&self) -> Option<Duration> {
        // Paths and process states go out even when no message comes.
        Some(Duration::from_millis(200))
    }

    fn step(&mut self, _rt: &mut Runtime, _wake: Wake, _inputs_ended: bool) -> Result<Step, StageError> {
        if let Some(s) = &self.server {
            self.clients_max = self.clients_max.max(s.client_count());
        }
        let reports = self.sdk_outbox_full.load(std::sync::atomic::Ordering::Relaxed);
        if reports > self.sdk_outbox_full_warned {
            self.sdk_outbox_full_warned = reports;
            tracing::warn!(
                reports,
                client_backlog = self.settings.client_backlog,
                "a client reads slower than the view is sent: the Foxglove SDK dropped its oldest queued messages \
                 (it says so at most every 30 s, not how many); raise client_backlog or lower the *_max_hz rates"
            );
        }
        self.drain_poses()?;
        self.drain_cloud()?;
        self.drain_landmarks()?;
        self.drain_octree()?;
        self.drain_grid()?;
        self.drain_traversability()?;
        self.drain_processes()?;
        Ok(Step::Idle)
    }

    type Summary = ViewerPart;

    fn finish(&mut self, _rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        // What came last reaches the clients before the server closes, the final map above all
        // (the octree is otherwise sent at most `octree_max_hz`, and the run's last voxels may
        // be held back by that rate when the run ends).
        if let Err(e) = self.drain_octree() {
            tracing::warn!("the last voxels could not be read: {e}");
        }
        if self.octree_dirty && self.octree_ch.has_sinks() {
            self.octree_dirty = false;
            self.count("/octree").logged += 1;
            let m = fx::voxels(self.octree_stamp, self.octree.values());
            self.octree_ch.log(&m);
        }
        if let Some(s) = self.server.take() {
            // A client that stopped reading can hold the server's close up: wait a second at
            // most (the summary part must reach the supervisor before its stop timeout).
            let handle = s.stop();
            let (tx, rx) = std::sync::mpsc::channel();
            std::thread::spawn(move || {
                handle.wait_blocking();
                let _ = tx.send(());
            });
            if rx.recv_timeout(Duration::from_secs(1)).is_err() {
                tracing::warn!("a client did not close within 1 s; the viewer stops without waiting for it");
            }
        }
        Ok(ViewerPart {
            viewer: ViewerSummary {
                ending: format!("{ending:?}"),
                host: self.settings.host.clone(),
                insecure: self.settings.insecure,
                port: self.port,
                tls: self.gate.is_some(),
                gate: self.gate.as_ref().map(|g| g.counts().summary()),
                clients_max: self.clients_max,
                sdk_outbox_full_reports: self.sdk_outbox_full.load(std::sync::atomic::Ordering::Relaxed),
                channels: self.counts.iter().map(|(k, c)| (k.to_string(), *c)).collect(),
                not_shown: self.not_shown.clone(),
                path_poses_thinned: self.paths.iter().map(|(k, p)| (k.to_string(), p.thinned)).collect(),
                octree_deltas_before_a_full_set: self.octree_waiting,
                octree_snapshots_asked: self.snapshots_asked,
                ground_truth_bad_lines: self.truth.bad_lines,
                seconds: self.started.elapsed().as_secs_f64(),
            },
        })
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (0, 0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_path_thins_its_older_half_and_keeps_the_newest_poses() {
        let ctx = Context::new();
        let mut p =
            Path { poses: vec![], last_ns: 0, channel: ctx.channel_builder("/p").build(), dirty: false, thinned: 0 };
        for k in 0..1000u64 {
            p.push(k, pose_of([k as f64, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]), 100);
            assert!(p.poses.len() <= 100);
        }
        let xs: Vec<f64> = p.poses.iter().map(|q| q.position.unwrap().x).collect();
        assert_eq!(*xs.first().unwrap(), 0.0, "the start stays");
        assert_eq!(*xs.last().unwrap(), 999.0, "the newest pose is last");
        assert!(xs.windows(2).all(|w| w[0] < w[1]), "in order");
        assert_eq!(p.thinned as usize + p.poses.len(), 1000);
        assert_eq!(p.last_ns, 999);
    }
}

#[cfg(test)]
mod truth_tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn the_ground_truth_file_is_followed_as_it_grows_and_started_over_when_rewritten() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ground_truth.tum");
        let mut t = TruthTail { path: path.clone(), offset: 0, partial: String::new(), head: vec![], bad_lines: 0 };
        let mut reset = false;
        assert!(t.read_new(&mut reset).is_empty(), "no file yet");
        let mut f = std::fs::File::create(&path).unwrap();
        write!(f, "1.0 1 2 3 0 0 0 1\n2.5 4 5 6 0 0 0 1\n3.0 7 8").unwrap();
        let got = t.read_new(&mut reset);
        assert_eq!(got.iter().map(|(ns, _)| *ns).collect::<Vec<_>>(), [1_000_000_000, 2_500_000_000]);
        assert_eq!(got[1].1.position.unwrap().y, 5.0);
        write!(f, " 9 0 0 0 1\nnot a pose\n").unwrap();
        let got = t.read_new(&mut reset);
        assert_eq!(got.len(), 1, "the line completed");
        assert_eq!(got[0].1.position.unwrap().z, 9.0);
        assert_eq!(t.bad_lines, 1);
        assert!(!reset);
        // Written anew (a restarted source, or this run's replacing an earlier run's file).
        std::fs::write(&path, "5.0 0 0 0 0 0 0 1\n6.0 1 1 1 0 0 0 1\n7.0 2 2 2 0 0 0 1\n8.0 3 3 3 0 0 0 1\n").unwrap();
        let got = t.read_new(&mut reset);
        assert!(reset);
        assert_eq!(got.len(), 4);
        assert_eq!(got[0].0, 5_000_000_000);
    }
}

//! The Zenoh bridge between pipelines, each under its own supervisor with its own iceoryx2
//! prefix, root and output directory:
//! - a robot (a short simulated mission through `ingest`, a recorder, a bridge sending odometry,
//!   depth and buoy ranges) and a base station (a bridge receiving them, a recorder) on loopback:
//!   the base station's recording holds every message the robot's holds, payload for payload with
//!   the same `origin_ns` (publish_ns stamped anew); the robot's end of stream ends the base
//!   station's pipeline; messages with another wire signature or a wrong length, put on the
//!   robot's keys by a stranger, are counted and not published;
//! - a robot with the estimators and a mapper in one network namespace, a base station with a
//!   mapper in another, joined by a veth pair (loopback where namespaces are not permitted: the
//!   test says so), the link cut for 3 s during the run (lease 20 s): the clouds' and the fused
//!   poses' digests are equal on both sides, and the base station's map, built at the bridged fused
//!   poses, agrees with the robot's map at the simulator's true poses;
//! - two robots with their estimators and one base station: each robot's buoy fixes on their own
//!   local service, both robots' clouds in one map, and a mapper per robot (its ports renamed by
//!   `remap`, its files in its own `out_dir`) at that robot's bridged fused poses, whose map agrees
//!   with the robot's own at the simulator's true poses;
//! - the base station's bridge killed mid-run: restarted by its supervisor, it reconnects, gets
//!   the end of stream and counts what was lost meanwhile; the robot's pipeline goes on.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use pipeline_tests::TestRun;
use zenoh::Wait;

const LONG: Duration = Duration::from_secs(240);
const SERVICES: [&str; 3] = ["pipeline/sensors/odometry", "pipeline/sensors/depth", "pipeline/sensors/buoy_ranges"];

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").expect("bind").local_addr().expect("addr").port()
}

/// The bridge's log lines above INFO (for a failure's message).
fn link_lines(run: &TestRun) -> String {
    run.log().lines().filter(|l| l.contains("[link]") && !l.contains(" INFO ")).collect::<Vec<_>>().join("\n")
}

/// Certificates made by `supervisor certs` (a CA and one per name) in a directory of the test's
/// own, removed on drop.
struct Certs(tempfile::TempDir);

impl Certs {
    fn new(names: &[&str], sans: &[&str]) -> Self {
        let dir = tempfile::tempdir().expect("tmp");
        let mut cmd = std::process::Command::new(pipeline_tests::bin("supervisor"));
        cmd.arg("certs").arg("--dir").arg(dir.path()).args(["--days", "1"]);
        for n in names {
            cmd.args(["--name", n]);
        }
        for s in sans {
            cmd.args(["--san", s]);
        }
        let out = cmd.output().expect("supervisor certs runs");
        assert!(out.status.success(), "supervisor certs: {}", String::from_utf8_lossy(&out.stderr));
        Self(dir)
    }

    /// `name`'s `tls` inline table (`extra`: more keys, e.g. `, receivers = ["base"]`).
    fn tls(&self, name: &str, extra: &str) -> String {
        let d = self.0.path();
        format!(
            "tls = {{ ca_certificate = {:?}, certificate = {:?}, private_key = {:?}{extra} }}",
            d.join("ca.pem"),
            d.join(format!("{name}.pem")),
            d.join(format!("{name}.key"))
        )
    }
}

/// Messages of `topic` in an MCAP file: (origin_ns, publish_ns, user header after `MsgHeader` +
/// payload).
fn messages(path: &Path, topic: &str) -> Vec<(u64, u64, Vec<u8>)> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    mcap::MessageStream::new(&bytes)
        .expect("MCAP")
        .map(|m| m.expect("message"))
        .filter(|m| m.channel.topic == topic)
        .map(|m| {
            let u = |i: usize| u64::from_le_bytes(m.data[i..i + 8].try_into().unwrap());
            (u(16), u(24), m.data[32..].to_vec())
        })
        .collect()
}

/// What reached the base station per service: the messages the robot sent, and their user
/// headers after `MsgHeader` and payloads as the base station's recorder wrote them.
type Reached = BTreeMap<&'static str, (u64, Vec<Vec<u8>>)>;

/// A robot streams its sensors to a base station over plain TCP (`certs` `None`: `insecure`; a
/// stranger's two bad messages are refused) or mutual TLS; everything arrives byte for byte.
fn stream_to_base(certs: Option<&Certs>) -> Reached {
    let port = free_port();
    let (proto, base_link, robot_link) = match certs {
        None => ("tcp", "insecure = true".to_string(), "insecure = true".to_string()),
        Some(c) => ("tls", c.tls("base", ""), c.tls("r1", "")),
    };
    let services = SERVICES.iter().map(|s| format!("\"{s}\"")).collect::<Vec<_>>().join(", ");
    let ins = SERVICES.iter().map(|s| format!("{{ from = \"r1\", service = \"{s}\" }}")).collect::<Vec<_>>().join(", ");
    let outs = SERVICES.iter().map(|s| format!("{{ service = \"{s}\" }}")).collect::<Vec<_>>().join(", ");

    let mut base = TestRun::new("brbase");
    let base_cfg = base.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"rec\"]\nduration_s = 200",
        &format!(
            r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
services = [{services}]
end_after = ["link"]
send_end_of_stream = true

[processes.link]
kind = "bridge"
after = ["rec"]
[processes.link.settings]
zenoh = {{ listen = ["{proto}/127.0.0.1:{port}"], {base_link} }}
accept = {{ max_rate_hz = 0 }}
in = [{ins}]
"#
        ),
    );
    base.start_supervisor(&base_cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));

    // A stranger puts a message with another wire signature and one of a wrong length on the
    // robot's odometry key: counted, not published. (Over TLS it cannot connect at all.)
    if certs.is_none() {
        let mut c = zenoh::Config::default();
        c.insert_json5("mode", "\"peer\"").unwrap();
        c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]")).unwrap();
        c.insert_json5("scouting/multicast/enabled", "false").unwrap();
        let s = zenoh::open(c).wait().expect("a stranger's session");
        let k = "slam/r1/pipeline/sensors/odometry";
        let p = s.declare_publisher(k).wait().expect("publisher");
        let t0 = std::time::Instant::now();
        while !p.matching_status().wait().unwrap().matching() {
            assert!(t0.elapsed() < Duration::from_secs(30), "the base station's bridge never subscribed");
            std::thread::sleep(Duration::from_millis(20));
        }
        let right = bridge_stage::signature(wire_topics::topic(SERVICES[0]).unwrap());
        p.put(vec![0u8; 32 + 168]).attachment("slam-wire;v=0;h=Old;p=Old;slice=false").wait().unwrap();
        p.put(vec![0u8; 32 + 7]).attachment(right.as_str()).wait().unwrap();
        s.close().wait().unwrap();
    }

    let mut robot = TestRun::new("brrobot");
    let robot_cfg = robot.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"rec\", \"link\"]\nduration_s = 200",
        &format!(
            r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
services = [{services}]
end_after = ["ingest"]
send_end_of_stream = true

[processes.link]
kind = "bridge"
[processes.link.settings]
robot = "r1"
end_after = ["ingest"]
zenoh = {{ connect = ["{proto}/127.0.0.1:{port}"], {robot_link} }}
out = [{outs}]

[processes.ingest]
kind = "ingest"
after = ["rec", "link"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 40.0
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#
        ),
    );
    robot.start_supervisor(&robot_cfg, &[]);
    let rs = robot.wait_supervisor(LONG).expect("the robot's run ends");
    let bs = base.wait_supervisor(LONG).expect("the base station's run ends (the robot's end of stream)");
    assert_eq!(rs.code(), Some(0), "robot:\n{}", robot.log());
    assert_eq!(bs.code(), Some(0), "base:\n{}", base.log());
    for run in [&robot, &base] {
        assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
    }
    let (r, b) = (robot.summary(), base.summary());
    crate::summary_schema::assert_declared(&r);
    crate::summary_schema::assert_declared(&b);
    crate::summary_schema::assert_valid_by_jsonschema(&robot.out_dir().join("summary.json"));
    crate::summary_schema::assert_valid_by_jsonschema(&base.out_dir().join("summary.json"));
    use crate::summary_schema::part;
    let (rp, bp): (bridge_stage::summary::BridgePart, bridge_stage::summary::BridgePart) = (part(&r), part(&b));
    let (rb, bb) = (&rp.bridge, &bp.bridge);
    let recorder: recorder_stage::summary::RecorderPart = part(&b);
    // Plain TCP only because the config says so, and the summary says it too.
    let mode = if certs.is_some() { "mutual_tls" } else { "insecure" };
    assert_eq!(rb.security.mode, mode, "{rb:?}");
    assert_eq!(bb.security.mode, mode, "{bb:?}");
    eprintln!("robot bridge {:#}\nbase bridge {:#}", r["bridge"], b["bridge"]);
    assert_eq!(rb.end_acknowledged, Some(true), "{rb:?}");
    assert_eq!(bb.ends_received, ["r1"], "{bb:?}");
    // `clock = "auto"`: the robot's bridge answered from this machine: origin_ns kept as is.
    let clock = &bb.clock["r1"];
    assert_eq!((clock.same_machine, clock.shifted), (Some(true), false), "{clock:?}");
    for s in SERVICES {
        let out = &rb.out[s].counts;
        let inn = &bb.inbound[s].counts;
        let sent = out.sent;
        assert!(sent > 5, "{s}: {out:?}");
        assert_eq!(out.received, sent, "{s}: {out:?}");
        let extra = if s == SERVICES[0] && certs.is_none() { 2 } else { 0 }; // the stranger's two
        assert_eq!(inn.received, sent + extra, "{s}: {inn:?}");
        assert_eq!(inn.published, sent, "{s}: {inn:?}");
        assert_eq!(bb.inbound[s].lost_on_the_way, Some(0), "{s}: {bb:?}");
        assert_eq!(inn.undelivered, 0, "{s}: {inn:?}");
        assert_eq!(recorder.recorder.messages.get(s), Some(&sent), "{s}: {:?}", recorder.recorder);
    }
    let odo = &bb.inbound[SERVICES[0]].counts;
    if certs.is_none() {
        assert_eq!((odo.wrong_type, odo.bad_length), (1, 1), "{odo:?}");
        assert!(base.log().contains("refused a message with another wire signature"), "warned");
    }

    // Payload for payload, with the same origin; published anew (later) on the base station.
    let ingest: ingest_stage::summary::IngestPart = part(&r);
    let ingest = &ingest.ingest.messages;
    let mut compared = BTreeMap::new();
    let mut reached = Reached::new();
    for (s, published) in SERVICES.iter().zip([ingest.odometry, ingest.depth, ingest.buoy_ranges]) {
        let here = messages(&robot.out_dir().join("recording.mcap"), s);
        let there = messages(&base.out_dir().join("recording.mcap"), s);
        assert_eq!(here.len() as u64, published, "{s}: the robot's recorder got everything");
        assert_eq!(here.len(), there.len(), "{s}");
        for (a, b) in here.iter().zip(&there) {
            assert_eq!(a.2, b.2, "{s}: payload");
            assert_eq!(a.0, b.0, "{s}: origin_ns kept");
            assert!(b.1 >= a.1, "{s}: published anew on the base station, after the robot");
        }
        compared.insert(*s, here.len());
        let sent = rb.out[*s].counts.sent;
        reached.insert(*s, (sent, there.into_iter().map(|m| m.2).collect()));
    }
    eprintln!("compared {compared:?}");
    reached
}

#[test]
fn a_robots_streams_reach_a_base_station_byte_for_byte_and_its_end_of_stream_ends_the_base() {
    let plain = stream_to_base(None);
    // The same mission over mutual TLS: the same messages, in the same order, to the byte.
    let certs = Certs::new(&["base", "r1"], &[]);
    let secure = stream_to_base(Some(&certs));
    for s in SERVICES {
        let (a, b) = (&plain[s], &secure[s]);
        assert_eq!(a.0, b.0, "{s}: sent over plain TCP and over TLS");
        assert!(a.1 == b.1, "{s}: the base station's messages differ between plain TCP and TLS");
    }
}

/// Two network namespaces joined by a veth pair (deleted on drop), when this user may make them.
struct NetPair {
    names: [String; 2],
    veth: [String; 2],
    addrs: [String; 2],
}

fn ip(args: &[&str]) -> bool {
    std::process::Command::new("ip")
        .args(args)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

impl NetPair {
    fn new() -> Option<Self> {
        // SAFETY: geteuid has no preconditions and cannot fail.
        if unsafe { libc::geteuid() } != 0 {
            return None;
        }
        let pid = std::process::id();
        let tag = format!("slb{}", pid % 100_000);
        let pair = Self {
            names: [format!("{tag}r"), format!("{tag}b")],
            veth: [format!("{tag}vr"), format!("{tag}vb")],
            addrs: [format!("10.213.{}.1", pid % 250), format!("10.213.{}.2", pid % 250)],
        };
        if !ip(&["netns", "add", &pair.names[0]]) {
            return None;
        }
        let ok = ip(&["netns", "add", &pair.names[1]])
            && ip(&["link", "add", &pair.veth[0], "type", "veth", "peer", "name", &pair.veth[1]])
            && (0..2).all(|i| {
                ip(&["link", "set", &pair.veth[i], "netns", &pair.names[i]])
                    && ip(&[
                        "-n",
                        &pair.names[i],
                        "addr",
                        "add",
                        &format!("{}/24", pair.addrs[i]),
                        "dev",
                        &pair.veth[i],
                    ])
                    && ip(&["-n", &pair.names[i], "link", "set", &pair.veth[i], "up"])
                    && ip(&["-n", &pair.names[i], "link", "set", "lo", "up"])
            });
        ok.then_some(pair)
    }

    fn wrapper(&self, i: usize) -> Vec<String> {
        vec!["ip".into(), "netns".into(), "exec".into(), self.names[i].clone()]
    }

    fn set_link(&self, up: bool) {
        assert!(ip(&["-n", &self.names[0], "link", "set", &self.veth[0], if up { "up" } else { "down" }]));
    }
}

impl Drop for NetPair {
    fn drop(&mut self) {
        for n in &self.names {
            ip(&["netns", "del", n]);
        }
    }
}

const ESTIMATORS: &str = r#"
[processes.buoy]
kind = "buoy_ekf"
after = ["sync"]
[processes.buoy.settings.ekf]
mode = "spatial"
buoys = [
    { id = 0, position_m = [-10.0, -10.0, 0.0] },
    { id = 1, position_m = [130.0, -10.0, 0.0] },
    { id = 2, position_m = [130.0, 90.0, 0.0] },
    { id = 3, position_m = [-10.0, 90.0, 0.0] },
    { id = 4, position_m = [60.0, 100.0, 0.0] },
]

[processes.slam]
kind = "fastslam"
after = ["sync"]
[processes.slam.settings.filter]
particles = 30

[processes.sync]
kind = "synchronizer"
after = ["fusion"]
[processes.sync.settings]
end_after = ["slam", "buoy"]

[processes.fusion]
kind = "fusion"
[processes.fusion.settings]
slam_process = "slam"
end_after = ["sync", "buoy", "slam"]
"#;

#[test]
fn a_robot_in_one_network_namespace_feeds_a_base_stations_map_in_another_through_a_link_cut() {
    let _heavy = pipeline_tests::heavy();
    let net = NetPair::new();
    let (robot_wrap, base_wrap, base_addr) = match &net {
        Some(n) => (n.wrapper(0), n.wrapper(1), format!("{}:7447", n.addrs[1])),
        None => {
            eprintln!(
                "network namespaces are not permitted here (not root, or `ip netns add` failed): both \
                 pipelines run on loopback, and the link cut is skipped"
            );
            (vec![], vec![], format!("127.0.0.1:{}", free_port()))
        }
    };
    // Mutual TLS: the base station's certificate names the address the robot dials.
    let certs = Certs::new(&["base", "auv"], &[base_addr.split(':').next().expect("ip")]);
    let (tls_base, tls_auv) = (certs.tls("base", ""), certs.tls("auv", ", receivers = [\"base\"]"));
    let mut base = TestRun::new("brmapbase");
    let base_cfg = base.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"map\", \"link\"]\nduration_s = 300",
        &format!(
            r#"
[processes.map]
kind = "octree_mapper"
restart = "never"
[processes.map.settings]
pose_source = "fused"
end_after = ["link"]

[processes.link]
kind = "bridge"
after = ["map"]
restart = "never"
[processes.link.settings]
zenoh = {{ listen = ["tls/{base_addr}"], lease_s = 20.0, {tls_base} }}
accept = {{ max_rate_hz = 0 }}
in = [{{ from = "auv", service = "pipeline/sensors/cloud" }}, {{ from = "auv", service = "pipeline/fusion/pose" }}]
"#
        ),
    );
    base.start_supervisor_in(&base_wrap, &base_cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));

    let mut robot = TestRun::new("brmaprobot");
    let robot_cfg = robot.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"map\", \"link\", \"fusion\"]\nduration_s = 300",
        &format!(
            r#"
{ESTIMATORS}
[processes.map]
kind = "octree_mapper"
restart = "never"
[processes.map.settings]
pose_source = "cloud"
end_after = ["ingest"]

[processes.link]
kind = "bridge"
restart = "never"
[processes.link.settings]
robot = "auv"
end_after = ["ingest", "fusion"]
zenoh = {{ connect = ["tls/{base_addr}"], lease_s = 20.0, {tls_auv} }}
out = [{{ service = "pipeline/sensors/cloud" }}, {{ service = "pipeline/fusion/pose" }}]

[processes.ingest]
kind = "ingest"
after = ["map", "link", "slam", "buoy"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
progress_interval_s = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 30.0
[processes.ingest.settings.sim.sensors.depth_camera]
width_px = 48
height_px = 36
"#
        ),
    );
    robot.start_supervisor_in(&robot_wrap, &robot_cfg, &[]);
    let mut cut_during_run = false;
    if let Some(n) = &net {
        robot.wait_for_log("process=ingest", 1, Duration::from_secs(120));
        std::thread::sleep(Duration::from_millis(500));
        n.set_link(false);
        // 3 s, well under half of the 20 s lease both bridges announce here (zenoh.lease_s): an
        // outage must be under about half the lease to lose nothing (TCP's back-off can make the
        // silence twice as long); with the default 10 s a 4 s cut on the loaded 2-core CI machine
        // once outlasted the lease (the link closed, 2 clouds lost and counted).
        std::thread::sleep(Duration::from_secs(3));
        cut_during_run = robot.wait_supervisor(Duration::ZERO).is_none();
        n.set_link(true);
    }
    let rs = robot.wait_supervisor(LONG).expect("the robot's run ends");
    let bs = base.wait_supervisor(LONG).expect("the base station's run ends");
    assert_eq!(rs.code(), Some(0), "robot:\n{}", robot.log());
    assert_eq!(bs.code(), Some(0), "base:\n{}", base.log());
    for run in [&robot, &base] {
        assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
    }
    let (r, b) = (robot.summary(), base.summary());
    use crate::summary_schema::part;
    let (rp, bp): (bridge_stage::summary::BridgePart, bridge_stage::summary::BridgePart) = (part(&r), part(&b));
    let (rb, bb) = (&rp.bridge, &bp.bridge);
    let cert = |b: &bridge_stage::summary::BridgeSummary| {
        b.security.tls.as_ref().and_then(|t| t.certificate.as_ref()).map(|c| c.common_name.clone())
    };
    assert_eq!(bb.security.mode, "mutual_tls", "{bb:?}");
    assert_eq!(cert(bb).as_deref(), Some("base"), "{bb:?}");
    assert_eq!(cert(rb).as_deref(), Some("auv"), "{rb:?}");
    eprintln!(
        "link cut for 3 s during the run: {cut_during_run}\nrobot bridge {:#}\nbase bridge {:#}\nrobot map {:#}\nbase map {:#}",
        r["bridge"], b["bridge"], r["octree_mapper"]["counters"], b["octree_mapper"]["counters"]
    );
    assert_eq!(rb.end_acknowledged, Some(true), "{rb:?}");
    for s in ["pipeline/sensors/cloud", "pipeline/fusion/pose"] {
        let (out, inn) = (&rb.out[s].counts, &bb.inbound[s].counts);
        assert!(out.sent > 3, "{s}: {out:?}");
        assert_eq!(out.missed_locally, 0, "{s}: {out:?}");
        assert_eq!(
            inn.published,
            out.sent,
            "{s}: {inn:?} against {out:?}\nrobot's link:\n{}\nbase's link:\n{}",
            link_lines(&robot),
            link_lines(&base)
        );
        assert_eq!(inn.digest, out.digest, "{s}: the same bytes arrived, in order");
        assert_eq!(bb.inbound[s].lost_on_the_way, Some(0), "{s}");
    }
    // The robot maps at the simulator's true poses (the clouds' own); the base station at the
    // bridged fused poses: every cloud from the first fused pose on is placed, and its map agrees
    // with the true-pose map leaf by leaf (as the indoor test and octree_bench compare maps).
    let ingest: ingest_stage::summary::IngestPart = part(&r);
    let clouds = ingest.ingest.messages.cloud;
    let (robot_map, base_map): (
        octree_mapper_stage::summary::OctreeMapperPart,
        octree_mapper_stage::summary::OctreeMapperPart,
    ) = (part(&r), part(&b));
    let c = &robot_map.octree_mapper.counters;
    assert_eq!(c.clouds_inserted, clouds, "robot: every cloud in the map: {c:?}");
    let c = &base_map.octree_mapper.counters;
    let inserted = c.clouds_inserted;
    assert_eq!(
        inserted + c.clouds_dropped_no_pose + c.clouds_dropped_behind + c.clouds_missed,
        clouds,
        "base: every cloud accounted for: {c:?}"
    );
    assert!(inserted as f64 >= 0.8 * clouds as f64, "base: {inserted} of {clouds} clouds placed at fused poses: {c:?}");
    let fusion: fusion_stage::summary::FusionPart = part(&r);
    let fused_ate = fusion.ate_m.as_ref().and_then(|a| a.fused).expect("the robot's fused ATE");
    let (recall, precision, why) =
        maps_agree(&robot.out_dir().join("map.bt"), &base.out_dir().join("map.bt"), fused_ate, &robot.out_dir());
    eprintln!("{why}");
    // The fused path's error on this short mission: 0.26 m (2026-12-05). Within 3 voxels the
    // map's agreement moves with the fused path's details, not its RMS error: recall 0.978 and
    // precision 0.953 before FastSLAM's speed work, 0.894-0.902 and 0.819-0.833 after it at the
    // same fused ATE (0.259 and 0.261 m); within 4 voxels 0.968 and 0.941.
    assert!(fused_ate <= 0.4, "{why}");
    assert!(recall >= 0.9 && precision >= 0.9, "{why}");
}

/// A map built at fused poses (`fused`) against one built at the true poses (`truth`), both
/// map.bt files: the recall (the true map's occupied leaves with an occupied leaf of the other
/// within k voxels), the precision (the other way round), k following the fused path's RMS error
/// `fused_ate` m, and a line saying all of it. Asserts that at least 60 % of the true map's free
/// leaves are free in the other.
/// RMS of the rotation angle between the fused live poses and the truth (nearest stamps) of a
/// robot's run, rad.
fn fused_attitude_rms_rad(out: &Path) -> f64 {
    let read = |f: &str| geometry::tum::read_tum(&out.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
    let (fused, truth) = (read("fused_live.tum"), read("ground_truth.tum"));
    let errs: Vec<f64> = fused
        .iter()
        .filter_map(|(t, p)| geometry::trajectory::nearest(&truth, *t).map(|q| p.rotation.angle_to(&q.rotation)))
        .collect();
    (errs.iter().map(|e| e * e).sum::<f64>() / errs.len().max(1) as f64).sqrt()
}

fn maps_agree(truth: &Path, fused: &Path, fused_ate: f64, robot_out: &Path) -> (f64, f64, String) {
    let truth = octree::OcTree::read_binary_file(truth).expect("the true-pose map.bt");
    let fused = octree::OcTree::read_binary_file(fused).expect("the fused-pose map.bt");
    let (mut occ_n, mut occ_ok, mut free_n, mut free_ok) = (0usize, 0usize, 0usize, 0usize);
    for l in truth.leaves() {
        let theirs = fused.is_occupied(truth.key_to_coord(l.key));
        if truth.is_occupied_log_odds(l.log_odds) {
            occ_n += 1;
            occ_ok += usize::from(theirs == Some(true));
        } else {
            free_n += 1;
            free_ok += usize::from(theirs == Some(false));
        }
    }
    let (occ, free) = (occ_ok as f64 / occ_n as f64, free_ok as f64 / free_n as f64);
    let near = |of: &octree::OcTree, within: &octree::OcTree, k: i32| {
        let res = of.resolution();
        let (mut n, mut ok) = (0usize, 0usize);
        for l in of.leaves().filter(|l| of.is_occupied_log_odds(l.log_odds)) {
            let c = of.key_to_coord(l.key);
            n += 1;
            ok += usize::from((-k..=k).any(|dx| {
                (-k..=k).any(|dy| {
                    (-k..=k).any(|dz| {
                        let p = [c[0] + dx as f64 * res, c[1] + dy as f64 * res, c[2] + dz as f64 * res];
                        within.is_occupied(p) == Some(true)
                    })
                })
            }));
        }
        ok as f64 / n.max(1) as f64
    };
    // Clouds placed at poses with an RMS error e land within about 1.5·e of the true surfaces:
    // the tolerance follows the fused poses' own error where they place the points, the position
    // error and the attitude error at half the depth camera's 14 m range (`max_range_m`). The
    // position's alone undercounts it: with the fused path at 0.26 m (2026-12-05) that gave 4
    // voxels of 0.1 m; at 0.14-0.18 m (2026-12-07, after the buoy EKF's attitude fix) 3, and
    // recall 0.91, precision 0.84-0.86, while the live attitude, 3.5-4.7° RMS on these short
    // missions, puts points 7 m out 0.4-0.6 m off (6 voxels: recall and precision 0.99-1.0).
    let attitude_rad = fused_attitude_rms_rad(robot_out);
    let placement_m = fused_ate.hypot(7.0 * attitude_rad);
    let k = ((1.5 * placement_m / truth.resolution()).ceil() as i32).clamp(2, 6);
    let (recall, precision) = (near(&truth, &fused, k), near(&fused, &truth, k));
    let why = format!(
        "map at the bridged fused poses against the robot's at the true poses: {:.1} % of {occ_n} occupied and \
         {:.1} % of {free_n} free leaves agree leaf by leaf; within {k} voxels, recall {recall:.3}, precision \
         {precision:.3}; the robot's fused ATE {fused_ate:.3} m, attitude {:.2}° RMS",
        100.0 * occ,
        100.0 * free,
        attitude_rad.to_degrees()
    );
    assert!(free >= 0.6, "{why}");
    (recall, precision, why)
}

/// A base station's mapper for robot `name` at its bridged fused poses: its ports renamed to the
/// robot's (`remap`), its files in a directory of its own (`out_dir`).
fn robot_mapper(name: &str) -> String {
    format!(
        r#"
[processes.map_{name}]
kind = "octree_mapper"
restart = "never"
out_dir = "{name}"
[processes.map_{name}.remap]
"pipeline/sensors/cloud" = "{name}/pipeline/sensors/cloud"
"pipeline/fusion/pose" = "{name}/pipeline/fusion/pose"
"pipeline/map/stats" = "{name}/pipeline/map/stats"
"pipeline/map/voxels" = "{name}/pipeline/map/voxels"
"pipeline/map/traversability" = "{name}/pipeline/map/traversability"
[processes.map_{name}.settings]
pose_source = "fused"
end_after = ["link"]
"#
    )
}

#[test]
fn two_robots_feed_one_base_station_which_maps_each_at_its_own_fused_poses() {
    let _heavy = pipeline_tests::heavy();
    let port = free_port();
    let certs = Certs::new(&["base", "r1", "r2"], &[]);
    let tls_base = certs.tls("base", "");
    let mut base = TestRun::new("br2base");
    let base_cfg = base.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"map\", \"map_r1\", \"map_r2\", \"link\"]\nduration_s = 300",
        &format!(
            r#"
[processes.map]
kind = "octree_mapper"
restart = "never"
[processes.map.settings]
pose_source = "cloud"
end_after = ["link"]
{}{}
[processes.link]
kind = "bridge"
after = ["map", "map_r1", "map_r2"]
restart = "never"
[processes.link.settings]
zenoh = {{ listen = ["tls/127.0.0.1:{port}"], {tls_base} }}
accept = {{ max_rate_hz = 0 }}
clock = "measure"
in = [
    {{ from = "r1", service = "pipeline/buoy/fix", local = "r1/pipeline/buoy/fix" }},
    {{ from = "r2", service = "pipeline/buoy/fix", local = "r2/pipeline/buoy/fix" }},
    {{ from = "r1", service = "pipeline/sensors/cloud" }},
    {{ from = "r2", service = "pipeline/sensors/cloud" }},
    {{ from = "r1", service = "pipeline/sensors/cloud", local = "r1/pipeline/sensors/cloud" }},
    {{ from = "r2", service = "pipeline/sensors/cloud", local = "r2/pipeline/sensors/cloud" }},
    {{ from = "r1", service = "pipeline/fusion/pose", local = "r1/pipeline/fusion/pose" }},
    {{ from = "r2", service = "pipeline/fusion/pose", local = "r2/pipeline/fusion/pose" }},
]
"#,
            robot_mapper("r1"),
            robot_mapper("r2")
        ),
    );
    base.start_supervisor(&base_cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));
    let robot = |name: &str, seed: u32| {
        let tls_robot = certs.tls(name, "");
        let mut run = TestRun::new(&format!("br2{name}"));
        let cfg = run.write_config(
            "end = \"end_of_stream\"\nend_of_stream_from = [\"map\", \"link\", \"fusion\"]\nduration_s = 300",
            &format!(
                r#"
{ESTIMATORS}
[processes.map]
kind = "octree_mapper"
restart = "never"
[processes.map.settings]
pose_source = "cloud"
end_after = ["ingest"]

[processes.link]
kind = "bridge"
restart = "never"
[processes.link.settings]
robot = "{name}"
end_after = ["ingest", "fusion"]
zenoh = {{ connect = ["tls/127.0.0.1:{port}"], {tls_robot} }}
out = [{{ service = "pipeline/buoy/fix" }}, {{ service = "pipeline/sensors/cloud" }}, {{ service = "pipeline/fusion/pose" }}]

[processes.ingest]
kind = "ingest"
after = ["map", "link", "slam", "buoy"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
progress_interval_s = 0.0
[processes.ingest.settings.sim]
seed = {seed}
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 20.0
[processes.ingest.settings.sim.sensors.depth_camera]
width_px = 32
height_px = 24
"#
            ),
        );
        run.start_supervisor(&cfg, &[]);
        run
    };
    let mut robots = [robot("r1", 1), robot("r2", 2)];
    for r in &mut robots {
        let st = r.wait_supervisor(LONG).expect("a robot's run ends");
        assert_eq!(st.code(), Some(0), "{}", r.log());
    }
    let bs = base.wait_supervisor(LONG).expect("the base station ends after both robots' ends of stream");
    assert_eq!(bs.code(), Some(0), "base:\n{}", base.log());
    let b = base.summary();
    use crate::summary_schema::part;
    let bp: bridge_stage::summary::BridgePart = part(&b);
    let bb = &bp.bridge;
    eprintln!("base bridge {:#}\nbase map {:#}", b["bridge"], b["octree_mapper"]["counters"]);
    assert_eq!(bb.ends_received, ["r1", "r2"], "{bb:?}");
    let mut clouds = 0;
    let mut digests = vec![];
    for (name, run) in ["r1", "r2"].iter().zip(&robots) {
        let r = run.summary();
        let rp: bridge_stage::summary::BridgePart = part(&r);
        let out = &rp.bridge.out;
        let fix = &bb.inbound[&format!("{name}/pipeline/buoy/fix")].counts;
        let sent_fix = &out["pipeline/buoy/fix"].counts;
        assert!(sent_fix.sent > 3, "{out:?}");
        assert_eq!(
            fix.published,
            sent_fix.sent,
            "{name}: {fix:?}\nits link:\n{}\nthe base's link:\n{}",
            link_lines(run),
            link_lines(&base)
        );
        assert_eq!(fix.digest, sent_fix.digest, "{name}: its own fixes, apart");
        digests.push(fix.digest);
        let sent_cloud = &out["pipeline/sensors/cloud"].counts;
        for route in [format!("{name}:pipeline/sensors/cloud"), format!("{name}/pipeline/sensors/cloud")] {
            let cloud = &bb.inbound[&route].counts;
            assert_eq!(cloud.published, sent_cloud.sent, "{route}: {cloud:?}");
            assert_eq!(cloud.digest, sent_cloud.digest, "{route}");
        }
        let (pose, sent_pose) =
            (&bb.inbound[&format!("{name}/pipeline/fusion/pose")].counts, &out["pipeline/fusion/pose"].counts);
        assert!(sent_pose.sent > 3, "{name}: {sent_pose:?}");
        assert_eq!((pose.published, pose.digest), (sent_pose.sent, sent_pose.digest), "{name}: {pose:?}");
        let ingest: ingest_stage::summary::IngestPart = part(&r);
        let robot_clouds = ingest.ingest.messages.cloud;
        clouds += robot_clouds;
        // `clock = "measure"` on one machine: the true offset is 0, so the estimate must lie
        // within half its round trip (the remote stamp falls between the query and the answer).
        let clock = &bb.clock[*name];
        assert!(clock.answered > 0, "{name}: {clock:?}");
        assert_eq!(clock.same_machine, Some(true), "{name}: {clock:?}");
        let (off, rtt) = (clock.offset_ns.expect("an offset"), clock.rtt_ns.expect("a round trip") as i64);
        assert!(off.abs() <= rtt / 2 + 1, "{name}: offset within the round trip's bound: {clock:?}");
        assert!(rtt < 1_000_000_000, "{name}: {clock:?}");
        assert!(clock.shifted, "{name}: measure shifts even on one machine: {clock:?}");

        // The base station's mapper of this robot, at its bridged fused poses: its part under
        // `instances`, its map in its own directory, compared with the robot's own map at the
        // simulator's true poses.
        let own = &b["instances"][format!("map_{name}")];
        let own: octree_mapper_stage::summary::OctreeMapperPart =
            serde_json::from_value(own.clone()).unwrap_or_else(|e| panic!("instances.map_{name}: {e}: {own:#}"));
        let c = &own.octree_mapper.counters;
        assert_eq!(
            c.clouds_inserted + c.clouds_dropped_no_pose + c.clouds_dropped_behind + c.clouds_missed,
            robot_clouds,
            "map_{name}: every cloud of {name} accounted for, none of the other's: {c:?}"
        );
        assert!(c.clouds_inserted as f64 >= 0.8 * robot_clouds as f64, "map_{name}: {c:?}");
        let fusion: fusion_stage::summary::FusionPart = part(&r);
        let fused_ate = fusion.ate_m.as_ref().and_then(|a| a.fused).expect("the robot's fused ATE");
        let (recall, precision, why) = maps_agree(
            &run.out_dir().join("map.bt"),
            &base.out_dir().join(name).join("map.bt"),
            fused_ate,
            &run.out_dir(),
        );
        eprintln!("{name}: {why}");
        assert!(fused_ate <= 0.4, "{name}: {why}");
        assert!(recall >= 0.9 && precision >= 0.9, "{name}: {why}");
    }
    assert_ne!(digests[0], digests[1], "two robots, two different fix streams");
    let map: octree_mapper_stage::summary::OctreeMapperPart = part(&b);
    let c = &map.octree_mapper.counters;
    assert_eq!(c.clouds_inserted, clouds, "both robots' clouds in one map: {c:?}");
    assert_eq!(base.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn a_base_station_bridge_killed_mid_run_is_restarted_reconnects_and_counts_what_it_lost() {
    let _heavy = pipeline_tests::heavy();
    let port = free_port();
    let certs = Certs::new(&["base", "r1"], &[]);
    let (tls_base, tls_robot) = (certs.tls("base", ""), certs.tls("r1", ""));
    let mut base = TestRun::new("brkbase");
    let base_cfg = base.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"link\"]\nduration_s = 300",
        &format!(
            r#"
[processes.link]
kind = "bridge"
restart = "on-failure"
backoff_initial_s = 0.2
[processes.link.settings]
zenoh = {{ listen = ["tls/127.0.0.1:{port}"], {tls_base} }}
accept = {{ max_rate_hz = 0 }}
in = [{{ from = "r1", service = "pipeline/sensors/odometry" }}]
"#
        ),
    );
    base.start_supervisor(&base_cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));
    let mut robot = TestRun::new("brkrobot");
    let robot_cfg = robot.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"link\"]\nduration_s = 300",
        &format!(
            r#"
[processes.link]
kind = "bridge"
restart = "never"
nice = 7
[processes.link.settings]
robot = "r1"
end_after = ["ingest"]
end_ack_timeout_s = 20.0
zenoh = {{ connect = ["tls/127.0.0.1:{port}"], {tls_robot} }}
out = [{{ service = "pipeline/sensors/odometry" }}]

[processes.ingest]
kind = "ingest"
after = ["link"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 6.0
progress_interval_s = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 12.0
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#
        ),
    );
    robot.start_supervisor(&robot_cfg, &[]);
    robot.wait_for_log("process=ingest", 1, Duration::from_secs(60));
    std::thread::sleep(Duration::from_secs(2));
    // The robot's bridge runs at the niceness its config asks for (field 19 of /proc/<pid>/stat).
    let rpid = *robot.started_pids("link").first().expect("the robot's bridge started");
    let stat = std::fs::read_to_string(format!("/proc/{rpid}/stat")).expect("its /proc stat");
    let after_comm = stat.rsplit_once(')').expect("stat format").1;
    assert_eq!(after_comm.split_whitespace().nth(16), Some("7"), "nice = 7: {stat}");
    let pid = *base.started_pids("link").first().expect("the base's bridge started");
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), nix::sys::signal::Signal::SIGKILL).expect("kill");
    assert!(robot.wait_supervisor(Duration::ZERO).is_none(), "the robot was still running when its base's bridge died");
    let rs = robot.wait_supervisor(LONG).expect("the robot's run ends");
    let bs = base.wait_supervisor(LONG).expect("the base station's run ends");
    assert_eq!(rs.code(), Some(0), "the robot's pipeline goes on:\n{}", robot.log());
    assert_eq!(bs.code(), Some(0), "base:\n{}", base.log());
    assert!(base.started_pids("link").len() >= 2, "restarted:\n{}", base.log());
    let (r, b) = (robot.summary(), base.summary());
    use crate::summary_schema::part;
    let (rp, bp): (bridge_stage::summary::BridgePart, bridge_stage::summary::BridgePart) = (part(&r), part(&b));
    let (rb, bb) = (&rp.bridge, &bp.bridge);
    eprintln!("robot bridge {:#}\nbase bridge {:#}", r["bridge"], b["bridge"]);
    assert_eq!(rb.end_acknowledged, Some(true), "the restarted bridge got the end of stream: {rb:?}");
    let s = "pipeline/sensors/odometry";
    let sent = rb.out[s].counts.sent;
    let got = bb.inbound[s].counts.received;
    let lost = bb.inbound[s].lost_on_the_way.expect("the robot's end said what it sent");
    assert!(got > 0 && lost > 0, "the new instance received the rest and counts the loss: {bb:?}");
    assert_eq!(got + lost, sent, "{bb:?}");
    assert!(base.log().contains("messages lost or refused across the bridge"), "warned");
    // The robot's side knows what it sent while nobody on the other side subscribed: counted as
    // dropped, in the status line and summary.json like any other loss.
    // The sender learns of the new subscriber through Zenoh's matching status, a moment after
    // the subscriber exists: what it sends in between counts as unmatched on this side and
    // arrives on the other (seen in CI: 310 unmatched and 309 lost; under load 313 and 308, the
    // status ~17 ms late at ~280 msg/s). Allowed: what the robot sends in a quarter of a second.
    let unmatched = rb.out[s].counts.no_subscriber;
    let lag = (sent as f64 / rb.wall_s * 0.25).ceil() as u64;
    assert!(
        unmatched > 0 && unmatched <= lost + lag,
        "{unmatched} sent unmatched, {lost} lost (allowed {lag} more, a quarter second's worth): {rb:?}"
    );
    assert!(unmatched + lag >= lost, "{unmatched} sent unmatched but {lost} lost: {rb:?}");
    let (robot_sup, base_sup): (supervisor::report::SupervisorPart, supervisor::report::SupervisorPart) =
        (part(&r), part(&b));
    let dropped = &robot_sup.dropped;
    assert!(
        dropped.iter().any(|d| d.process == "link" && d.reason == "no subscriber on the other side"),
        "{dropped:#?}"
    );
    let bd = &base_sup.dropped;
    assert!(bd.iter().any(|d| d.process == "link" && d.reason == "lost on the way"), "{bd:#?}");
    assert_eq!(base.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn a_robots_bridge_killed_mid_run_is_restarted_and_counts_on_from_the_killed_ones_counts() {
    let port = free_port();
    let certs = Certs::new(&["base", "r1"], &[]);
    let (tls_base, tls_robot) = (certs.tls("base", ""), certs.tls("r1", ""));
    let mut base = TestRun::new("brsbase");
    let base_cfg = base.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"link\"]\nduration_s = 300",
        &format!(
            r#"
[processes.link]
kind = "bridge"
restart = "never"
[processes.link.settings]
zenoh = {{ listen = ["tls/127.0.0.1:{port}"], {tls_base} }}
accept = {{ max_rate_hz = 0 }}
in = [{{ from = "r1", service = "pipeline/sensors/odometry" }}]
"#
        ),
    );
    base.start_supervisor(&base_cfg, &[]);
    base.wait_for_log("zenoh session open", 1, Duration::from_secs(60));
    let mut robot = TestRun::new("brsrobot");
    let robot_cfg = robot.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"link\"]\nduration_s = 300",
        &format!(
            r#"
[processes.link]
kind = "bridge"
restart = "on-failure"
backoff_initial_s = 0.2
[processes.link.settings]
robot = "r1"
end_after = ["ingest"]
end_ack_timeout_s = 20.0
zenoh = {{ connect = ["tls/127.0.0.1:{port}"], {tls_robot} }}
out = [{{ service = "pipeline/sensors/odometry" }}]

[processes.ingest]
kind = "ingest"
after = ["link"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 6.0
progress_interval_s = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 12.0
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#
        ),
    );
    robot.start_supervisor(&robot_cfg, &[]);
    robot.wait_for_log("process=ingest", 1, Duration::from_secs(60));
    std::thread::sleep(Duration::from_secs(2));
    let pid = *robot.started_pids("link").first().expect("the robot's bridge started");
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), nix::sys::signal::Signal::SIGKILL).expect("kill");
    let rs = robot.wait_supervisor(LONG).expect("the robot's run ends");
    let bs = base.wait_supervisor(LONG).expect("the base station's run ends");
    assert_eq!(rs.code(), Some(0), "the robot's pipeline goes on:\n{}", robot.log());
    assert_eq!(bs.code(), Some(0), "the restarted bridge's end of stream ends the base:\n{}", base.log());
    assert!(robot.started_pids("link").len() >= 2, "restarted:\n{}", robot.log());
    assert!(robot.log().contains("restarted: counting on from the killed instance's counts"), "{}", robot.log());
    let (r, b) = (robot.summary(), base.summary());
    use crate::summary_schema::part;
    let (rp, bp): (bridge_stage::summary::BridgePart, bridge_stage::summary::BridgePart) = (part(&r), part(&b));
    let (rb, bb) = (&rp.bridge, &bp.bridge);
    eprintln!("robot bridge {:#}\nbase bridge {:#}", r["bridge"], b["bridge"]);
    let s = "pipeline/sensors/odometry";
    let out = &rb.out[s].counts;
    let (sent, missed) = (out.sent, out.missed_locally);
    let ingest: ingest_stage::summary::IngestPart = part(&r);
    let published = ingest.ingest.messages.odometry;
    // The restarted bridge counts on from the killed one's counts and last sequence numbers: what
    // the ingest published while no bridge took it shows as a sequence gap (missed locally), and
    // sent + missed covers the run, short of what the killed one handled after its last snapshot.
    assert!(missed > 0, "the gap while the bridge was down: {out:?}");
    assert!(sent + missed <= published, "{sent} + {missed} of {published}");
    assert!((sent + missed) as f64 >= 0.9 * published as f64, "{sent} + {missed} of {published}: {out:?}");
    let inn = &bb.inbound[s].counts;
    let got = inn.received;
    assert_eq!(bb.ends_received, ["r1"], "{bb:?}");
    // The base sees the true gap; the robot's count of it also holds what the killed bridge sent
    // after its last snapshot (taken again by nobody, so counted as missed: never less than lost).
    let gaps = inn.seq_gaps;
    assert!(gaps > 0 && gaps <= missed, "{gaps} gaps at the base, {missed} missed at the robot: {inn:?}");
    assert!(got + gaps <= published && (got + gaps) as f64 >= 0.9 * published as f64, "{inn:?}: of {published}");
    assert_eq!(robot.leftovers(), Vec::<std::path::PathBuf>::new());
}

//! Data sources: each yields [`Item`]s in data-time order, already in wire types.

use std::path::Path;

use geometry::StereoPixels;
use nalgebra::Isometry3;
use shared_types::convert::{mat3_to_row_major, quat_to_xyzw};
use shared_types::{
    BuoyRange, DepthReading, HeadingReading, LaserScanHeader, OdometryInput, PlanarOdometry, STEREO_HAS_DESCRIPTOR,
    STEREO_HAS_PIXELS, STEREO_HAS_TRACK_ID, StereoObservation,
};

/// One message to publish.
#[derive(Debug, Clone, PartialEq)]
pub enum Item {
    /// Odometry / input.
    Odometry {
        /// Measurement time, ns.
        stamp_ns: u64,
        /// The input.
        input: OdometryInput,
    },
    /// One stereo frame.
    Stereo {
        /// Measurement time, ns.
        stamp_ns: u64,
        /// Observations.
        observations: Vec<StereoObservation>,
    },
    /// Buoy ranges of one ping cycle.
    BuoyRanges {
        /// Measurement time, ns.
        stamp_ns: u64,
        /// Ranges.
        ranges: Vec<BuoyRange>,
    },
    /// Pressure depth.
    Depth {
        /// Measurement time, ns.
        stamp_ns: u64,
        /// The reading.
        reading: DepthReading,
    },
    /// A heading (compass).
    Heading {
        /// Measurement time, ns.
        stamp_ns: u64,
        /// The reading.
        reading: HeadingReading,
    },
    /// A planar laser scan.
    Laser {
        /// Measurement time, ns.
        stamp_ns: u64,
        /// Geometry (the header's `msg` is filled in when published).
        header: LaserScanHeader,
        /// Ranges, m.
        ranges: Vec<f32>,
    },
    /// Planar wheel odometry.
    PlanarOdometry {
        /// Measurement time, ns.
        stamp_ns: u64,
        /// The odometry.
        odometry: PlanarOdometry,
    },
    /// A point cloud.
    Cloud {
        /// Measurement time, ns.
        stamp_ns: u64,
        /// world_from_sensor, when the source knows it.
        world_from_sensor: Option<Isometry3<f64>>,
        /// Points in the sensor frame, m.
        points: Vec<[f32; 3]>,
    },
}

impl Item {
    /// Measurement time, ns.
    pub fn stamp_ns(&self) -> u64 {
        match self {
            Item::Odometry { stamp_ns, .. }
            | Item::Stereo { stamp_ns, .. }
            | Item::BuoyRanges { stamp_ns, .. }
            | Item::Depth { stamp_ns, .. }
            | Item::Heading { stamp_ns, .. }
            | Item::Laser { stamp_ns, .. }
            | Item::PlanarOdometry { stamp_ns, .. }
            | Item::Cloud { stamp_ns, .. } => *stamp_ns,
        }
    }
}

/// An error of a source: the data set or file (named), the simulator's settings, or writing the
/// source's outputs.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// A data file is unreadable (named with its line where there is one).
    #[error(transparent)]
    Data(#[from] datasets::DatasetError),
    /// A depth image or its intrinsics are invalid.
    #[error(transparent)]
    Depth(#[from] datasets::DepthError),
    /// The simulator refused its settings.
    #[error(transparent)]
    Sim(#[from] sim::SimError),
    /// Writing an output of the source (scene.json, a trajectory) failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: std::path::PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The source's settings name something that is not there or cannot be used.
    #[error("{0}")]
    Settings(String),
}

impl From<SourceError> for pipeline_runtime::StageError {
    fn from(e: SourceError) -> Self {
        pipeline_runtime::StageError::stage(e)
    }
}

fn io_at(path: &Path) -> impl FnOnce(std::io::Error) -> SourceError + use<> {
    let path = path.to_path_buf();
    move |source| SourceError::Io { path, source }
}

/// Writes `scene.json` (pretty JSON) into `out_dir` (for the other sources' modules).
pub(crate) fn write_scene_json(out_dir: &Path, scene: &serde_json::Value) -> Result<(), SourceError> {
    write_scene(out_dir, scene)
}

/// Writes `scene.json` (pretty JSON) into `out_dir`.
fn write_scene(out_dir: &Path, scene: &serde_json::Value) -> Result<(), SourceError> {
    std::fs::create_dir_all(out_dir).map_err(io_at(out_dir))?;
    let path = out_dir.join("scene.json");
    let text =
        serde_json::to_vec_pretty(scene).map_err(|e| SourceError::Io { path: path.clone(), source: e.into() })?;
    std::fs::write(&path, text).map_err(io_at(&path))
}

/// A source of items.
pub trait Source {
    /// The next item, `None` at the end.
    fn next_item(&mut self) -> Result<Option<Item>, SourceError>;
    /// Fraction done in [0, 1], when known.
    fn progress(&self) -> Option<f64>;
    /// Called once after the last item: writes other outputs to `out_dir` (the ground truth is
    /// written as it becomes known: see [`Source::truth`]).
    fn finish(&mut self, out_dir: &Path) -> Result<(), SourceError>;
    /// One line describing the source, for the log.
    fn describe(&self) -> String;
    /// Appends to `out` the ground truth known so far from sample `from` on (`world_from_body` at
    /// `t_s`, in time order). A simulator's grows as it advances; a replay knows all of it at
    /// once. The default is a source without ground truth.
    fn truth(&self, _from: usize, _out: &mut Vec<(f64, Isometry3<f64>)>) {}
    /// The warts of the data met so far, counted by kind (lines out of order, rows skipped...),
    /// for summary.json. Each kind is also warned about in the log when first met.
    fn warts(&self) -> std::collections::BTreeMap<&'static str, u64> {
        Default::default()
    }
    /// More about the source for summary.json (an object merged into `ingest`; per-route counts
    /// of a bag, say). The default is nothing.
    fn details(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
}

/// `ground_truth.tum`, written while the source advances: a run stopped early (or a crash) leaves
/// the ground truth of everything published, so that the stages can still score themselves.
/// Each batch of samples goes out in one write of whole lines.
pub struct TruthFile {
    file: std::fs::File,
    path: std::path::PathBuf,
    written: usize,
    pending: Vec<(f64, Isometry3<f64>)>,
    text: String,
}

impl TruthFile {
    /// Creates (truncates) `<out_dir>/ground_truth.tum`.
    pub fn create(out_dir: &Path) -> std::io::Result<Self> {
        std::fs::create_dir_all(out_dir)?;
        let path = out_dir.join("ground_truth.tum");
        let file = std::fs::File::create(&path)?;
        Ok(Self { file, path, written: 0, pending: vec![], text: String::new() })
    }

    /// Writes the samples `source` has learnt since the last call; returns how many.
    pub fn update(&mut self, source: &dyn Source) -> std::io::Result<usize> {
        use std::io::Write as _;
        self.pending.clear();
        source.truth(self.written, &mut self.pending);
        if self.pending.is_empty() {
            return Ok(0);
        }
        self.text.clear();
        for (t, p) in &self.pending {
            geometry::tum::push_tum_line(&mut self.text, *t, p);
        }
        self.file.write_all(self.text.as_bytes())?;
        self.written += self.pending.len();
        Ok(self.pending.len())
    }

    /// Samples written so far.
    pub fn written(&self) -> usize {
        self.written
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Seconds to the pipeline's nanosecond stamps.
pub fn stamp_from_s(t_s: f64) -> u64 {
    (t_s * 1e9).round().max(0.0) as u64
}

pub use geometry::tum::write_tum;

/// The built-in simulator as a source.
pub struct SimSource {
    sim: sim::Simulator,
    expected_s: f64,
}

impl SimSource {
    /// Builds the simulator and writes `scene.json` into `out_dir`.
    pub fn new(config: sim::SimConfig, out_dir: &Path) -> Result<Self, SourceError> {
        let sim = sim::Simulator::new(config)?;
        let scene = serde_json::json!({
            "scene": sim.scene(),
            "mission": sim.config().mission,
            "sensors": sim.config().sensors,
            "seed": sim.config().seed,
            "body_from_stereo_camera": {
                "translation_m": sim.body_from_stereo().translation.vector.as_slice(),
                "rotation_xyzw": quat_to_xyzw(&sim.body_from_stereo().rotation),
            },
        });
        write_scene(out_dir, &scene)?;
        let expected_s = sim.expected_duration_s();
        Ok(Self { sim, expected_s })
    }

    /// Converts one simulator event into a wire item.
    pub fn to_item(event: sim::SimEvent) -> Item {
        match event {
            sim::SimEvent::Odometry(o) => {
                let mut input_covariance = [0.0; 16];
                for (i, v) in o.variances.iter().enumerate() {
                    input_covariance[i * 5] = *v;
                }
                Item::Odometry {
                    stamp_ns: stamp_from_s(o.t_s),
                    input: OdometryInput {
                        v_mps: o.input.v_mps,
                        delta_theta_rad: o.input.delta_theta_rad.into(),
                        dt_s: o.input.dt_s,
                        input_covariance,
                    },
                }
            }
            sim::SimEvent::Stereo(f) => Item::Stereo {
                stamp_ns: stamp_from_s(f.t_s),
                observations: f
                    .observations
                    .iter()
                    .map(|o| StereoObservation {
                        point_cam_m: o.point_cam_m.into(),
                        covariance_cam_m2: mat3_to_row_major(&o.covariance_cam_m2),
                        pixels_ul_ur_v: [o.pixels.u_left_px, o.pixels.u_right_px, o.pixels.v_px],
                        source_id: o.landmark_id.unwrap_or(u64::MAX),
                        descriptor: o.descriptor,
                        flags: STEREO_HAS_DESCRIPTOR | STEREO_HAS_PIXELS,
                        _reserved: 0,
                    })
                    .collect(),
            },
            sim::SimEvent::Buoys(b) => Item::BuoyRanges {
                stamp_ns: stamp_from_s(b.t_s),
                ranges: b
                    .ranges
                    .iter()
                    .map(|r| BuoyRange { buoy_id: r.buoy_id, _reserved: 0, range_m: r.range_m, sigma_m: r.sigma_m })
                    .collect(),
            },
            sim::SimEvent::Cloud(c) => Item::Cloud {
                stamp_ns: stamp_from_s(c.t_s),
                world_from_sensor: Some(c.world_from_sensor),
                points: c.points_sensor_m,
            },
            sim::SimEvent::Compass(c) => Item::Heading {
                stamp_ns: stamp_from_s(c.t_s),
                reading: HeadingReading { yaw_rad: c.yaw_rad, sigma_rad: c.sigma_rad },
            },
            sim::SimEvent::Pressure(p) => Item::Depth {
                stamp_ns: stamp_from_s(p.t_s),
                reading: DepthReading { depth_m: p.depth_m, sigma_m: p.sigma_m },
            },
        }
    }
}

impl Source for SimSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        Ok(self.sim.next().map(Self::to_item))
    }

    fn progress(&self) -> Option<f64> {
        Some((self.sim.time_s() / self.expected_s).min(1.0))
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn truth(&self, from: usize, out: &mut Vec<(f64, Isometry3<f64>)>) {
        out.extend(self.sim.truth().iter().skip(from).map(|t| (t.t_s, t.world_from_body)));
    }

    fn describe(&self) -> String {
        format!(
            "simulated mission (seed {}, {} landmarks, ~{:.0} s of data)",
            self.sim.config().seed,
            self.sim.scene().landmark_count,
            self.expected_s
        )
    }
}

/// Creates the replay source for `kind` (everything but the simulator).
pub fn file_source(
    kind: crate::SourceKind,
    settings: &crate::IngestSettings,
    config_dir: &Path,
    _out_dir: &Path,
) -> Result<Box<dyn Source>, SourceError> {
    use crate::SourceKind::*;
    Ok(match kind {
        Sim | StereoSim | Indoor => return Err(SourceError::Settings("a simulator is not a file source".into())),
        Plaza2 => Box::new(Plaza2Source::load(&crate::resolve(config_dir, &settings.plaza2.dir), &settings.plaza2)?),
        StereoVo => {
            Box::new(StereoVoSource::load(&crate::resolve(config_dir, &settings.stereo_vo.dir), &settings.stereo_vo)?)
        }
        Clouds => Box::new(CloudFileSource::new(config_dir, &settings.clouds)?),
        Carmen => Box::new(crate::carmen::CarmenSource::load(config_dir, &settings.carmen)?),
        DepthImages => Box::new(DepthImageSource::new(config_dir, &settings.depth_images)?),
        Rosbag2 => Box::new(crate::rosbag2::Rosbag2Source::open(config_dir, &settings.rosbag2)?),
    })
}

/// Elements to reserve per cloud sample up front.
pub fn initial_cloud_len(settings: &crate::IngestSettings) -> usize {
    match settings.source {
        crate::SourceKind::Sim => {
            let d = &settings.sim.sensors.depth_camera;
            (d.width_px * d.height_px) as usize
        }
        crate::SourceKind::DepthImages => 640 * 480,
        crate::SourceKind::Clouds => 100_000,
        crate::SourceKind::Rosbag2 => 65_536,
        crate::SourceKind::Indoor => {
            let d = &settings.indoor.depth;
            (d.width_px * d.height_px) as usize
        }
        _ => 1,
    }
}

/// Elements to reserve per laser scan up front.
pub fn initial_laser_len(settings: &crate::IngestSettings) -> usize {
    match settings.source {
        crate::SourceKind::Carmen => 361,
        crate::SourceKind::Indoor => settings.indoor.laser.beams,
        crate::SourceKind::Rosbag2 => 1081,
        _ => 1,
    }
}

/// Replay of Plaza2: odometry increments as inputs (v = Δd/Δt, δθz = Δheading) and each beacon
/// range as a one-element `BuoyRange` slice, merged in time order on the data set's clock.
pub struct Plaza2Source {
    data: datasets::Plaza2,
    settings: crate::Plaza2Settings,
    next_odo: usize,
    next_range: usize,
    t_first_s: f64,
    t_last_s: f64,
    t_now_s: f64,
    skipped_odometry: u64,
    dir: std::path::PathBuf,
    /// The ground truth as body poses (Plaza2's heading is offset by π from the direction of travel).
    truth: Vec<(f64, Isometry3<f64>)>,
    /// The last item has been taken.
    exhausted: bool,
}

impl Plaza2Source {
    /// Loads the four files of `dir` (the run's prefix from the settings, else found in `dir`).
    /// Lines out of time order are sorted into place, counted and warned about once per file.
    pub fn load(dir: &Path, settings: &crate::Plaza2Settings) -> Result<Self, SourceError> {
        let data = match &settings.prefix {
            Some(prefix) => datasets::Plaza2::load_with_prefix(dir, prefix)?,
            None => datasets::Plaza2::load(dir)?,
        };
        for o in &data.out_of_order {
            tracing::warn!(file = %o.path.display(), lines = o.lines, "{o}");
        }
        let truth = data
            .ground_truth
            .iter()
            .map(|g| {
                let rot = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, g.heading_rad + std::f64::consts::PI);
                (g.t_s, Isometry3::from_parts(nalgebra::Translation3::new(g.x_m, g.y_m, 0.0), rot))
            })
            .collect();
        let t_first_s = data
            .odometry
            .first()
            .map(|r| r.t_s)
            .unwrap_or(0.0)
            .min(data.ranges.first().map(|r| r.t_s).unwrap_or(f64::MAX));
        let t_last_s =
            data.odometry.last().map(|r| r.t_s).unwrap_or(0.0).max(data.ranges.last().map(|r| r.t_s).unwrap_or(0.0));
        Ok(Self {
            data,
            settings: settings.clone(),
            next_odo: 0,
            next_range: 0,
            t_first_s,
            t_last_s,
            t_now_s: t_first_s,
            skipped_odometry: 0,
            dir: dir.to_path_buf(),
            truth,
            exhausted: false,
        })
    }

    fn odometry_item(&mut self, i: usize) -> Option<Item> {
        let row = self.data.odometry[i];
        let dt = if i == 0 { 0.1 } else { row.t_s - self.data.odometry[i - 1].t_s };
        if dt.is_nan() || dt <= 0.0 {
            self.skipped_odometry += 1;
            tracing::warn!(row = i + 1, dt, "Plaza2 odometry: time does not advance; row skipped");
            return None;
        }
        let mut input_covariance = [0.0; 16];
        input_covariance[0] = self.settings.speed_sigma_mps.powi(2);
        for k in 1..4 {
            input_covariance[k * 5] = self.settings.turn_sigma_rad.powi(2);
        }
        Some(Item::Odometry {
            stamp_ns: stamp_from_s(row.t_s),
            input: OdometryInput {
                v_mps: row.delta_dist_m / dt,
                delta_theta_rad: [0.0, 0.0, row.delta_heading_rad],
                dt_s: dt,
                input_covariance,
            },
        })
    }
}

impl Source for Plaza2Source {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        loop {
            let t_odo = self.data.odometry.get(self.next_odo).map(|r| r.t_s);
            let t_rng = self.data.ranges.get(self.next_range).map(|r| r.t_s);
            match (t_odo, t_rng) {
                (None, None) => {
                    self.exhausted = true;
                    return Ok(None);
                }
                (Some(to), tr) if tr.is_none_or(|tr| to <= tr) => {
                    let i = self.next_odo;
                    self.next_odo += 1;
                    self.t_now_s = to;
                    if let Some(item) = self.odometry_item(i) {
                        return Ok(Some(item));
                    }
                }
                (_, Some(tr)) => {
                    let r = self.data.ranges[self.next_range];
                    self.next_range += 1;
                    self.t_now_s = tr;
                    let range = BuoyRange {
                        buoy_id: r.beacon_id,
                        _reserved: 0,
                        range_m: r.range_m,
                        sigma_m: self.settings.range_sigma_m,
                    };
                    return Ok(Some(Item::BuoyRanges { stamp_ns: stamp_from_s(r.t_s), ranges: vec![range] }));
                }
                (Some(_), None) => unreachable!("covered by the first arm"),
            }
        }
    }

    fn progress(&self) -> Option<f64> {
        Some(((self.t_now_s - self.t_first_s) / (self.t_last_s - self.t_first_s).max(1e-9)).clamp(0.0, 1.0))
    }

    /// The ground-truth rows up to the data time reached (all of them at the end), so that a run
    /// stopped early is scored on the part it replayed.
    fn truth(&self, from: usize, out: &mut Vec<(f64, Isometry3<f64>)>) {
        let known =
            if self.exhausted { self.truth.len() } else { self.truth.partition_point(|(t, _)| *t <= self.t_now_s) };
        out.extend(self.truth.iter().take(known).skip(from).copied());
    }

    fn warts(&self) -> std::collections::BTreeMap<&'static str, u64> {
        let out_of_order: usize = self.data.out_of_order.iter().map(|o| o.lines).sum();
        [("lines_out_of_time_order", out_of_order as u64), ("odometry_rows_skipped", self.skipped_odometry)]
            .into_iter()
            .filter(|(_, n)| *n > 0)
            .collect()
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        if self.skipped_odometry > 0 {
            tracing::warn!(rows = self.skipped_odometry, "Plaza2 odometry rows skipped (time not advancing)");
        }
        Ok(())
    }

    fn describe(&self) -> String {
        format!(
            "Plaza2 replay from {} ({} odometry rows, {} ranges to {} beacons, {:.0} s)",
            self.dir.display(),
            self.data.odometry.len(),
            self.data.ranges.len(),
            self.data.beacons.len(),
            self.t_last_s - self.t_first_s
        )
    }
}

/// Replay of stereo landmark observations (stereo_vo_large format): one message per frame,
/// stamped `frame_id / rate_hz`; the covariance of each point follows from the pixel noise.
pub struct StereoVoSource {
    frames: Vec<datasets::StereoFrame>,
    poses: Vec<datasets::stereo_vo::CameraPose>,
    rig: geometry::StereoRig,
    sigma_px: f64,
    rate_hz: f64,
    next: usize,
    rejected: u64,
    dir: std::path::PathBuf,
    track_ids: bool,
}

impl StereoVoSource {
    /// Loads the data set in `dir`.
    pub fn load(dir: &Path, settings: &crate::StereoVoSettings) -> Result<Self, SourceError> {
        let vo = datasets::StereoVo::load(dir)?;
        let c = vo.calibration;
        let rig = geometry::StereoRig {
            f_px: c.fx_px,
            cx_px: c.cx_px,
            cy_px: c.cy_px,
            baseline_m: c.baseline_m,
            width_px: (2.0 * c.cx_px).ceil() as u32,
            height_px: (2.0 * c.cy_px).ceil() as u32,
        };
        Ok(Self {
            frames: datasets::group_by_frame(&vo.factors),
            poses: vo.poses,
            rig,
            sigma_px: settings.pixel_sigma_px,
            rate_hz: settings.rate_hz,
            next: 0,
            rejected: 0,
            dir: dir.to_path_buf(),
            track_ids: settings.track_ids,
        })
    }
}

impl Source for StereoVoSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        let Some(frame) = self.frames.get(self.next) else { return Ok(None) };
        self.next += 1;
        let mut observations = Vec::with_capacity(frame.observations.len());
        for f in &frame.observations {
            let px = StereoPixels { u_left_px: f.u_left_px, u_right_px: f.u_right_px, v_px: f.v_px };
            match self.rig.triangulation_covariance(&px, self.sigma_px) {
                Ok(cov) => observations.push(StereoObservation {
                    point_cam_m: f.point_cam_m,
                    covariance_cam_m2: mat3_to_row_major(&cov),
                    pixels_ul_ur_v: [f.u_left_px, f.u_right_px, f.v_px],
                    source_id: f.landmark_id,
                    descriptor: [0; 32],
                    flags: STEREO_HAS_PIXELS | if self.track_ids { STEREO_HAS_TRACK_ID } else { 0 },
                    _reserved: 0,
                }),
                Err(e) => {
                    self.rejected += 1;
                    tracing::warn!(frame = frame.frame_id, landmark = f.landmark_id, "observation skipped: {e}");
                }
            }
        }
        Ok(Some(Item::Stereo { stamp_ns: stamp_from_s(frame.frame_id as f64 / self.rate_hz), observations }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.next as f64 / self.frames.len().max(1) as f64)
    }

    fn finish(&mut self, out_dir: &Path) -> Result<(), SourceError> {
        // The data set's own VO poses, for comparison with the SLAM trajectory (e.g. with evo).
        let poses: Vec<(f64, Isometry3<f64>)> = self
            .poses
            .iter()
            .map(|p| {
                let m = p.world_from_camera;
                let rot = nalgebra::Rotation3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned());
                let iso = Isometry3::from_parts(
                    nalgebra::Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
                    nalgebra::UnitQuaternion::from_rotation_matrix(&rot),
                );
                (p.frame_id as f64 / self.rate_hz, iso)
            })
            .collect();
        let path = out_dir.join("vo_camera_poses.tum");
        write_tum(&path, poses.iter().map(|(t, p)| (*t, p))).map_err(io_at(&path))?;
        Ok(())
    }

    fn warts(&self) -> std::collections::BTreeMap<&'static str, u64> {
        [("observations_rejected", self.rejected)].into_iter().filter(|(_, n)| *n > 0).collect()
    }

    fn describe(&self) -> String {
        format!(
            "stereo replay from {} ({} frames, {} observations)",
            self.dir.display(),
            self.frames.len(),
            self.frames.iter().map(|f| f.observations.len()).sum::<usize>()
        )
    }
}

/// The KITTI-like simulated stereo drive (`sim::road`): one stereo message per published frame,
/// stamped at the frame's time; `ground_truth.tum` (the car's body pose) and `scene.json` (the
/// camera mounting) at the end.
pub struct StereoSimSource {
    sim: sim::road::RoadSim,
    track_ids: bool,
    features: u64,
}

impl StereoSimSource {
    /// Builds the drive and writes `scene.json` (the camera mounting) into `out_dir`.
    pub fn new(settings: &crate::StereoSimSettings, out_dir: &Path) -> Result<Self, SourceError> {
        let sim = sim::road::RoadSim::new(settings.drive.clone())?;
        let b = sim.body_from_camera();
        let scene = serde_json::json!({
            "drive": sim.config(),
            "landmarks": sim.landmark_count(),
            "path_length_m": sim.path_length_m(),
            "body_from_stereo_camera": {
                "translation_m": b.translation.vector.as_slice(),
                "rotation_xyzw": quat_to_xyzw(&b.rotation),
            },
        });
        write_scene(out_dir, &scene)?;
        Ok(Self { sim, track_ids: settings.track_ids, features: 0 })
    }
}

impl Source for StereoSimSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        let Some(frame) = self.sim.next() else { return Ok(None) };
        let flags = STEREO_HAS_PIXELS | if self.track_ids { STEREO_HAS_TRACK_ID } else { 0 };
        self.features += frame.observations.len() as u64;
        Ok(Some(Item::Stereo {
            stamp_ns: stamp_from_s(frame.t_s),
            observations: frame
                .observations
                .iter()
                .map(|o| StereoObservation {
                    point_cam_m: o.point_cam_m.into(),
                    covariance_cam_m2: mat3_to_row_major(&o.covariance_cam_m2),
                    pixels_ul_ur_v: [o.pixels.u_left_px, o.pixels.u_right_px, o.pixels.v_px],
                    source_id: o.track_id,
                    descriptor: [0; 32],
                    flags,
                    _reserved: 0,
                })
                .collect(),
        }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.sim.progress())
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        tracing::info!(
            dropped_frames = self.sim.dropped(),
            "{} frames dropped by the simulated camera, as configured",
            self.sim.dropped()
        );
        Ok(())
    }

    fn truth(&self, from: usize, out: &mut Vec<(f64, Isometry3<f64>)>) {
        out.extend(self.sim.truth().iter().skip(from).map(|t| (t.t_s, t.world_from_body)));
    }

    fn warts(&self) -> std::collections::BTreeMap<&'static str, u64> {
        [("frames_dropped_by_the_simulated_camera", self.sim.dropped() as u64)]
            .into_iter()
            .filter(|(_, n)| *n > 0)
            .collect()
    }

    fn describe(&self) -> String {
        let c = self.sim.config();
        format!(
            "simulated stereo drive (seed {}, {} frames, {} landmarks, {:.0} m{})",
            c.seed,
            c.frames,
            self.sim.landmark_count(),
            self.sim.path_length_m(),
            if self.track_ids { ", with track ids" } else { "" }
        )
    }
}

/// Point clouds from files (OctoMap scan.dat, optionally .bz2, with NODE poses; PLY), one cloud
/// per scan, at `rate_hz`, read when due.
pub struct CloudFileSource {
    files: Vec<std::path::PathBuf>,
    rate_hz: f64,
    repeat: u32,
    next_file: usize,
    queued: VecDeque<PosedCloud>,
    emitted: u64,
}

use std::collections::VecDeque;

/// A cloud with its world_from_sensor pose, when known.
type PosedCloud = (Option<Isometry3<f64>>, Vec<[f32; 3]>);

impl CloudFileSource {
    /// Checks that every file exists.
    pub fn new(config_dir: &Path, settings: &crate::CloudFileSettings) -> Result<Self, SourceError> {
        let files: Vec<_> = settings.files.iter().map(|f| crate::resolve(config_dir, f)).collect();
        for f in &files {
            if !f.is_file() {
                return Err(SourceError::Settings(format!("cloud file {} does not exist", f.display())));
            }
        }
        Ok(Self {
            files,
            rate_hz: settings.rate_hz,
            repeat: settings.repeat,
            next_file: 0,
            queued: VecDeque::new(),
            emitted: 0,
        })
    }

    fn load(path: &Path) -> Result<Vec<PosedCloud>, SourceError> {
        let name = path.to_string_lossy().to_lowercase();
        if name.ends_with(".ply") {
            Ok(vec![(None, datasets::read_ply(path)?)])
        } else {
            // scan.dat: the sensor is at the origin unless NODE lines give poses.
            Ok(datasets::read_scan_file(path)?.into_iter().map(|s| (Some(s.world_from_sensor()), s.points)).collect())
        }
    }
}

impl Source for CloudFileSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        while self.queued.is_empty() {
            if self.next_file >= self.files.len() * self.repeat as usize {
                return Ok(None);
            }
            let path = self.files[self.next_file % self.files.len()].clone();
            self.next_file += 1;
            self.queued.extend(Self::load(&path)?);
        }
        let (pose, points) = self.queued.pop_front().expect("not empty");
        self.emitted += 1;
        Ok(Some(Item::Cloud {
            stamp_ns: stamp_from_s(self.emitted as f64 / self.rate_hz),
            world_from_sensor: pose,
            points,
        }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.next_file as f64 / (self.files.len() * self.repeat as usize).max(1) as f64)
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn describe(&self) -> String {
        format!("{} cloud file(s) × {} at {} Hz", self.files.len(), self.repeat, self.rate_hz)
    }
}

/// Depth images back-projected to clouds in the camera optical frame ([2D3D] eq 6-8).
pub struct DepthImageSource {
    files: Vec<std::path::PathBuf>,
    settings: crate::DepthImageSettings,
    intrinsics: datasets::DepthIntrinsics,
    next: usize,
}

impl DepthImageSource {
    /// Checks the files and intrinsics.
    pub fn new(config_dir: &Path, settings: &crate::DepthImageSettings) -> Result<Self, SourceError> {
        let files: Vec<_> = settings.files.iter().map(|f| crate::resolve(config_dir, f)).collect();
        for f in &files {
            if !f.is_file() {
                return Err(SourceError::Settings(format!("depth image {} does not exist", f.display())));
            }
        }
        let intrinsics = datasets::DepthIntrinsics {
            fx: settings.fx_px,
            fy: settings.fy_px,
            cx: settings.cx_px,
            cy: settings.cy_px,
            depth_scale: settings.depth_scale,
            min_depth_m: settings.min_depth_m,
            max_depth_m: settings.max_depth_m,
        };
        intrinsics.validate()?;
        Ok(Self { files, settings: settings.clone(), intrinsics, next: 0 })
    }
}

impl Source for DepthImageSource {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        let Some(path) = self.files.get(self.next) else { return Ok(None) };
        self.next += 1;
        let is_png = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
        let image = if is_png {
            datasets::read_depth_png(path)?
        } else {
            if self.settings.raw_width == 0 || self.settings.raw_height == 0 {
                return Err(SourceError::Settings(format!(
                    "{}: raw depth images need depth_images.raw_width and raw_height",
                    path.display()
                )));
            }
            datasets::read_depth_raw(path, self.settings.raw_width, self.settings.raw_height)?
        };
        let points = datasets::back_project(&image, &self.intrinsics, self.settings.stride)?;
        Ok(Some(Item::Cloud {
            stamp_ns: stamp_from_s(self.next as f64 / self.settings.rate_hz),
            world_from_sensor: None,
            points,
        }))
    }

    fn progress(&self) -> Option<f64> {
        Some(self.next as f64 / self.files.len().max(1) as f64)
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn describe(&self) -> String {
        format!("{} depth image(s) at {} Hz", self.files.len(), self.settings.rate_hz)
    }
}

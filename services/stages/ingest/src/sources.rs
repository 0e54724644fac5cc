//! Data sources: each yields [`Item`]s in data-time order, already in wire types.

use std::path::Path;

use nalgebra::Isometry3;
use shared_types::{
    BuoyRange, DepthReading, HeadingReading, LaserScanHeader, OdometryInput, PlanarOdometry, StereoObservation,
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

pub(crate) fn io_at(path: &Path) -> impl FnOnce(std::io::Error) -> SourceError + use<> {
    let path = path.to_path_buf();
    move |source| SourceError::Io { path, source }
}

/// Writes `scene.json` (pretty JSON) into `out_dir` (for the other sources' modules).
pub(crate) fn write_scene_json(out_dir: &Path, scene: &serde_json::Value) -> Result<(), SourceError> {
    write_scene(out_dir, scene)
}

/// Writes `scene.json` (pretty JSON) into `out_dir`.
pub(crate) fn write_scene(out_dir: &Path, scene: &serde_json::Value) -> Result<(), SourceError> {
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
    /// More about the source for summary.json (merged into `ingest`; per-route counts of a bag,
    /// say). The default is nothing.
    fn details(&self) -> crate::summary::SourceDetails {
        Default::default()
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

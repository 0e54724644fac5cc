//! 2-D grid SLAM ([2D3D] §III.A-B, docs/EQUATIONS.md §8): a Rao-Blackwellised particle filter over planar
//! poses with occupancy-grid maps, as gmapping (Grisetti, Stachniss, Burgard 2007), with
//!
//! - [`grid`]: log-odds grids in tiles shared copy-on-write between particles;
//! - [`matcher`]: the scan matcher (score and likelihood of a pose against a particle's map);
//! - [`filter`]: the filter (improved proposal, N_eff resampling, tracking between updates);
//! - [`densify`]: poses between scans, shaped by the odometry;
//! - [`drift`]: seeded synthetic odometry drift for SLAM-corrected logs;
//! - [`relations`]: the relations metric of Kümmerle et al. 2009;
//! - [`export`]: the map_server files, a PNG, TUM trajectories.
//!
//! Frames: `map_from_body` poses in the map frame (the odometry frame at the first scan), m and
//! rad; the laser's pose on the robot is `body_from_laser`.

#[cfg(feature = "pose-graph")]
pub mod backend;
pub mod config;
pub mod correlative;
pub mod densify;
pub mod drift;
pub mod export;
pub mod filter;
pub mod grid;
pub mod matcher;
#[cfg(feature = "pose-graph")]
pub mod posegraph;
pub mod relations;

pub use filter::{
    GridSlam, GridSlamConfig, GridSlamStats, MapBeam, MemoryStats, MotionNoise, NeffSummary, PreparedScan,
    ProposalLikelihood, ScanGeometry, ScanOutcome,
};
pub use omni::Pose2;

/// What can go wrong.
#[derive(Debug, thiserror::Error)]
pub enum GridSlamError {
    /// Settings are invalid: every problem, with its key.
    #[error("invalid grid_slam settings: {}", .0.iter().map(|i| format!("{}: {}", i.key, i.message)).collect::<Vec<_>>().join("; "))]
    Config(Vec<validation::ConfigIssue>),
    /// A scan's beam count differs from the laser's.
    #[error("scan has {got} beams, the laser has {expected}")]
    BeamCount {
        /// Beams configured.
        expected: usize,
        /// Beams in the scan.
        got: usize,
    },
    /// A scan's stamp is not after the previous one (or not finite).
    #[error("scan stamp {stamp_s} s is not after the previous one ({last_s} s)")]
    Stamp {
        /// The scan's stamp.
        stamp_s: f64,
        /// The previous scan's.
        last_s: f64,
    },
    /// The odometry pose is not finite.
    #[error("odometry at {stamp_s} s is not finite")]
    Odometry {
        /// The scan's stamp.
        stamp_s: f64,
    },
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// A snapshot cannot be restored.
    #[error("grid_slam snapshot: {why}")]
    Snapshot {
        /// What is wrong.
        why: String,
    },
    /// The pose graph cannot be optimised.
    #[error("pose graph: {why}")]
    Optimisation {
        /// What is wrong.
        why: String,
    },
    /// A line of a text file is malformed.
    #[error("{file}:{line}: {why}")]
    Parse {
        /// The file (or what the text came from).
        file: String,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        why: String,
    },
}

//! Readers (and a few writers) of the real sensor data files the pipeline replays, one module
//! per format:
//!
//! - [`plaza2`]: the CMU Plaza 2 range-only data set (odometry, UWB ranges, ground truth, beacons);
//! - [`stereo_vo`]: GTSAM's stereo visual-odometry example (calibration, observations, poses);
//! - [`scan`]: OctoMap's plain-text point clouds (`scan.dat`, with optional `NODE` poses);
//! - [`ply`]: PLY point clouds (ASCII and binary), plus a writer;
//! - [`carmen`]: CARMEN 2-D laser logs (FLASER, RAWLASER, ROBOTLASER1, ODOM; plain or gzip);
//! - [`depth`]: 16-bit depth images (PNG or raw) and their back-projection to points;
//! - [`octomap_bench`]: the OctoMap reference benchmark's depth frames and scene.
//!
//! This is a pure library: no IPC, no logging, no panics on bad input. Every failure is a
//! [`DatasetError`] whose message names the file and, for text, the 1-based line, e.g.
//! `data/Plaza2_TD.txt:17: expected 4 numbers, got 3`. NaN and infinite values are errors.
//! Text files ending in `.bz2` are decompressed on the fly. Units are SI and appear in field
//! names (`_m`, `_s`, `_rad`, `_px`); points are `[f32; 3]` (x, y, z) in metres.

pub mod carmen;
pub mod depth;
pub mod error;
mod lines;
pub mod octomap_bench;
pub mod plaza2;
pub mod ply;
pub mod scan;
pub mod stereo_vo;

pub use depth::{DepthError, DepthImage, DepthIntrinsics, back_project, read_depth_png, read_depth_raw};
pub use error::{DatasetError, FileErrorKind, LineErrorKind, Result};
pub use plaza2::Plaza2;
pub use ply::{PlyFormat, read_ply, write_ply};
pub use scan::{Pose6D, Scan, read_scan_file};
pub use stereo_vo::{StereoFrame, StereoVo, group_by_frame};

/// For tests: whether the shared data set file or directory `path` (under `../shared/data`) is
/// present. When it is absent, under CI (the `CI` environment variable set to anything but
/// `false` or empty, as `.ci/run` does: CI runs with `../shared` beside the clone) this panics
/// naming the path, so that a test never passes without its data; elsewhere it prints that the
/// test is skipped and returns false (a fresh clone may not have the data sets beside it).
#[must_use]
pub fn shared_data_present(path: impl AsRef<std::path::Path>, test: &str) -> bool {
    let path = path.as_ref();
    if path.exists() {
        return true;
    }
    let ci = std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "false");
    assert!(
        !ci,
        "{test}: {} is missing: CI runs with the shared data sets (../shared/data) beside the clone",
        path.display()
    );
    eprintln!("{test} skipped: {} is absent (set CI=1 to make this a failure)", path.display());
    false
}

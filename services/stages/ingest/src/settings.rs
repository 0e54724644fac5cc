//! Settings of the ingest process (`[processes.<name>.settings]` with `kind = "ingest"`).
//! Paths are relative to the pipeline config file's directory.

use std::path::{Path, PathBuf};

use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};
use shared_types::services::{CLOUD, service_spec};

/// Which data source feeds the pipeline.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum SourceKind {
    /// The built-in simulated mission (`sim` table).
    #[default]
    Sim,
    /// Plaza2 odometry and beacon ranges (`plaza2` table).
    Plaza2,
    /// Stereo landmark observations in the stereo_vo_large format (`stereo_vo` table).
    StereoVo,
    /// The KITTI-like simulated stereo drive with ground truth (`stereo_sim` table).
    StereoSim,
    /// Point-cloud files, scan.dat or PLY (`clouds` table).
    Clouds,
    /// Depth images, 16-bit PNG or raw (`depth_images` table).
    DepthImages,
    /// A CARMEN 2-D laser log: laser scans and planar odometry (`carmen` table).
    Carmen,
    /// The simulated indoor mission of the omni-directional robot (`indoor` table).
    Indoor,
    /// A ROS 2 bag (rosbag2, MCAP storage): routed topics (`rosbag2` table).
    Rosbag2,
}

/// Ingest settings.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IngestSettings {
    /// The source.
    pub source: SourceKind,
    /// 1.0 = real time, N = N× real time, 0 = as fast as possible with back-pressure (nothing is
    /// dropped for a consumer whose process is alive; a dead one, or a hung one once the
    /// supervisor has killed it, is skipped and what it misses is counted).
    pub real_time_factor: f64,
    /// With factor 0: longest wait for a full subscriber queue, s (0 = as long as the consumer's
    /// process is alive, the default).
    pub backpressure_max_wait_s: f64,
    /// With factor 0: when a service loses a subscriber (a consumer died and is being restarted),
    /// wait up to this long for it to come back before publishing more on that service, s (0 =
    /// do not wait). Replaying as fast as possible, a restart then loses only what the dead
    /// instance had not processed, not everything published while it restarted.
    pub resubscribe_wait_s: f64,
    /// With factor 0: each depth cloud is published after the other messages up to this much
    /// later in data time, s (0 = strict data order). A mapper that holds the source back
    /// while it inserts a cloud then does not hold back the odometry a SLAM frame published
    /// just before is waiting for. Real-time replays keep the data order.
    pub cloud_lag_s: f64,
    /// Period of the progress log line, s (0 = off).
    pub progress_interval_s: f64,
    /// Wait this long after creating the publishers before the first message, s, waking the
    /// subscribers every 25 ms meanwhile: a subscriber attaches to a new publisher when its loop
    /// runs, and what is sent to it before that may be lost (counted as `undelivered`).
    pub connect_grace_s: f64,
    /// Simulator settings.
    pub sim: sim::SimConfig,
    /// Plaza2 replay settings.
    pub plaza2: Plaza2Settings,
    /// Stereo replay settings.
    pub stereo_vo: StereoVoSettings,
    /// Simulated stereo drive settings.
    pub stereo_sim: StereoSimSettings,
    /// Point-cloud file settings.
    pub clouds: CloudFileSettings,
    /// Depth-image settings.
    pub depth_images: DepthImageSettings,
    /// CARMEN log settings.
    pub carmen: crate::carmen::CarmenSettings,
    /// Indoor simulator settings.
    pub indoor: sim::indoor::IndoorConfig,
    /// rosbag2 replay settings.
    pub rosbag2: crate::rosbag2::Rosbag2Settings,
}

impl Default for IngestSettings {
    fn default() -> Self {
        Self {
            source: SourceKind::Sim,
            real_time_factor: 1.0,
            backpressure_max_wait_s: 0.0,
            resubscribe_wait_s: 10.0,
            progress_interval_s: 5.0,
            cloud_lag_s: 0.1,
            connect_grace_s: 1.0,
            sim: sim::SimConfig::default(),
            plaza2: Plaza2Settings::default(),
            stereo_vo: StereoVoSettings::default(),
            stereo_sim: StereoSimSettings::default(),
            clouds: CloudFileSettings::default(),
            depth_images: DepthImageSettings::default(),
            carmen: crate::carmen::CarmenSettings::default(),
            indoor: sim::indoor::IndoorConfig::default(),
            rosbag2: crate::rosbag2::Rosbag2Settings::default(),
        }
    }
}

/// Plaza2 replay.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Plaza2Settings {
    /// Directory with Plaza2_DR.txt, Plaza2_TD.txt, Plaza2_GT.txt, Plaza2_TL.txt (or another
    /// run's files under its own prefix, e.g. Plaza1_DR.txt).
    pub dir: PathBuf,
    /// The run's file prefix (`Plaza1_`); default: `Plaza2_`, else the one `*TD.txt` in `dir`.
    pub prefix: Option<String>,
    /// σ attached to every range, m.
    pub range_sigma_m: f64,
    /// Odometry noise σ of the speed, m/s, and of the heading increment per step, rad.
    pub speed_sigma_mps: f64,
    /// See `speed_sigma_mps`.
    pub turn_sigma_rad: f64,
}

impl Default for Plaza2Settings {
    fn default() -> Self {
        Self {
            dir: PathBuf::from("../algorithms/datasets/data/plaza2"),
            prefix: None,
            range_sigma_m: 1.0,
            speed_sigma_mps: 0.1,
            turn_sigma_rad: 0.01,
        }
    }
}

/// Stereo replay (files VO_calibration.txt and VO_stereo_factors_large.txt).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StereoVoSettings {
    /// Directory of the data set (read-only; it must not be committed).
    pub dir: PathBuf,
    /// Frame rate the frames are stamped at, Hz.
    pub rate_hz: f64,
    /// Pixel noise σ used for the observation covariance, px.
    pub pixel_sigma_px: f64,
    /// Pass the data set's landmark ids as feature track ids (flag `STEREO_HAS_TRACK_ID`): what
    /// a feature tracker upstream would provide. Off: consumers get points only.
    pub track_ids: bool,
}

impl Default for StereoVoSettings {
    fn default() -> Self {
        Self {
            dir: PathBuf::from("../../shared/data/stereo_vo_large"),
            rate_hz: 10.0,
            pixel_sigma_px: 0.5,
            track_ids: false,
        }
    }
}

/// The KITTI-like simulated stereo drive (`sim::road`): its settings plus whether the feature
/// track ids are passed on.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StereoSimSettings {
    /// The drive (road, rig, noise and warts; defaults: 400 frames at 10 Hz, ~700 features).
    pub drive: sim::road::RoadConfig,
    /// Pass the simulated tracker's feature track ids (flag `STEREO_HAS_TRACK_ID`).
    pub track_ids: bool,
}

/// Point-cloud files, published in order at `rate_hz`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CloudFileSettings {
    /// Files (`.dat`, `.dat.bz2` in OctoMap scan format, `.ply`).
    pub files: Vec<PathBuf>,
    /// Clouds per second.
    pub rate_hz: f64,
    /// Times to repeat the list (1 = once).
    pub repeat: u32,
}

impl Default for CloudFileSettings {
    fn default() -> Self {
        Self { files: vec![], rate_hz: 1.0, repeat: 1 }
    }
}

/// Depth images back-projected to clouds ([2D3D] eq 6-8).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DepthImageSettings {
    /// Image files (16-bit PNG, or raw little-endian u16 with `raw_width`/`raw_height`).
    pub files: Vec<PathBuf>,
    /// Frames per second.
    pub rate_hz: f64,
    /// Focal lengths and principal point, px.
    pub fx_px: f64,
    /// See `fx_px`.
    pub fy_px: f64,
    /// See `fx_px`.
    pub cx_px: f64,
    /// See `fx_px`.
    pub cy_px: f64,
    /// Raw depth units per metre (1000 for millimetres).
    pub depth_scale: f64,
    /// Depths outside [min, max] are skipped, m.
    pub min_depth_m: f64,
    /// See `min_depth_m`.
    pub max_depth_m: f64,
    /// Use every k-th pixel in both directions.
    pub stride: u32,
    /// Size of raw images, px.
    pub raw_width: u32,
    /// See `raw_width`.
    pub raw_height: u32,
}

impl Default for DepthImageSettings {
    fn default() -> Self {
        Self {
            files: vec![],
            rate_hz: 5.0,
            fx_px: 525.0,
            fy_px: 525.0,
            cx_px: 319.5,
            cy_px: 239.5,
            depth_scale: 1000.0,
            min_depth_m: 0.1,
            max_depth_m: 10.0,
            stride: 1,
            raw_width: 0,
            raw_height: 0,
        }
    }
}

/// Most points in one cloud.
pub const MAX_CLOUD_POINTS: usize = 4_000_000;

impl ProcessSettings for IngestSettings {
    fn shm_estimate_bytes(&self, extra_subscribers: usize) -> u64 {
        let points = match self.source {
            SourceKind::Sim => {
                let d = &self.sim.sensors.depth_camera;
                if d.rate_hz > 0.0 { (d.width_px * d.height_px) as usize } else { 0 }
            }
            SourceKind::Clouds => 400_000,
            SourceKind::Indoor => (self.indoor.depth.width_px * self.indoor.depth.height_px) as usize,
            SourceKind::DepthImages => 640 * 480,
            SourceKind::Rosbag2
                if self.rosbag2.routes.iter().any(|r| r.service == ros2_interop::route::InService::Cloud) =>
            {
                300_000
            }
            _ => 0,
        };
        let qos = service_spec(CLOUD).expect("cloud service is in the contract").qos;
        let chunk = (points.max(1) * size_of::<shared_types::CloudPoint>()).next_power_of_two() as u64;
        chunk * qos.with_extra(extra_subscribers).chunks_per_publisher() as u64 + (4 << 20)
    }
}

impl Validate for IngestSettings {
    fn validate(&self, issues: &mut Issues) {
        let rtf = self.real_time_factor;
        issues.check(rtf.is_finite() && rtf >= 0.0, "real_time_factor", "must be >= 0 (0 = as fast as possible)");
        issues.check(
            self.backpressure_max_wait_s.is_finite() && self.backpressure_max_wait_s >= 0.0,
            "backpressure_max_wait_s",
            "must be >= 0 (0 = as long as the consumer is alive)",
        );
        issues.check(
            self.resubscribe_wait_s.is_finite() && self.resubscribe_wait_s >= 0.0,
            "resubscribe_wait_s",
            "must be >= 0 (0 = do not wait)",
        );
        issues.check(
            self.connect_grace_s.is_finite() && self.connect_grace_s >= 0.0,
            "connect_grace_s",
            "must be >= 0",
        );
        issues.check(
            self.cloud_lag_s.is_finite() && (0.0..=10.0).contains(&self.cloud_lag_s),
            "cloud_lag_s",
            "must be 0..=10 s (0 = strict data order)",
        );
        issues.check(self.progress_interval_s >= 0.0, "progress_interval_s", "must be >= 0");
        match self.source {
            SourceKind::Sim => {
                issues.nested("sim", &self.sim);
            }
            SourceKind::Plaza2 => {
                issues.check(self.plaza2.range_sigma_m > 0.0, "plaza2.range_sigma_m", "must be > 0");
            }
            SourceKind::StereoSim => {
                issues.nested("stereo_sim.drive", &self.stereo_sim.drive);
            }
            SourceKind::StereoVo => {
                issues.check(self.stereo_vo.rate_hz > 0.0, "stereo_vo.rate_hz", "must be > 0");
                issues.check(self.stereo_vo.pixel_sigma_px > 0.0, "stereo_vo.pixel_sigma_px", "must be > 0");
            }
            SourceKind::Clouds => {
                issues.check(!self.clouds.files.is_empty(), "clouds.files", "no files");
                issues.check(self.clouds.rate_hz > 0.0, "clouds.rate_hz", "must be > 0");
                issues.check(self.clouds.repeat >= 1, "clouds.repeat", "must be >= 1");
            }
            SourceKind::Carmen => issues.nested("carmen", &self.carmen),
            SourceKind::Rosbag2 => issues.nested("rosbag2", &self.rosbag2),
            SourceKind::Indoor => {
                issues.nested("indoor", &self.indoor);
            }
            SourceKind::DepthImages => {
                let d = &self.depth_images;
                issues.check(!d.files.is_empty(), "depth_images.files", "no files");
                issues.check(d.rate_hz > 0.0, "depth_images.rate_hz", "must be > 0");
                issues.check(d.fx_px > 0.0 && d.fy_px > 0.0, "depth_images.fx_px", "focal lengths must be > 0");
                issues.check(d.depth_scale > 0.0, "depth_images.depth_scale", "must be > 0");
                issues.check(d.min_depth_m < d.max_depth_m, "depth_images.max_depth_m", "must exceed min_depth_m");
                issues.check(d.stride >= 1, "depth_images.stride", "must be >= 1");
            }
        }
    }
}

/// Resolves a settings path against the config file's directory.
pub fn resolve(config_dir: &Path, p: &Path) -> PathBuf {
    if p.is_absolute() { p.to_path_buf() } else { config_dir.join(p) }
}

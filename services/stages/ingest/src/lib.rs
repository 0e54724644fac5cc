//! Ingest: turns sensor data into pipeline messages (EQUATIONS §1, §2, §5, §7).
//!
//! A [`Source`] yields [`Item`]s in data-time order: the built-in simulator ([`sim`]), or replays
//! of real data (Plaza2 odometry and beacon ranges, stereo landmark observations in the
//! `stereo_vo_large` format, point-cloud files, depth images, CARMEN 2-D laser logs). The process paces them on the data
//! clock ([`Pacer`]: real time, N× or as fast as possible with back-pressure), publishes each on its
//! service, reports progress, and ends with an end-of-stream message. This library holds the pure
//! parts (settings, sources, conversions, pacing); [`stage::IngestStage`] is the stage around
//! them; `main.rs` one line.

pub mod carmen;
pub mod file_sources;
pub mod indoor;
pub mod plaza2;
pub mod progress;
pub mod reorder;
pub mod rosbag2;
pub mod settings;
pub mod sim_source;
pub mod sources;
pub mod stage;
pub mod stereo_sim;
pub mod stereo_vo;
pub mod summary;

use std::time::{Duration, Instant};

pub use file_sources::{CloudFileSource, DepthImageSource};
pub use plaza2::Plaza2Source;
pub use progress::Progress;
pub use settings::*;
pub use sim_source::SimSource;
pub use sources::*;
pub use stereo_sim::StereoSimSource;
pub use stereo_vo::StereoVoSource;

pub use pipeline_runtime::restart::{ENV_RESTARTS, is_restart};

/// Maps data time to wall-clock deadlines for a real-time factor.
#[derive(Debug, Clone, Copy)]
pub struct Pacer {
    /// 1.0 = real time, N = N× faster, 0 = as fast as possible.
    pub real_time_factor: f64,
    start: Option<(Instant, u64)>,
}

impl Pacer {
    /// A pacer for `real_time_factor` (0 = no pacing).
    pub fn new(real_time_factor: f64) -> Self {
        Self { real_time_factor, start: None }
    }

    /// When the item stamped `stamp_ns` is due; the first item is due at once and anchors the
    /// data clock to the wall clock. `None` when there is no pacing.
    pub fn due(&mut self, stamp_ns: u64, now: Instant) -> Option<Instant> {
        if self.real_time_factor <= 0.0 {
            return None;
        }
        let (wall0, data0) = *self.start.get_or_insert((now, stamp_ns));
        let data_s = stamp_ns.saturating_sub(data0) as f64 / 1e9;
        Some(wall0 + Duration::from_secs_f64(data_s / self.real_time_factor))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pacer_scales_data_time_by_the_real_time_factor() {
        let t0 = Instant::now();
        let mut p = Pacer::new(2.0);
        assert_eq!(p.due(10_000_000_000, t0), Some(t0));
        assert_eq!(p.due(12_000_000_000, t0 + Duration::from_secs(5)), Some(t0 + Duration::from_secs(1)));
        let mut afap = Pacer::new(0.0);
        assert_eq!(afap.due(5, t0), None);
    }

    #[test]
    fn ground_truth_is_on_disk_as_soon_as_the_source_knows_it() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = sim::SimConfig::default();
        config.mission.max_duration_s = 20.0;
        let mut source = SimSource::new(config, dir.path()).unwrap();
        let mut truth = TruthFile::create(dir.path()).unwrap();
        let mut items = 0;
        while items < 50 {
            source.next_item().unwrap().unwrap();
            truth.update(&source).unwrap();
            items += 1;
        }
        // Mid-run: the file holds exactly what the simulator has produced, every line whole.
        let mut known = vec![];
        source.truth(0, &mut known);
        assert!(!known.is_empty());
        let on_disk = geometry::tum::read_tum(truth.path()).unwrap();
        assert_eq!(on_disk.len(), known.len());
        assert_eq!(truth.written(), known.len());
        assert!((on_disk.last().unwrap().0 - known.last().unwrap().0).abs() < 1e-9);
        while source.next_item().unwrap().is_some() {
            truth.update(&source).unwrap();
        }
        truth.update(&source).unwrap();
        let mut all = vec![];
        source.truth(0, &mut all);
        assert!(all.len() > known.len());
        assert_eq!(geometry::tum::read_tum(truth.path()).unwrap().len(), all.len());
        assert_eq!(truth.update(&source).unwrap(), 0, "nothing new, nothing written");
    }
}

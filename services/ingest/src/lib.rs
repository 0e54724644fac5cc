//! Ingest: turns sensor data into pipeline messages (SPEC §1, §2, §5, §7).
//!
//! A [`Source`] yields [`Item`]s in data-time order: the built-in simulator ([`sim`]), or replays
//! of real data (Plaza2 odometry and beacon ranges, stereo landmark observations in the
//! `stereo_vo_large` format, point-cloud files, depth images). The process paces them on the data
//! clock ([`Pacer`]: real time, N× or as fast as possible with back-pressure), publishes each on its
//! service, reports progress, and ends with an end-of-stream message. This library holds the pure
//! parts (settings, sources, conversions, pacing); `main.rs` is the wiring.

pub mod progress;
pub mod settings;
pub mod sources;

use std::time::{Duration, Instant};

pub use progress::{Progress, ProgressFile};
pub use settings::*;
pub use sources::*;

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
}

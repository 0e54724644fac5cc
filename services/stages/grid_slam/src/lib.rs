//! The `grid_slam` process ([2D3D] §III.A-B, docs/EQUATIONS.md §8): laser scans and planar odometry in, the
//! [`grid_slam::GridSlam`] filter in the middle, poses, particles and the occupancy grid out.
//!
//! This library holds the settings and the pure part, [`ScanQueue`]: scans wait until the
//! odometry has reached their stamp (interpolated there), in data time, so a replay gives the same
//! result however loaded the machine is; bad input is counted by kind and never stops the run.
//! [`stage::GridSlamStage`] is the stage around it; `main.rs` one line.

pub mod stage;
pub mod summary;

use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;

use grid_slam::backend::BackEndConfig;
use grid_slam::{GridSlamConfig, Pose2};
use pipeline_runtime::Validate;
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};

/// Settings of the `grid_slam` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridSlamSettings {
    /// The filter (particles, resolution, update distances, matcher, motion noise...): every key
    /// is documented in `algorithms/grid_slam/src/filter.rs`.
    pub filter: GridSlamConfig,
    /// What runs behind the filter: `"pose_graph"` (default) closes loops over the filter's
    /// final path at the end of the run (submaps, branch-and-bound loop search, sparse
    /// optimisation with a robust kernel; `algorithms/grid_slam/src/backend.rs`) and writes the
    /// grid and `grid_slam.tum` from the optimised poses; `"none"` writes the filter's own.
    pub back_end: BackEndKind,
    /// The pose-graph back end's settings (every key documented in
    /// `algorithms/grid_slam/src/backend.rs`).
    pub pose_graph: BackEndConfig,
    /// Longest a scan waits for odometry up to its stamp, in data time, s: once a later scan is
    /// this far past it and the odometry is not, the scan goes with the latest odometry (counted).
    pub odometry_wait_s: f64,
    /// Publish the best particle's grid every this many seconds of data time (0: only at the end).
    pub grid_every_s: f64,
    /// Publish the particles at every filter update.
    pub publish_particles: bool,
    /// Margin of unknown cells around the known map in the outputs.
    pub grid_margin_cells: i32,
    /// Ground truth to evaluate against at the end (TUM, relative to the output directory);
    /// skipped when missing.
    pub ground_truth: String,
    /// A relations file (Kümmerle et al. 2009) to score the trajectory against at the end,
    /// relative to the config's directory; skipped when empty or missing.
    pub relations: PathBuf,
    /// Seconds added to the trajectory's stamps to reach the relations' clock.
    pub relations_offset_s: f64,
    /// Snapshot the filter (the best particle's map and pose, the trajectory so far) into the
    /// runtime's restart state every this many seconds of data time, so a restarted instance
    /// goes on from there instead of from an empty map (0: never).
    pub snapshot_every_s: f64,
    /// `grid_slam.tum` also holds a pose at every odometry stamp between two scans: the
    /// odometry's motion from the scan before, with its disagreement with the scan after spread
    /// over the interval (`algorithms/grid_slam/src/densify.rs`). Odometry often runs faster than
    /// the laser (the subsampled Intel and ACES logs: a scan every 2-3 s, odometry every 0.2 s),
    /// and a trajectory read at a stamp between scans is then more than a straight line. The
    /// odometry is kept for the whole run (32 bytes a sample). `false`: the scans' poses only.
    pub trajectory_between_scans: bool,
}

impl Default for GridSlamSettings {
    fn default() -> Self {
        Self {
            filter: GridSlamConfig::default(),
            back_end: BackEndKind::PoseGraph,
            pose_graph: BackEndConfig::default(),
            odometry_wait_s: 0.5,
            grid_every_s: 5.0,
            publish_particles: true,
            grid_margin_cells: 5,
            ground_truth: "ground_truth.tum".into(),
            relations: PathBuf::new(),
            relations_offset_s: 0.0,
            snapshot_every_s: 30.0,
            trajectory_between_scans: true,
        }
    }
}

impl ProcessSettings for GridSlamSettings {
    fn shm_estimate_bytes(&self, _extra_subscribers: usize) -> u64 {
        // The grid service: 1 MiB initial slices, a few in flight.
        8 << 20
    }
}

impl Validate for GridSlamSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.nested("filter", &self.filter);
        issues.nested("pose_graph", &self.pose_graph);
        issues.check(
            self.odometry_wait_s.is_finite() && self.odometry_wait_s >= 0.0,
            "odometry_wait_s",
            "must be >= 0",
        );
        issues.check(
            self.grid_every_s.is_finite() && self.grid_every_s >= 0.0,
            "grid_every_s",
            "must be >= 0 (0: only at the end)",
        );
        issues.check(self.grid_margin_cells >= 0, "grid_margin_cells", "must be >= 0");
        issues.check(self.relations_offset_s.is_finite(), "relations_offset_s", "must be finite");
        issues.check(
            self.snapshot_every_s.is_finite() && self.snapshot_every_s >= 0.0,
            "snapshot_every_s",
            "must be >= 0 (0: no snapshots)",
        );
    }
}

/// The back end behind the filter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum BackEndKind {
    /// Pose graph with loop closures (Hess et al. 2016), run at the end.
    PoseGraph,
    /// The filter's best particle only ([2D3D] as published).
    None,
}

/// Most odometry samples kept while no scan takes them.
pub const MAX_ODOMETRY: usize = 1 << 16;

/// One scan waiting for its odometry.
#[derive(Debug, Clone, PartialEq)]
pub struct PendingScan {
    /// Stamp, ns.
    pub stamp_ns: u64,
    /// origin_ns of the message.
    pub origin_ns: u64,
    /// Ranges, m.
    pub ranges: Vec<f32>,
}

/// Scans and odometry in stamp order, paired by interpolation.
#[derive(Debug, Default)]
pub struct ScanQueue {
    odometry: VecDeque<(u64, Pose2)>,
    scans: VecDeque<PendingScan>,
    /// Newest scan stamp pushed, ns.
    newest_scan_ns: Option<u64>,
    /// `newest_scan_ns` at the last [`ScanQueue::settle`]: the data-time evidence that odometry
    /// has stalled.
    settled_scan_ns: Option<u64>,
    /// Rejected inputs by kind.
    pub rejected: BTreeMap<&'static str, u64>,
}

fn lerp(a: &(u64, Pose2), b: &(u64, Pose2), t: u64) -> Pose2 {
    let f = if b.0 == a.0 { 1.0 } else { (t - a.0) as f64 / (b.0 - a.0) as f64 };
    let (p, q) = (a.1, b.1);
    Pose2 {
        x_m: p.x_m + f * (q.x_m - p.x_m),
        y_m: p.y_m + f * (q.y_m - p.y_m),
        theta_rad: omni_wrap(p.theta_rad + f * omni_wrap(q.theta_rad - p.theta_rad)),
    }
}

fn omni_wrap(a: f64) -> f64 {
    let w = a.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI { w - std::f64::consts::TAU } else { w }
}

impl ScanQueue {
    fn reject(&mut self, kind: &'static str) {
        *self.rejected.entry(kind).or_default() += 1;
    }

    /// An odometry sample; one not after the previous, or not finite, is rejected (counted).
    /// Returns whether it was kept.
    pub fn push_odometry(&mut self, stamp_ns: u64, pose: Pose2) -> bool {
        if !(pose.x_m.is_finite() && pose.y_m.is_finite() && pose.theta_rad.is_finite()) {
            self.reject("odometry_not_finite");
            return false;
        }
        if self.odometry.back().is_some_and(|(t, _)| *t >= stamp_ns) {
            self.reject("odometry_stamp_not_increasing");
            return false;
        }
        self.odometry.push_back((stamp_ns, pose));
        // Odometry without scans (a laser that stopped) must not grow without bound: 65,536
        // samples are 22 min at 50 Hz.
        if self.odometry.len() > MAX_ODOMETRY {
            self.odometry.pop_front();
            self.reject("odometry_buffer_overflow");
        }
        true
    }

    /// A scan; one not after the previous queued scan is rejected (counted).
    pub fn push_scan(&mut self, scan: PendingScan) -> bool {
        if self.scans.back().is_some_and(|s| s.stamp_ns >= scan.stamp_ns) {
            self.reject("scan_stamp_not_increasing");
            return false;
        }
        self.newest_scan_ns = Some(scan.stamp_ns);
        self.scans.push_back(scan);
        true
    }

    /// Takes the scans pushed so far as evidence for the data-time rule of [`ScanQueue::pop`];
    /// call it before receiving odometry. A source replaying in stamp order as fast as it can
    /// publishes between the two receives: scans received after the odometry may run ahead of
    /// odometry that was published before them, but after the odometry was received. Scans
    /// received before the odometry cannot: the odometry up to them has arrived with it.
    pub fn settle(&mut self) {
        self.settled_scan_ns = self.newest_scan_ns;
    }

    /// Scans waiting.
    pub fn pending(&self) -> usize {
        self.scans.len()
    }

    /// The next scan that can go, with its odometry: when the odometry has reached its stamp
    /// (interpolated), or — with `flush` (the inputs ended) or once a later scan known at the
    /// last [`ScanQueue::settle`] is `wait_ns` past it — with the latest odometry (counted as `scans_with_stale_odometry`). A scan before
    /// the first odometry sample, or with none at all when it must go, is dropped (counted).
    pub fn pop(&mut self, wait_ns: u64, flush: bool) -> Option<(PendingScan, Pose2)> {
        loop {
            let scan = self.scans.front()?;
            let t = scan.stamp_ns;
            let newest_scan = self.settled_scan_ns.unwrap_or(t).max(t);
            let i = self.odometry.partition_point(|(s, _)| *s < t);
            let pose = if let Some(b) = self.odometry.get(i) {
                if b.0 == t {
                    Some(b.1)
                } else if i == 0 {
                    // Odometry starts after this scan: nothing to place it with.
                    self.scans.pop_front();
                    self.reject("scans_before_the_first_odometry");
                    continue;
                } else {
                    Some(lerp(&self.odometry[i - 1], b, t))
                }
            } else if flush || newest_scan.saturating_sub(t) >= wait_ns.max(1) {
                match self.odometry.back() {
                    Some(last) => {
                        *self.rejected.entry("scans_with_stale_odometry").or_default() += 1;
                        Some(last.1)
                    }
                    None => {
                        self.scans.pop_front();
                        self.reject("scans_without_odometry");
                        continue;
                    }
                }
            } else {
                return None;
            };
            let scan = self.scans.pop_front()?;
            // Keep one odometry sample at or before the next scan.
            while self.odometry.len() > 1 && self.odometry[1].0 <= scan.stamp_ns {
                self.odometry.pop_front();
            }
            return pose.map(|p| (scan, p));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan(t: u64) -> PendingScan {
        PendingScan { stamp_ns: t, origin_ns: 0, ranges: vec![1.0] }
    }

    fn at(x: f64) -> Pose2 {
        Pose2 { x_m: x, y_m: 0.0, theta_rad: 0.0 }
    }

    #[test]
    fn scans_wait_for_odometry_and_get_it_interpolated() {
        let mut q = ScanQueue::default();
        q.push_odometry(100, at(1.0));
        q.push_scan(scan(150));
        assert_eq!(q.pop(1000, false), None, "odometry has not reached 150 yet");
        q.push_odometry(200, at(2.0));
        let (s, p) = q.pop(1000, false).expect("ready");
        assert_eq!((s.stamp_ns, p.x_m), (150, 1.5));
        // Exact stamps pair exactly.
        q.push_scan(scan(200));
        assert_eq!(q.pop(1000, false).map(|(_, p)| p.x_m), Some(2.0));
    }

    #[test]
    fn stalled_odometry_releases_scans_in_data_time_and_bad_input_is_counted() {
        let mut q = ScanQueue::default();
        q.push_odometry(100, at(1.0));
        q.push_scan(scan(200));
        q.push_scan(scan(250));
        assert_eq!(q.pop(100, false), None);
        q.push_scan(scan(300));
        assert_eq!(q.pop(100, false), None, "300 came after the odometry was received: not yet evidence");
        q.settle();
        assert_eq!(q.pop(100, false).map(|(s, p)| (s.stamp_ns, p.x_m)), Some((200, 1.0)));
        assert!(!q.push_scan(scan(300)), "a repeated stamp");
        assert!(!q.push_odometry(50, at(0.0)), "odometry going back");
        assert!(!q.push_odometry(400, Pose2 { x_m: f64::NAN, ..at(0.0) }));
        assert_eq!(q.pop(100, true).map(|(s, _)| s.stamp_ns), Some(250));
        assert_eq!(q.pop(100, true).map(|(s, _)| s.stamp_ns), Some(300));
        assert_eq!(q.rejected.get("scans_with_stale_odometry"), Some(&3));
        assert_eq!(q.rejected.get("scan_stamp_not_increasing"), Some(&1));
        assert_eq!(q.rejected.get("odometry_stamp_not_increasing"), Some(&1));
        assert_eq!(q.rejected.get("odometry_not_finite"), Some(&1));
        let mut empty = ScanQueue::default();
        empty.push_scan(scan(10));
        assert_eq!(empty.pop(0, true), None);
        assert_eq!(empty.rejected.get("scans_without_odometry"), Some(&1));
    }
}

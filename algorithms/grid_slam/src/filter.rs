//! The Rao-Blackwellised particle filter (docs/EQUATIONS.md §8, Grisetti et al. 2007).
//!
//! Each particle holds a pose, a log-weight, its own [`Grid`] (tiles shared copy-on-write with its
//! relatives) and its path. A filter *update* runs when the odometry has moved by
//! `linear_update_m` or turned by `angular_update_rad` since the last one: every particle
//! scan-matches the scan against its own map from its odometry prediction, draws its new pose from
//! a Gaussian fitted around the match (weighting the points by likelihood × motion model) and
//! multiplies its weight by that Gaussian's normaliser η; the particles are resampled
//! (systematic) only when N_eff falls below `resample_threshold`·N; each particle then writes the
//! scan into its map at its new pose. Between updates every scan is matched against the best
//! particle's map (tracking), so a pose is reported for every scan; those poses are kept relative
//! to the particle's pose at the preceding update, so the final trajectory follows the final best
//! particle's path (loop closures included) at every scan.

use crate::GridSlamError;
pub use crate::config::{GridSlamConfig, MotionNoise, ProposalLikelihood, ScanGeometry};
use crate::grid::{Grid, LogOddsParams};
use crate::matcher::{self, BeamPoint, ScanPoints};
use omni::{Pose2, wrap_angle};
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rand_xoshiro::Xoshiro256PlusPlus;
use std::sync::Arc;
use validation::{Issues, Validate};

/// A node of a particle's path: its pose at one filter update.
#[derive(Debug)]
struct PathNode {
    update: u32,
    pose: Pose2,
    parent: Option<Arc<PathNode>>,
}

impl Drop for PathNode {
    // Long paths drop iteratively, not by recursion.
    fn drop(&mut self) {
        let mut next = self.parent.take();
        while let Some(node) = next {
            match Arc::try_unwrap(node) {
                Ok(mut n) => next = n.parent.take(),
                Err(_) => break,
            }
        }
    }
}

#[derive(Debug, Clone)]
struct Particle {
    pose: Pose2,
    log_weight: f64,
    grid: Grid,
    path: Arc<PathNode>,
    /// The particle of the first set (or of the restart) this one descends from: how many
    /// distinct ones are left says how many hypotheses the set still carries.
    ancestor: u32,
    /// The particle it descends from of the set [`LINEAGE_WINDOW`] updates back at most.
    window_ancestor: u32,
}

/// Updates over which [`GridSlam::lineages`] counts the lineages that survived: about 50 m or
/// 25 turns at the default update thresholds, the length of a corridor loop.
pub const LINEAGE_WINDOW: u32 = 50;

/// How one scan went.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanOutcome {
    /// The pose reported for this scan (`map_from_body`).
    pub pose: Pose2,
    /// Whether the particles were updated at this scan.
    pub updated: bool,
    /// Whether they were resampled.
    pub resampled: bool,
    /// N_eff after the update (before resampling), or the last value.
    pub n_eff: f64,
    /// Beams of this scan that were NaN, negative or below the minimum range (skipped).
    pub invalid_beams: usize,
    /// Whether the tracking match of this scan failed (the pose is then dead reckoning).
    pub match_failed: bool,
    /// The filter update this scan belongs to (the update it made, or the last one before it):
    /// its index in [`GridSlam::node_path`].
    pub update: u32,
}

/// Counts kept over a run.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GridSlamStats {
    /// Scans processed.
    pub scans: u64,
    /// Filter updates.
    pub updates: u64,
    /// Resamplings.
    pub resamples: u64,
    /// Beams skipped as NaN, negative or below the minimum range.
    pub invalid_beams: u64,
    /// Per-particle matches that failed at updates (motion model used instead).
    pub proposal_fallbacks: u64,
    /// Tracking matches that failed (dead reckoning used for that scan).
    pub tracking_failures: u64,
    /// Tiles written at updates that became deltas over another particle's like tile.
    pub shared_tiles: u64,
    /// Scan matches (with the proposal's lattice) at updates: one for each group of copies of
    /// a particle, which share it, so fewer than particles × updates after resamplings.
    #[serde(default)]
    pub matches: u64,
}

/// How peaked the weights were over a run ([`GridSlam::n_eff_summary`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct NeffSummary {
    /// Filter updates (one N_eff each).
    pub updates: usize,
    /// Mean of N_eff / N.
    pub mean_share: f64,
    /// Its 10th percentile.
    pub p10_share: f64,
    /// Its median.
    pub median_share: f64,
    /// Particles of the first set with descendants at the end ([`GridSlam::distinct_ancestors`]).
    pub distinct_ancestors: usize,
    /// Mean of [`GridSlam::lineages`]: particles with descendants [`LINEAGE_WINDOW`] updates
    /// later (`None` before the first window ends).
    pub lineages_mean: Option<f64>,
}

/// Memory held by the particles' maps.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct MemoryStats {
    /// Bytes of the distinct tiles and deltas over all particles.
    pub bytes: usize,
    /// Bytes of the best particle's map alone.
    pub best_bytes: usize,
    /// bytes / best_bytes: what N particles cost against one map.
    pub ratio: f64,
}

#[derive(Debug, Clone, Copy)]
struct ScanRecord {
    stamp_s: f64,
    update: u32,
    rel: Pose2,
}

/// What [`GridSlam::snapshot`] keeps: the best particle (pose, map), the odometry and clock it
/// was at, the trajectory so far, and the counters.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
struct Snapshot {
    version: u32,
    resolution_m: f64,
    geometry: ScanGeometry,
    updates: u32,
    last_update_odom: Pose2,
    last_stamp_s: f64,
    pose: Pose2,
    rel: Pose2,
    history: Vec<(f64, Pose2)>,
    tiles: Vec<crate::grid::TileData>,
    stats: GridSlamStats,
}

const SNAPSHOT_VERSION: u32 = 2;

/// The 2-D grid SLAM filter.
pub struct GridSlam {
    cfg: GridSlamConfig,
    geom: ScanGeometry,
    dirs: Vec<(f64, f64)>,
    particles: Vec<Particle>,
    threads: usize,
    /// Copies of one particle share their match and proposal ([`copy_groups`]); `false` only
    /// in the test that checks this changes nothing.
    share_copies: bool,
    last_stamp_s: Option<f64>,
    last_update_odom: Pose2,
    updates: u32,
    records: Vec<ScanRecord>,
    best: usize,
    n_eff: f64,
    /// (stamp s, N_eff) at every update.
    n_eff_history: Vec<(f64, f64)>,
    /// Lineages that survived each window of [`LINEAGE_WINDOW`] updates.
    lineage_history: Vec<usize>,
    stats: GridSlamStats,
    peak_memory: Option<MemoryStats>,
    /// The trajectory before a restore (frozen: later loop closures do not move it).
    history: Vec<(f64, Pose2)>,
}

/// One beam prepared for the map update: its end in the body frame and whether it is a hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapBeam {
    /// The beam's end in the body frame (through the laser's mounting), m.
    pub end: (f64, f64),
    /// Whether it ends on an obstacle (a hit) or only frees space up to `end`.
    pub hit: bool,
}

/// A scan as the map and the matcher use it: the body-frame beams and the matching points.
#[derive(Debug, Clone, Default)]
pub struct PreparedScan {
    /// Beams for the map update.
    pub beams: Vec<MapBeam>,
    /// Points for matching.
    pub points: ScanPoints,
    /// The laser's origin in the body frame, m.
    pub origin: (f64, f64),
}

impl GridSlam {
    /// A filter for a laser with geometry `geom`.
    pub fn new(cfg: GridSlamConfig, geom: ScanGeometry) -> Result<Self, GridSlamError> {
        let mut issues = Issues::new();
        cfg.validate(&mut issues);
        geom.validate(&mut issues);
        issues.into_result().map_err(GridSlamError::Config)?;
        let dirs = (0..geom.beams)
            .map(|k| {
                let a = geom.angle_min_rad + k as f64 * geom.angle_increment_rad;
                (a.cos(), a.sin())
            })
            .collect();
        let threads = if cfg.threads == 0 {
            std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
        } else {
            cfg.threads
        }
        .min(cfg.particles);
        Ok(Self {
            cfg,
            geom,
            dirs,
            particles: Vec::new(),
            threads,
            share_copies: true,
            last_stamp_s: None,
            last_update_odom: Pose2::default(),
            updates: 0,
            records: Vec::new(),
            best: 0,
            n_eff: 0.0,
            n_eff_history: Vec::new(),
            lineage_history: Vec::new(),
            stats: GridSlamStats::default(),
            peak_memory: None,
            history: Vec::new(),
        })
    }

    /// The filter's state as bytes, for a restart: the best particle's pose and map (not the
    /// other particles: a restored filter starts from N copies of the best one), the odometry and
    /// stamp it was at, the trajectory so far and the counters. Empty before the first scan.
    pub fn snapshot(&self) -> Vec<u8> {
        let Some(best) = self.particles.get(self.best) else { return Vec::new() };
        let s = Snapshot {
            version: SNAPSHOT_VERSION,
            resolution_m: self.cfg.resolution_m,
            geometry: self.geom,
            updates: self.updates,
            last_update_odom: self.last_update_odom,
            last_stamp_s: self.last_stamp_s.unwrap_or(f64::NEG_INFINITY),
            pose: best.pose,
            rel: self.records.last().map(|r| r.rel).unwrap_or_default(),
            history: self.trajectory(),
            tiles: best.grid.to_tiles(),
            stats: self.stats,
        };
        // Plain data: encoding cannot fail.
        bincode::serde::encode_to_vec(&s, bincode::config::standard()).unwrap_or_default()
    }

    /// A filter from [`GridSlam::snapshot`]'s bytes, with settings `cfg` (the particle count may
    /// differ; the resolution and the laser geometry must be the snapshot's).
    pub fn restore(cfg: GridSlamConfig, bytes: &[u8]) -> Result<Self, GridSlamError> {
        let bad = |why: String| GridSlamError::Snapshot { why };
        let (s, _): (Snapshot, usize) = bincode::serde::decode_from_slice(bytes, bincode::config::standard())
            .map_err(|e| bad(format!("cannot decode: {e}")))?;
        if s.version != SNAPSHOT_VERSION {
            return Err(bad(format!("version {}, this build reads {SNAPSHOT_VERSION}", s.version)));
        }
        if (s.resolution_m - cfg.resolution_m).abs() > 1e-12 {
            return Err(bad(format!("resolution {} m, the settings say {} m", s.resolution_m, cfg.resolution_m)));
        }
        let grid = Grid::from_tiles(s.resolution_m, &s.tiles).ok_or_else(|| bad("a tile has the wrong size".into()))?;
        let mut f = GridSlam::new(cfg, s.geometry)?;
        let path = Arc::new(PathNode { update: s.updates, pose: s.pose, parent: None });
        let p = Particle { pose: s.pose, log_weight: 0.0, grid, path, ancestor: 0, window_ancestor: 0 };
        f.particles = vec![p; f.cfg.particles];
        number_ancestors(&mut f.particles);
        f.updates = s.updates;
        f.last_update_odom = s.last_update_odom;
        f.last_stamp_s = s.last_stamp_s.is_finite().then_some(s.last_stamp_s);
        f.stats = s.stats;
        f.n_eff = f.cfg.particles as f64;
        // The last scan's record continues from the restored pose; the history holds the rest.
        let mut history = s.history;
        let last = history.pop();
        f.history = history;
        if let Some((t, _)) = last {
            f.records.push(ScanRecord { stamp_s: t, update: s.updates, rel: s.rel });
        }
        f.note_memory();
        Ok(f)
    }

    /// The settings.
    pub fn config(&self) -> &GridSlamConfig {
        &self.cfg
    }

    /// The laser geometry.
    pub fn geometry(&self) -> &ScanGeometry {
        &self.geom
    }

    /// Splits a scan into matching points and map beams (body frame), counting invalid beams.
    fn prepare(&self, ranges: &[f32]) -> (ScanPoints, Vec<MapBeam>, usize) {
        let g = &self.geom;
        let lp = g.body_from_laser;
        let usable = self.cfg.usable_range_m.min(g.range_max_m);
        let res = self.cfg.resolution_m;
        let mut pts = ScanPoints::default();
        let mut beams = Vec::with_capacity(ranges.len());
        let mut invalid = 0;
        let spacing2 = self.cfg.matcher.min_point_spacing_m.powi(2);
        let mut last_kept: Option<(f64, f64)> = None;
        for (k, (&r, &(c, s))) in ranges.iter().zip(&self.dirs).enumerate() {
            let r = r as f64;
            if !r.is_finite() || r < g.range_min_m || r <= 0.0 {
                invalid += 1;
                continue;
            }
            let no_return = r >= g.range_max_m;
            if no_return && self.cfg.no_return_free_m <= 0.0 {
                continue;
            }
            let (len, hit) = if no_return {
                (self.cfg.no_return_free_m.min(usable), false)
            } else if r > usable {
                (usable, false)
            } else {
                (r, true)
            };
            let at = |d: f64| lp.compose(&Pose2 { x_m: d * c, y_m: d * s, theta_rad: 0.0 });
            let end = at(len);
            beams.push(MapBeam { end: (end.x_m, end.y_m), hit });
            if hit
                && k % self.cfg.matcher.beam_stride == 0
                && last_kept.is_none_or(|q| (q.0 - end.x_m).powi(2) + (q.1 - end.y_m).powi(2) >= spacing2)
            {
                last_kept = Some((end.x_m, end.y_m));
                let free = at((len - res).max(0.0));
                pts.points.push(BeamPoint { hit: (end.x_m, end.y_m), free: (free.x_m, free.y_m) });
            }
        }
        (pts, beams, invalid)
    }

    /// A scan's beams and matching points as the filter uses them (invalid beams dropped).
    pub fn prepare_scan(&self, ranges: &[f32]) -> PreparedScan {
        let (points, beams, _) = self.prepare(ranges);
        PreparedScan { beams, points, origin: (self.geom.body_from_laser.x_m, self.geom.body_from_laser.y_m) }
    }

    /// Writes a prepared scan into `grid` at `pose` (`map_from_body`).
    pub fn integrate(grid: &mut Grid, pose: &Pose2, origin: (f64, f64), beams: &[MapBeam], lo: &LogOddsParams) {
        let (s, c) = pose.theta_rad.sin_cos();
        let w = |q: (f64, f64)| (pose.x_m + c * q.0 - s * q.1, pose.y_m + s * q.0 + c * q.1);
        let o = w(origin);
        for b in beams {
            grid.cast(o, w(b.end), b.hit, lo);
        }
    }

    /// Processes one scan with the odometry pose at its stamp (`odom_from_body`, any fixed
    /// origin: only increments are used). `stamp_s` must increase; `ranges` must have the
    /// geometry's beam count. Invalid beams (NaN, negative, below the minimum) are skipped and
    /// counted; ranges at or above the maximum are "no return".
    pub fn process(&mut self, stamp_s: f64, odom: Pose2, ranges: &[f32]) -> Result<ScanOutcome, GridSlamError> {
        if ranges.len() != self.geom.beams {
            return Err(GridSlamError::BeamCount { expected: self.geom.beams, got: ranges.len() });
        }
        if !stamp_s.is_finite() {
            return Err(GridSlamError::Stamp { stamp_s, last_s: self.last_stamp_s.unwrap_or(f64::NAN) });
        }
        if let Some(last) = self.last_stamp_s
            && stamp_s <= last
        {
            return Err(GridSlamError::Stamp { stamp_s, last_s: last });
        }
        if !(odom.x_m.is_finite() && odom.y_m.is_finite() && odom.theta_rad.is_finite()) {
            return Err(GridSlamError::Odometry { stamp_s });
        }
        let (pts, beams, invalid) = self.prepare(ranges);
        self.last_stamp_s = Some(stamp_s);
        self.stats.scans += 1;
        self.stats.invalid_beams += invalid as u64;
        let origin = (self.geom.body_from_laser.x_m, self.geom.body_from_laser.y_m);

        if self.particles.is_empty() {
            let mut grid = Grid::new(self.cfg.resolution_m);
            Self::integrate(&mut grid, &odom, origin, &beams, &self.cfg.log_odds);
            grid.take_written();
            let path = Arc::new(PathNode { update: 0, pose: odom, parent: None });
            let p = Particle { pose: odom, log_weight: 0.0, grid, path, ancestor: 0, window_ancestor: 0 };
            self.particles = vec![p; self.cfg.particles];
            number_ancestors(&mut self.particles);
            self.last_update_odom = odom;
            self.records.push(ScanRecord { stamp_s, update: 0, rel: Pose2::default() });
            self.n_eff = self.cfg.particles as f64;
            self.note_memory();
            return Ok(ScanOutcome {
                pose: odom,
                updated: true,
                resampled: false,
                n_eff: self.n_eff,
                invalid_beams: invalid,
                match_failed: false,
                update: 0,
            });
        }

        let delta = self.last_update_odom.between(&odom);
        let moved = delta.x_m.hypot(delta.y_m) >= self.cfg.linear_update_m
            || delta.theta_rad.abs() >= self.cfg.angular_update_rad;
        let min_score = self.cfg.matcher.min_score_share * pts.points.len() as f64;
        if !moved {
            // Tracking: match against the best particle's map only.
            let best = &self.particles[self.best];
            let predicted = best.pose.compose(&delta);
            let (pose, failed) = if pts.points.is_empty() {
                (predicted, true)
            } else {
                let (m, f) = matcher::optimize(&best.grid, &pts, &predicted, &self.cfg.matcher);
                if f.score >= min_score { (m, false) } else { (predicted, true) }
            };
            if failed {
                self.stats.tracking_failures += 1;
            }
            let rel = best.pose.between(&pose);
            self.records.push(ScanRecord { stamp_s, update: self.updates, rel });
            return Ok(ScanOutcome {
                pose,
                updated: false,
                resampled: false,
                n_eff: self.n_eff,
                invalid_beams: invalid,
                match_failed: failed,
                update: self.updates,
            });
        }

        // A filter update.
        let update = self.updates + 1;
        let cfg = &self.cfg;
        let seed = cfg.seed;
        let fallbacks = std::sync::atomic::AtomicU64::new(0);
        // Copies of one particle (a resampling's picks of one parent: the same path node, pose
        // and map) get the same match and proposal: computed once for each group, by its first.
        let leaders =
            if self.share_copies { copy_groups(&self.particles) } else { (0..self.particles.len()).collect() };
        let firsts: Vec<usize> = (0..leaders.len()).filter(|&i| leaders[i] == i).collect();
        self.stats.matches += firsts.len() as u64;
        // Workers take the next job from a shared queue (jobs differ in work: a fixed split left
        // one core idle at the end of most updates): the groups' proposals, then each
        // particle's draw and map update.
        let workers = self.threads.min(self.particles.len()).max(1);
        let mut proposals = vec![Proposal::MotionModel; self.particles.len()];
        {
            let particles = &self.particles;
            let queue = std::sync::Mutex::new(firsts.iter().copied());
            let done: Vec<Vec<(usize, Proposal)>> = std::thread::scope(|scope| {
                let handles: Vec<_> = (0..workers.min(firsts.len()).max(1))
                    .map(|_| {
                        let (pts, delta, queue) = (&pts, &delta, &queue);
                        scope.spawn(move || {
                            let mut out = Vec::new();
                            loop {
                                // A poisoned lock means another worker panicked: the scope
                                // re-raises that.
                                let next = match queue.lock() {
                                    Ok(mut q) => q.next(),
                                    Err(_) => None,
                                };
                                let Some(index) = next else { break };
                                let p = &particles[index];
                                out.push((index, proposal(cfg, &p.pose, &p.grid, delta, pts, min_score)));
                            }
                            out
                        })
                    })
                    .collect();
                handles.into_iter().map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))).collect()
            });
            for (index, pr) in done.into_iter().flatten() {
                proposals[index] = pr;
            }
        }
        let proposals = &proposals;
        let leaders = &leaders;
        let queue = std::sync::Mutex::new(self.particles.iter_mut().enumerate());
        std::thread::scope(|scope| {
            for _ in 0..workers {
                let (pts, beams, fallbacks, queue, delta) = (&pts, &beams, &fallbacks, &queue, &delta);
                scope.spawn(move || {
                    loop {
                        // A poisoned lock means another worker panicked: the scope re-raises that.
                        let next = match queue.lock() {
                            Ok(mut q) => q.next(),
                            Err(_) => None,
                        };
                        let Some((index, p)) = next else { break };
                        let mut rng = Xoshiro256PlusPlus::seed_from_u64(mix(seed, update as u64, index as u64));
                        let (pose, log_eta, fell_back) = draw(cfg, &proposals[leaders[index]], p, delta, pts, &mut rng);
                        if fell_back {
                            fallbacks.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        }
                        p.pose = pose;
                        p.log_weight += log_eta;
                        Self::integrate(&mut p.grid, &pose, origin, beams, &cfg.log_odds);
                        p.path = Arc::new(PathNode { update, pose, parent: Some(p.path.clone()) });
                    }
                });
            }
        });
        self.stats.proposal_fallbacks += fallbacks.into_inner();
        self.updates = update;
        self.stats.updates += 1;
        self.last_update_odom = odom;

        // Normalise (tempered), N_eff, resample.
        let gain = 1.0 / (self.cfg.obs_gain * self.particles.len() as f64);
        let max = self.particles.iter().map(|p| p.log_weight).fold(f64::NEG_INFINITY, f64::max);
        let w: Vec<f64> = self.particles.iter().map(|p| ((p.log_weight - max) * gain).exp()).collect();
        let sum: f64 = w.iter().sum();
        let w: Vec<f64> = w.iter().map(|x| x / sum).collect();
        self.n_eff = 1.0 / w.iter().map(|x| x * x).sum::<f64>();
        self.n_eff_history.push((stamp_s, self.n_eff));
        self.best = w.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|(i, _)| i).unwrap_or(0);
        let mut resampled = false;
        if self.n_eff < self.cfg.resample_threshold * self.particles.len() as f64 {
            let mut rng = Xoshiro256PlusPlus::seed_from_u64(mix(seed ^ 0x5eed, update as u64, u64::MAX));
            let picks = systematic_resample(&w, rng.random::<f64>());
            let old = std::mem::take(&mut self.particles);
            self.particles = picks
                .iter()
                .map(|&i| {
                    let mut p = old[i].clone();
                    p.log_weight = 0.0;
                    p
                })
                .collect();
            self.best = picks.iter().position(|&i| i == self.best).unwrap_or(0);
            self.stats.resamples += 1;
            resampled = true;
        }
        if update.is_multiple_of(LINEAGE_WINDOW) {
            self.lineage_history.push(distinct(&self.particles, |p| p.window_ancestor));
            for (i, p) in self.particles.iter_mut().enumerate() {
                p.window_ancestor = i as u32;
            }
        }
        // Tiles the particles wrote alike become deltas over one another's.
        self.stats.shared_tiles +=
            crate::grid::share_written_tiles(self.particles.iter_mut().map(|p| &mut p.grid), SHARE_MAX_CELLS) as u64;
        let pose = self.particles[self.best].pose;
        self.records.push(ScanRecord { stamp_s, update, rel: Pose2::default() });
        self.note_memory();
        Ok(ScanOutcome {
            pose,
            updated: true,
            resampled,
            n_eff: self.n_eff,
            invalid_beams: invalid,
            match_failed: false,
            update,
        })
    }

    fn note_memory(&mut self) {
        let m = self.memory();
        if self.peak_memory.is_none_or(|p| m.bytes > p.bytes) {
            self.peak_memory = Some(m);
        }
    }

    /// Memory of the particles' maps now.
    pub fn memory(&self) -> MemoryStats {
        let mut seen = std::collections::HashSet::new();
        let bytes: usize = self.particles.iter().map(|p| p.grid.add_bytes(&mut seen)).sum();
        let best_bytes = self.particles.get(self.best).map_or(0, |p| p.grid.bytes());
        MemoryStats { bytes, best_bytes, ratio: if best_bytes == 0 { 0.0 } else { bytes as f64 / best_bytes as f64 } }
    }

    /// The memory at its peak over the run (by bytes).
    pub fn peak_memory(&self) -> Option<MemoryStats> {
        self.peak_memory
    }

    /// Counters.
    pub fn stats(&self) -> GridSlamStats {
        self.stats
    }

    /// N_eff (the effective number of particles, 1/Σw², before any resampling) at every filter
    /// update: (scan stamp s, N_eff). Near N: the weights are flat; near 1: one particle has all
    /// the weight, and resampling leaves copies of it alone (Grisetti et al. 2007, §IV).
    pub fn n_eff_history(&self) -> &[(f64, f64)] {
        &self.n_eff_history
    }

    /// N_eff over the run as shares of N (see [`Self::n_eff_history`]); `None` before the
    /// first update.
    pub fn n_eff_summary(&self) -> Option<NeffSummary> {
        let n = self.cfg.particles as f64;
        let mut v: Vec<f64> = self.n_eff_history.iter().map(|(_, e)| e / n).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(NeffSummary {
            updates: v.len(),
            mean_share: v.iter().sum::<f64>() / v.len() as f64,
            p10_share: v[v.len() / 10],
            median_share: v[v.len() / 2],
            distinct_ancestors: self.distinct_ancestors(),
            lineages_mean: (!self.lineage_history.is_empty())
                .then(|| self.lineage_history.iter().sum::<usize>() as f64 / self.lineage_history.len() as f64),
        })
    }

    /// How many particles of the first set (or of the restart) still have descendants: the
    /// hypotheses the filter carries. 1: the set has collapsed onto one lineage, and a loop
    /// closure can only pick among its near copies.
    pub fn distinct_ancestors(&self) -> usize {
        distinct(&self.particles, |p| p.ancestor)
    }

    /// Every [`LINEAGE_WINDOW`] updates: how many particles of the set that many updates back
    /// had descendants (1..=N). Over a whole log every particle filter's set descends from one
    /// particle in the end; what decides whether a loop can be closed is how many hypotheses
    /// survive the length of a loop.
    pub fn lineages(&self) -> &[usize] {
        &self.lineage_history
    }

    /// The best particle's map.
    pub fn best_grid(&self) -> Option<&Grid> {
        self.particles.get(self.best).map(|p| &p.grid)
    }

    /// The pose of the latest scan (`map_from_body`) on the best particle.
    pub fn current_pose(&self) -> Option<Pose2> {
        let r = self.records.last()?;
        let p = self.particles.get(self.best)?;
        Some(p.pose.compose(&r.rel))
    }

    /// The particles' poses (at the latest scan, through the tracking offset) and normalised,
    /// tempered weights.
    pub fn particles(&self) -> Vec<(Pose2, f64)> {
        let rel = self.records.last().map(|r| r.rel).unwrap_or_default();
        let gain = 1.0 / (self.cfg.obs_gain * self.particles.len().max(1) as f64);
        let max = self.particles.iter().map(|p| p.log_weight).fold(f64::NEG_INFINITY, f64::max);
        let w: Vec<f64> = self.particles.iter().map(|p| ((p.log_weight - max) * gain).exp()).collect();
        let sum: f64 = w.iter().sum();
        self.particles.iter().zip(w).map(|(p, w)| (p.pose.compose(&rel), w / sum)).collect()
    }

    /// The weighted covariance of the particles' poses (x, y, θ; row-major 3×3, m², rad²).
    pub fn covariance(&self) -> [f64; 9] {
        let ps = self.particles();
        let mut mean = [0.0; 3];
        let Some(&(p0, _)) = ps.first() else { return [0.0; 9] };
        for (p, w) in &ps {
            mean[0] += w * p.x_m;
            mean[1] += w * p.y_m;
            mean[2] += w * wrap_angle(p.theta_rad - p0.theta_rad);
        }
        let mut cov = [0.0; 9];
        for (p, w) in &ps {
            let d = [p.x_m - mean[0], p.y_m - mean[1], wrap_angle(p.theta_rad - p0.theta_rad) - mean[2]];
            for r in 0..3 {
                for c in 0..3 {
                    cov[r * 3 + c] += w * d[r] * d[c];
                }
            }
        }
        cov
    }

    /// The trajectory at every processed scan along the best particle's final path
    /// (`map_from_body`, stamped with the scans' stamps).
    pub fn trajectory(&self) -> Vec<(f64, Pose2)> {
        self.trajectory_with(&self.node_path())
    }

    /// The best particle's pose at every filter update (`map_from_body`; index = update, `None`
    /// for updates before a restore): the nodes a pose-graph back end optimises.
    pub fn node_path(&self) -> Vec<Option<Pose2>> {
        let Some(best) = self.particles.get(self.best) else { return Vec::new() };
        let mut at_update = vec![None; self.updates as usize + 1];
        let mut node = Some(&best.path);
        while let Some(n) = node {
            if let Some(slot) = at_update.get_mut(n.update as usize) {
                *slot = Some(n.pose);
            }
            node = n.parent.as_ref();
        }
        at_update
    }

    /// The trajectory at every processed scan with the update poses `at_update` (as
    /// [`GridSlam::node_path`] gives them, or optimised): each scan keeps its pose relative to its
    /// update. Scans before a restore keep their frozen poses.
    pub fn trajectory_with(&self, at_update: &[Option<Pose2>]) -> Vec<(f64, Pose2)> {
        let mut out = self.history.clone();
        out.extend(self.records.iter().filter_map(|r| {
            at_update.get(r.update as usize).copied().flatten().map(|p| (r.stamp_s, p.compose(&r.rel)))
        }));
        out
    }
}

/// SplitMix64 over the seed, update and particle: independent streams per particle and update,
/// the same whatever the thread count.
/// A tile a particle wrote at an update becomes a delta over another particle's tile at the
/// same place when they differ in at most this many of its 256 cells (a delta of n cells costs
/// about 300 + 16·n bytes against a tile's 4,096).
const SHARE_MAX_CELLS: usize = 200;

fn mix(seed: u64, a: u64, b: u64) -> u64 {
    let mut z = seed ^ a.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ b.wrapping_mul(0xD1B5_4A32_D192_ED03);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Systematic resampling: N indices drawn with one uniform offset `u` in [0, 1).
pub fn systematic_resample(weights: &[f64], u: f64) -> Vec<usize> {
    let n = weights.len();
    let mut out = Vec::with_capacity(n);
    let mut c = weights.first().copied().unwrap_or(0.0);
    let mut i = 0;
    for k in 0..n {
        let target = (k as f64 + u) / n as f64;
        while target > c && i + 1 < n {
            i += 1;
            c += weights[i];
        }
        out.push(i);
    }
    out
}

/// What the improved proposal computes for one particle before its draw: the scan match, the
/// Gaussian fitted at the lattice around it and ln η. It depends only on the particle's pose and
/// map, so copies of one particle (a resampling's picks of one parent, which share its pose and
/// every tile of its map) share it: each then draws its own pose from it.
#[derive(Debug, Clone, Copy)]
enum Proposal {
    /// The match failed (or the scan has no points): the motion model, per particle.
    MotionModel,
    /// The proposal's Gaussian: its mean (μ, with θ as the match's plus an offset), its
    /// covariance and ln η.
    Gaussian { star: Pose2, mu: [f64; 3], cov: [[f64; 3]; 3], log_eta: f64 },
}

/// The improved proposal's deterministic part for a particle at `p_pose` with map `grid`
/// (Grisetti et al. 2007, docs/EQUATIONS.md §8).
fn proposal(
    cfg: &GridSlamConfig,
    p_pose: &Pose2,
    grid: &Grid,
    delta: &Pose2,
    pts: &ScanPoints,
    min_score: f64,
) -> Proposal {
    let predicted = p_pose.compose(delta);
    let sd = cfg.motion.sd(delta);
    let motion_ll = |x: &Pose2| {
        let e = predicted.between(x);
        -0.5 * ((e.x_m / sd[0]).powi(2) + (e.y_m / sd[1]).powi(2) + (e.theta_rad / sd[2]).powi(2))
    };
    if pts.points.is_empty() {
        return Proposal::MotionModel;
    }
    let (sm, sr) = (cfg.proposal_step_m, cfg.proposal_step_rad);
    // τ_j = p(z | m, x_j) · p(x_j | x', u) at a 3×3×3 lattice around the match.
    let (star, lattice) = match cfg.proposal_likelihood {
        ProposalLikelihood::Evaluated => {
            let (star, f) = matcher::optimize(grid, pts, &predicted, &cfg.matcher);
            if f.score < min_score {
                return Proposal::MotionModel;
            }
            (star, matcher::log_likelihood_lattice(grid, pts, &star, &cfg.matcher, sm, sr))
        }
        ProposalLikelihood::Modelled => {
            let (star, f, model) = matcher::optimize_modelled(grid, pts, &predicted, &cfg.matcher);
            if f.score < min_score {
                return Proposal::MotionModel;
            }
            let mut lattice = [0.0; 27];
            for (n, ll) in lattice.iter_mut().enumerate() {
                let (a, b, t) = ((n / 9) as f64 - 1.0, ((n / 3) % 3) as f64 - 1.0, (n % 3) as f64 - 1.0);
                *ll = model.at([a * sm, b * sm, t * sr]);
            }
            (star, lattice)
        }
    };
    let mut samples = Vec::with_capacity(27);
    for a in -1..=1 {
        for b in -1..=1 {
            for t in -1..=1 {
                let x = Pose2 {
                    x_m: star.x_m + a as f64 * sm,
                    y_m: star.y_m + b as f64 * sm,
                    theta_rad: wrap_angle(star.theta_rad + t as f64 * sr),
                };
                let ll = lattice[(9 * (a + 1) + 3 * (b + 1) + (t + 1)) as usize] + motion_ll(&x);
                samples.push((x, ll));
            }
        }
    }
    let max = samples.iter().map(|s| s.1).fold(f64::NEG_INFINITY, f64::max);
    let taus: Vec<f64> = samples.iter().map(|s| (s.1 - max).exp()).collect();
    let eta: f64 = taus.iter().sum();
    let log_eta = max + eta.ln();
    let mut mu = [0.0; 3];
    for ((x, _), t) in samples.iter().zip(&taus) {
        mu[0] += t * x.x_m;
        mu[1] += t * x.y_m;
        mu[2] += t * wrap_angle(x.theta_rad - star.theta_rad);
    }
    for m in &mut mu {
        *m /= eta;
    }
    let mut cov = [[0.0; 3]; 3];
    for ((x, _), t) in samples.iter().zip(&taus) {
        let d = [x.x_m - mu[0], x.y_m - mu[1], wrap_angle(x.theta_rad - star.theta_rad) - mu[2]];
        for r in 0..3 {
            for c in 0..3 {
                cov[r][c] += t * d[r] * d[c] / eta;
            }
        }
    }
    cov[0][0] += cfg.proposal_min_sd_m.powi(2);
    cov[1][1] += cfg.proposal_min_sd_m.powi(2);
    cov[2][2] += cfg.proposal_min_sd_rad.powi(2);
    Proposal::Gaussian { star, mu, cov, log_eta }
}

/// One particle's draw from `proposal` (its own `rng`): (new pose, ln η, whether it fell back to
/// the motion model).
fn draw(
    cfg: &GridSlamConfig,
    proposal: &Proposal,
    p: &Particle,
    delta: &Pose2,
    pts: &ScanPoints,
    rng: &mut Xoshiro256PlusPlus,
) -> (Pose2, f64, bool) {
    let normal = |rng: &mut Xoshiro256PlusPlus| rng.sample::<f64, _>(StandardNormal);
    let fallback = |rng: &mut Xoshiro256PlusPlus| {
        let predicted = p.pose.compose(delta);
        let sd = cfg.motion.sd(delta);
        let n = Pose2 { x_m: sd[0] * normal(rng), y_m: sd[1] * normal(rng), theta_rad: sd[2] * normal(rng) };
        let x = predicted.compose(&n);
        let ll = matcher::log_likelihood(&p.grid, pts, &x, &cfg.matcher);
        (x, ll, true)
    };
    let Proposal::Gaussian { star, mu, cov, log_eta } = *proposal else { return fallback(rng) };
    if cfg.particles == 1 {
        // One particle represents no distribution: a draw from the proposal would only add its
        // spread as noise at every update (a random walk: on the simulated ring, ATE 0.90 m drawn
        // against 0.35 m at the mean; docs/grid_slam.md). It takes the proposal's mean, as a scan
        // matcher takes its optimum.
        let x = Pose2 { x_m: mu[0], y_m: mu[1], theta_rad: wrap_angle(star.theta_rad + mu[2]) };
        return (x, log_eta, false);
    }
    let Some(l) = matcher::cholesky3(&cov) else { return fallback(rng) };
    let n = [normal(rng), normal(rng), normal(rng)];
    let dx = [l[0][0] * n[0], l[1][0] * n[0] + l[1][1] * n[1], l[2][0] * n[0] + l[2][1] * n[1] + l[2][2] * n[2]];
    let x = Pose2 { x_m: mu[0] + dx[0], y_m: mu[1] + dx[1], theta_rad: wrap_angle(star.theta_rad + mu[2] + dx[2]) };
    (x, log_eta, false)
}

/// For each particle, the first particle it is a copy of (itself if none before it is): copies
/// share their path node (a resampling's picks of one parent, the first set, a restart), and
/// with it their pose and every tile of their map.
fn copy_groups(particles: &[Particle]) -> Vec<usize> {
    let mut first: std::collections::HashMap<*const PathNode, usize> = std::collections::HashMap::new();
    particles
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let k = *first.entry(Arc::as_ptr(&p.path)).or_insert(i);
            if particles[k].pose == p.pose { k } else { i }
        })
        .collect()
}

/// Numbers the particles of a new set as their own ancestors.
fn number_ancestors(particles: &mut [Particle]) {
    for (i, p) in particles.iter_mut().enumerate() {
        p.ancestor = i as u32;
        p.window_ancestor = i as u32;
    }
}

/// Distinct values of `key` over the particles.
fn distinct(particles: &[Particle], key: fn(&Particle) -> u32) -> usize {
    let mut a: Vec<u32> = particles.iter().map(key).collect();
    a.sort_unstable();
    a.dedup();
    a.len()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matcher::MatcherParams;

    #[test]
    fn systematic_resampling_follows_the_weights() {
        let picks = systematic_resample(&[0.0, 0.5, 0.0, 0.5], 0.3);
        assert_eq!(picks, vec![1, 1, 3, 3]);
        let picks = systematic_resample(&[0.25; 4], 0.99);
        assert_eq!(picks, vec![0, 1, 2, 3]);
    }

    /// A beam at the laser's maximum (no return, as raw logs write it) adds no hit; it frees
    /// the cells along it up to `no_return_free_m`, and nothing when that is 0.
    #[test]
    fn no_return_beams_free_up_to_the_set_range_and_add_no_hit() {
        let geom = ScanGeometry {
            angle_min_rad: -0.1,
            angle_increment_rad: 0.1,
            beams: 3,
            range_min_m: 0.1,
            range_max_m: 81.83,
            body_from_laser: Pose2::default(),
        };
        let ranges = [2.0f32, 81.83, 2.0];
        for free_m in [0.0, 4.0] {
            let cfg = GridSlamConfig { particles: 1, no_return_free_m: free_m, ..Default::default() };
            let mut f = GridSlam::new(cfg, geom).expect("valid");
            f.process(1.0, Pose2::default(), &ranges).expect("scan");
            let g = f.best_grid().expect("a map");
            // Along the middle beam (θ = 0): 1 m, 3.5 m (inside 4 m), 6 m (beyond).
            let at = |x: f64| g.log_odds(g.cell_of(x, 0.01).0, g.cell_of(x, 0.01).1);
            if free_m == 0.0 {
                assert_eq!((at(1.0), at(3.5), at(6.0)), (0.0, 0.0, 0.0), "nothing written along a no-return beam");
            } else {
                assert!(at(1.0) < 0.0 && at(3.5) < 0.0, "freed up to 4 m: {} {}", at(1.0), at(3.5));
                assert!(at(4.05) <= 0.0 && at(6.0) == 0.0, "no hit at 4 m, nothing beyond");
            }
            // The returning beams still hit at 2 m.
            let (s, c) = 0.1f64.sin_cos();
            assert!(g.log_odds(g.cell_of(2.0 * c, 2.0 * s).0, g.cell_of(2.0 * c, 2.0 * s).1) > 0.0);
        }
        let bad = GridSlamConfig { no_return_free_m: -1.0, ..Default::default() };
        assert!(bad.issues().to_string().contains("no_return_free_m"));
    }

    #[test]
    fn bad_scans_are_refused_with_what_is_wrong() {
        let geom = ScanGeometry {
            angle_min_rad: -1.0,
            angle_increment_rad: 0.01,
            beams: 201,
            range_min_m: 0.1,
            range_max_m: 10.0,
            body_from_laser: Pose2::default(),
        };
        let mut f = GridSlam::new(GridSlamConfig { particles: 2, ..Default::default() }, geom).expect("valid");
        let e = f.process(1.0, Pose2::default(), &[1.0; 200]).unwrap_err();
        assert!(e.to_string().contains("201") && e.to_string().contains("200"), "{e}");
        let mut r = vec![2.0f32; 201];
        r[3] = f32::NAN;
        r[4] = -1.0;
        r[5] = 0.01;
        let out = f.process(1.0, Pose2::default(), &r).expect("a scan with some bad beams is used");
        assert_eq!(out.invalid_beams, 3);
        let e = f.process(0.5, Pose2::default(), &r).unwrap_err();
        assert!(matches!(e, GridSlamError::Stamp { .. }), "{e}");
        let e = f.process(2.0, Pose2 { x_m: f64::NAN, ..Default::default() }, &r).unwrap_err();
        assert!(matches!(e, GridSlamError::Odometry { .. }), "{e}");
        assert_eq!(f.stats().scans, 1);
    }

    #[test]
    fn config_errors_name_the_key() {
        let e = GridSlamConfig { resolution_m: 0.0, ..Default::default() }.issues();
        assert!(e.to_string().contains("resolution_m"), "{e}");
        let e = GridSlamConfig { particles: 0, ..Default::default() }.issues();
        assert!(e.to_string().contains("particles"), "{e}");
        let m = MatcherParams { coarse_stride: 0, ..Default::default() };
        let e = GridSlamConfig { matcher: m, ..Default::default() }.issues();
        assert!(e.to_string().contains("matcher.coarse_stride"), "{e}");
        let m = MatcherParams { coarse_refinements: 9, ..Default::default() };
        let e = GridSlamConfig { matcher: m, ..Default::default() }.issues();
        assert!(e.to_string().contains("matcher.coarse_refinements"), "{e}");
        for bad in [-0.1, f64::NAN] {
            let m = MatcherParams { min_point_spacing_m: bad, ..Default::default() };
            let e = GridSlamConfig { matcher: m, ..Default::default() }.issues();
            assert!(e.to_string().contains("matcher.min_point_spacing_m"), "{e}");
        }
    }

    #[test]
    fn points_closer_than_the_spacing_along_the_scan_are_left_out_of_matching() {
        // 360 beams 1° apart, all 2 m away: end points 3.5 cm apart. A spacing of 5 cm keeps
        // every second one; the map still gets every beam.
        let geom = ScanGeometry {
            angle_min_rad: -std::f64::consts::PI,
            angle_increment_rad: std::f64::consts::TAU / 360.0,
            beams: 360,
            range_min_m: 0.05,
            range_max_m: 10.0,
            body_from_laser: Pose2::default(),
        };
        let ranges = vec![2.0f32; 360];
        let all = GridSlam::new(GridSlamConfig::default(), geom).expect("filter").prepare_scan(&ranges);
        let m = MatcherParams { min_point_spacing_m: 0.05, ..Default::default() };
        let spaced = GridSlam::new(GridSlamConfig { matcher: m, ..Default::default() }, geom)
            .expect("filter")
            .prepare_scan(&ranges);
        assert_eq!(all.points.points.len(), 360);
        assert_eq!(spaced.points.points.len(), 180);
        assert_eq!(spaced.beams.len(), 360);
        for w in spaced.points.points.windows(2) {
            let d = (w[1].hit.0 - w[0].hit.0).hypot(w[1].hit.1 - w[0].hit.1);
            assert!(d >= 0.05, "{d}");
        }
    }

    /// The best particle's path and the counts over the first `scans` scans of the simulated
    /// indoor mission, with 6 particles on 2 threads.
    fn indoor_run(share_copies: bool, scans: usize) -> (Vec<(f64, Pose2)>, GridSlamStats) {
        use sim::indoor::{IndoorConfig, IndoorEvent, IndoorSim};
        let mut sc = IndoorConfig { seed: 2, ..Default::default() };
        sc.depth.rate_hz = 0.0;
        let mut sim = IndoorSim::new(sc.clone()).expect("simulator");
        let l = &sc.laser;
        let geom = ScanGeometry {
            angle_min_rad: -std::f64::consts::PI,
            angle_increment_rad: std::f64::consts::TAU / l.beams as f64,
            beams: l.beams,
            range_min_m: 0.05,
            range_max_m: l.max_range_m,
            body_from_laser: Pose2 { x_m: l.offset_m[0], y_m: l.offset_m[1], theta_rad: 0.0 },
        };
        let cfg = GridSlamConfig { particles: 6, threads: 2, seed: 3, usable_range_m: 12.0, ..Default::default() };
        let mut f = GridSlam::new(cfg, geom).expect("filter");
        f.share_copies = share_copies;
        let (mut odom, mut seen) = (Pose2::default(), 0);
        while let Some(events) = sim.next_events() {
            for e in events {
                match e {
                    IndoorEvent::Odometry { pose, .. } => odom = pose,
                    IndoorEvent::Laser { t_s, ranges } => {
                        f.process(t_s, odom, &ranges).expect("scan");
                        seen += 1;
                    }
                    IndoorEvent::Cloud { .. } => {}
                }
            }
            if seen >= scans {
                break;
            }
        }
        (f.trajectory(), f.stats())
    }

    /// Copies of one particle (after a resampling) have the same pose and map, so the same match
    /// and proposal: computed once for them, the filter's result is the same to the last bit.
    #[test]
    fn copies_of_a_particle_share_one_match_and_the_result_is_the_same() {
        let (shared, s) = indoor_run(true, 300);
        let (each, e) = indoor_run(false, 300);
        assert!(s.updates >= 20 && s.resamples >= 5, "the robot moved and the set was resampled: {s:?}");
        assert_eq!(e.matches, 6 * e.updates, "without sharing, one match per particle and update: {e:?}");
        assert!(s.matches < e.matches && s.matches >= s.updates, "copies shared their match: {s:?} against {e:?}");
        assert_eq!(shared.len(), each.len());
        assert!(shared.iter().zip(&each).all(|(a, b)| a == b), "the same path to the last bit");
        // The same counts, but for the tiles shared: which of two copies writing a tile they share
        // on two threads copies it first decides which one's tile stays whole (the cells read the
        // same either way), so that count varies from run to run by a few.
        let counts = |s: GridSlamStats| GridSlamStats { matches: 0, shared_tiles: 0, ..s };
        assert_eq!(counts(s), counts(e), "the same counts");
    }
}

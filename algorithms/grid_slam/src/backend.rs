//! The pose-graph back end behind the particle filter (the method of Cartographer, Hess et al.
//! 2016, and of Karto / slam_toolbox), docs/EQUATIONS.md §8: the filter ([2D3D] §III.A, Grisetti
//! et al. 2007) stays the front end and gives a pose at every update (a node) with its scan;
//!
//! 1. consecutive nodes are joined by the front end's relative pose (σ growing with the motion);
//! 2. the nodes are cut into submaps of `submap_nodes` consecutive nodes, each starting half a
//!    submap after the previous (so every place is in a submap with its surroundings), written
//!    into a grid in the frame of the submap's first node (its anchor) at the front end's poses;
//! 3. every `search_every`-th node is matched against each submap it is not a neighbour of in
//!    time, if its current estimate lies near one of the submap's nodes, by branch-and-bound
//!    correlative matching ([`crate::correlative`]) in a window around its current estimate in
//!    the submap that grows with the path travelled between the two (the odometry's accumulated
//!    uncertainty), refined by the filter's matcher; a match scoring at least `min_score` adds a
//!    loop constraint from the anchor to the node;
//! 4. the graph is optimised ([`crate::posegraph`]) with a Huber kernel on the loop
//!    constraints, loop constraints whose error stays above `outlier_chi2` (χ² with 3 degrees of
//!    freedom) are dropped as false and the graph optimised again; steps 3-4 repeat `rounds`
//!    times from the corrected poses (the windows shrink as the drift is taken out);
//! 5. the grid is rebuilt from the nodes' scans at the optimised poses.

use crate::correlative::{self, LookupGrid, Window};
use crate::filter::{GridSlam, GridSlamConfig, PreparedScan};
use crate::grid::Grid;
use crate::posegraph::{self, Edge, Kernel, OptimizeParams};
use crate::{GridSlamError, matcher};
use omni::Pose2;
use validation::{Issues, Validate};

/// Back-end settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BackEndConfig {
    /// Nodes (filter updates) per submap.
    pub submap_nodes: usize,
    /// Every this-many-th node is searched for loop closures.
    pub search_every: usize,
    /// A match is a loop closure when the mean likelihood field over its points is at least
    /// this (0-1; 1 = every point on an occupied cell).
    pub min_score: f64,
    /// Search window half-width in x and y: this ...
    pub window_base_m: f64,
    /// ... plus this per metre of path between the node and the submap ...
    pub window_per_m: f64,
    /// ... at most this, m.
    pub window_max_m: f64,
    /// Search window half-width in θ: this ...
    pub angular_window_base_rad: f64,
    /// ... plus this per metre of path ...
    pub angular_window_per_m: f64,
    /// ... at most this, rad.
    pub angular_window_max_rad: f64,
    /// A stretch of nodes passing a submap (consecutive candidates less than a submap's nodes
    /// apart) is searched at this many evenly spaced nodes at most: a revisit needs a few
    /// constraints, not one per node.
    pub max_per_visit: usize,
    /// End points used to search (a voxel filter of 2 cells, then every k-th), at most.
    pub max_points: usize,
    /// Levels of the branch-and-bound grids above the finest (blocks of 2^depth cells).
    pub depth: u32,
    /// σ of the front end's relative pose between consecutive nodes: this ...
    pub odometry_sigma_m: f64,
    /// ... plus this per metre moved, m.
    pub odometry_sigma_per_m: f64,
    /// σ of the relative heading: this ...
    pub odometry_sigma_rad: f64,
    /// ... plus this per radian turned and per metre moved.
    pub odometry_sigma_per_rad: f64,
    /// σ of a loop constraint's translation, m.
    pub loop_sigma_m: f64,
    /// ... and rotation, rad.
    pub loop_sigma_rad: f64,
    /// Huber scale of the loop constraints, in σ.
    pub huber: f64,
    /// A loop constraint whose χ² (3 degrees of freedom) stays above this after optimising is
    /// dropped (16.27: the 99.9 % quantile).
    pub outlier_chi2: f64,
    /// Search-and-optimise rounds.
    pub rounds: usize,
    /// Threads for the search (0: all cores).
    pub threads: usize,
}

impl Default for BackEndConfig {
    fn default() -> Self {
        Self {
            submap_nodes: 20,
            search_every: 2,
            min_score: 0.55,
            window_base_m: 1.0,
            window_per_m: 0.03,
            window_max_m: 6.0,
            angular_window_base_rad: 0.15,
            angular_window_per_m: 0.003,
            angular_window_max_rad: 0.6,
            max_per_visit: 3,
            max_points: 120,
            depth: 6,
            odometry_sigma_m: 0.01,
            odometry_sigma_per_m: 0.02,
            odometry_sigma_rad: 0.005,
            odometry_sigma_per_rad: 0.02,
            loop_sigma_m: 0.05,
            loop_sigma_rad: 0.02,
            huber: 1.0,
            outlier_chi2: 16.27,
            rounds: 2,
            threads: 0,
        }
    }
}

impl Validate for BackEndConfig {
    fn validate(&self, issues: &mut Issues) {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        let nonneg = |v: f64| v.is_finite() && v >= 0.0;
        issues.check(self.submap_nodes >= 2, "submap_nodes", "must be at least 2");
        issues.check(self.search_every != 0, "search_every", "must be at least 1");
        issues.check(self.min_score > 0.0 && self.min_score <= 1.0, "min_score", "must be in (0, 1]");
        for (k, v) in [
            ("window_base_m", self.window_base_m),
            ("angular_window_base_rad", self.angular_window_base_rad),
            ("odometry_sigma_m", self.odometry_sigma_m),
            ("odometry_sigma_rad", self.odometry_sigma_rad),
            ("loop_sigma_m", self.loop_sigma_m),
            ("loop_sigma_rad", self.loop_sigma_rad),
            ("huber", self.huber),
            ("outlier_chi2", self.outlier_chi2),
        ] {
            issues.check(pos(v), k, "must be finite and > 0");
        }
        for (k, v) in [
            ("window_per_m", self.window_per_m),
            ("angular_window_per_m", self.angular_window_per_m),
            ("odometry_sigma_per_m", self.odometry_sigma_per_m),
            ("odometry_sigma_per_rad", self.odometry_sigma_per_rad),
        ] {
            issues.check(nonneg(v), k, "must be finite and >= 0");
        }
        issues.check(
            self.window_max_m.is_finite() && self.window_max_m >= self.window_base_m,
            "window_max_m",
            "must be finite and >= window_base_m",
        );
        issues.check(
            self.angular_window_max_rad.is_finite()
                && self.angular_window_max_rad >= self.angular_window_base_rad
                && self.angular_window_max_rad <= std::f64::consts::PI,
            "angular_window_max_rad",
            "must be >= angular_window_base_rad and <= π",
        );
        issues.check(self.max_per_visit != 0, "max_per_visit", "must be at least 1");
        issues.check(self.max_points >= 10, "max_points", "must be at least 10");
        issues.check((1..=10).contains(&self.depth), "depth", "must be 1-10");
        issues.check(self.rounds != 0, "rounds", "must be at least 1");
    }
}

/// What the back end did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct BackEndReport {
    /// Nodes in the graph.
    pub nodes: usize,
    /// Submaps.
    pub submaps: usize,
    /// Node-submap pairs searched.
    pub searched: usize,
    /// Matches that scored at least `min_score`.
    pub matches: usize,
    /// Loop constraints kept in the final graph.
    pub loop_constraints: usize,
    /// Loop constraints dropped as false (χ² above `outlier_chi2` after optimising).
    pub rejected: usize,
    /// Largest move of a node from the front end's pose, m.
    pub max_correction_m: f64,
    /// Mean move, m.
    pub mean_correction_m: f64,
    /// Optimiser iterations over all rounds.
    pub iterations: usize,
    /// Seconds spent building submaps and their search grids, summed over the threads (the
    /// submaps are built and searched on all threads, a submap per thread at a time).
    pub submaps_s: f64,
    /// Wall time of building and searching the submaps.
    pub search_s: f64,
    /// ... optimising.
    pub optimise_s: f64,
}

/// One submap's search: the matches (anchor, node, `anchor_from_node`), the pairs tried and the
/// seconds spent building its grid.
type SubmapSearch = (Vec<(usize, usize, Pose2)>, Vec<(usize, usize)>, f64);

/// The back end's result.
#[derive(Debug, Clone)]
pub struct BackEndResult {
    /// Optimised pose per update (index = update; `None` where the front end has none).
    pub nodes: Vec<Option<Pose2>>,
    /// The grid rebuilt from the nodes' scans at the optimised poses.
    pub grid: Grid,
    /// What was done.
    pub report: BackEndReport,
}

/// The nodes' scans, kept as the filter updates: the ranges only (4 bytes a beam), prepared again
/// when the graph is built (prepared scans take ~14× that).
#[derive(Debug, Clone, Default)]
pub struct BackEnd {
    cfg: BackEndConfig,
    scans: Vec<Option<Box<[f32]>>>,
}

impl BackEnd {
    /// A back end with `cfg` (checked).
    pub fn new(cfg: BackEndConfig) -> Result<Self, GridSlamError> {
        let mut issues = Issues::at("pose_graph");
        cfg.validate(&mut issues);
        issues.into_result().map_err(GridSlamError::Config)?;
        Ok(Self { cfg, scans: Vec::new() })
    }

    /// Its settings.
    pub fn config(&self) -> &BackEndConfig {
        &self.cfg
    }

    /// Keeps the scan (ranges, m) of filter update `update` (call when
    /// [`crate::ScanOutcome::updated`]).
    pub fn add_node(&mut self, update: u32, ranges: &[f32]) {
        let scan: Box<[f32]> = ranges.into();
        let k = update as usize;
        if self.scans.len() <= k {
            self.scans.resize(k + 1, None);
        }
        self.scans[k] = Some(scan);
    }

    /// Nodes kept.
    pub fn len(&self) -> usize {
        self.scans.iter().filter(|s| s.is_some()).count()
    }

    /// Whether no node is kept.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes of the kept scans.
    pub fn bytes(&self) -> usize {
        self.scans.iter().flatten().map(|s| s.len() * std::mem::size_of::<f32>()).sum()
    }

    /// Closes loops over the filter's final path: search, optimise, rebuild the grid.
    pub fn run(&self, filter: &GridSlam) -> Result<BackEndResult, GridSlamError> {
        self.optimize(&filter.node_path(), filter.config(), |r| filter.prepare_scan(r))
    }

    /// As [`BackEnd::run`] with the front end's poses per update `path` and its settings.
    /// `prepare` turns a node's ranges into beams and matching points as the filter does
    /// ([`GridSlam::prepare_scan`]).
    pub fn optimize(
        &self,
        path: &[Option<Pose2>],
        fcfg: &GridSlamConfig,
        prepare: impl Fn(&[f32]) -> PreparedScan + Sync,
    ) -> Result<BackEndResult, GridSlamError> {
        let cfg = &self.cfg;
        // Every update needs its pose and scan: a filter restored from a snapshot has neither for
        // the updates before it, and a graph of the rest would rebuild the map without them.
        let missing =
            (0..path.len()).filter(|&k| path[k].is_none() || self.scans.get(k).is_none_or(|s| s.is_none())).count();
        if missing > 0 {
            return Err(GridSlamError::Optimisation {
                why: format!(
                    "{missing} of {} filter updates have no pose or no scan (a filter restored from a snapshot keeps \
                     neither for the updates before it): the pose graph needs them all",
                    path.len()
                ),
            });
        }
        if path.len() < 2 {
            return Err(GridSlamError::Optimisation {
                why: format!("{} filter update(s): nothing to optimise", path.len()),
            });
        }
        // The nodes: updates with a pose and a scan.
        let ids: Vec<usize> =
            (0..path.len()).filter(|&k| path[k].is_some() && self.scans.get(k).is_some_and(|s| s.is_some())).collect();
        let front: Vec<Pose2> = ids.iter().map(|&k| path[k].unwrap_or_default()).collect();
        let ranges: Vec<&[f32]> = ids.iter().filter_map(|&k| self.scans[k].as_deref()).collect();
        let scan = |i: usize| prepare(ranges[i]);
        let n = ids.len();
        let mut report = BackEndReport { nodes: n, ..Default::default() };
        // Path length at each node.
        let mut along = vec![0.0; n];
        for i in 1..n {
            along[i] = along[i - 1] + (front[i].x_m - front[i - 1].x_m).hypot(front[i].y_m - front[i - 1].y_m);
        }
        // Chain constraints.
        let mut edges: Vec<Edge> = (1..n)
            .map(|i| {
                let z = front[i - 1].between(&front[i]);
                let d = z.x_m.hypot(z.y_m);
                let sm = cfg.odometry_sigma_m + cfg.odometry_sigma_per_m * d;
                let sr = cfg.odometry_sigma_rad + cfg.odometry_sigma_per_rad * (z.theta_rad.abs() + d);
                Edge {
                    from: i - 1,
                    to: i,
                    measured: z,
                    information: [1.0 / (sm * sm), 1.0 / (sm * sm), 1.0 / (sr * sr)],
                    kernel: Kernel::None,
                }
            })
            .collect();
        let chain = edges.len();
        // Submaps: [start, start + submap_nodes), starts half a submap apart.
        let k = cfg.submap_nodes;
        let half = (k / 2).max(1);
        let starts: Vec<usize> = if n >= k { (0..=n - k).step_by(half).collect() } else { Vec::new() };
        report.submaps = starts.len();
        // Search points per node (voxel filter of 2 cells over the hits, then a stride).
        let cell = 2.0 * fcfg.resolution_m;
        let points: Vec<Vec<(f64, f64)>> = (0..n)
            .map(|i| {
                let s = scan(i);
                let mut seen = std::collections::HashSet::new();
                let v: Vec<(f64, f64)> = s
                    .beams
                    .iter()
                    .filter(|b| b.hit)
                    .map(|b| b.end)
                    .filter(|p| seen.insert(((p.0 / cell).floor() as i64, (p.1 / cell).floor() as i64)))
                    .collect();
                let stride = v.len().div_ceil(cfg.max_points).max(1);
                v.into_iter().step_by(stride).collect()
            })
            .collect();
        let threads = if cfg.threads == 0 {
            std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
        } else {
            cfg.threads
        };
        let loop_info = [
            1.0 / (cfg.loop_sigma_m * cfg.loop_sigma_m),
            1.0 / (cfg.loop_sigma_m * cfg.loop_sigma_m),
            1.0 / (cfg.loop_sigma_rad * cfg.loop_sigma_rad),
        ];
        let mut est = front.clone();
        let mut tried = std::collections::HashSet::new();
        let params = OptimizeParams { fixed: 0, ..Default::default() };
        for _round in 0..cfg.rounds {
            // Each submap (its candidates, its grid, their matches) goes to a thread from a queue;
            // the pairs tried and the matches are merged after the round, in submap order.
            let search_submap = |s0: usize| -> Option<SubmapSearch> {
                let members = s0..(s0 + k).min(n);
                let anchor = front[s0];
                let anchor_est = est[s0];
                // Candidate nodes for this submap.
                let all: Vec<(usize, Pose2, Window)> = (0..n)
                    .step_by(cfg.search_every)
                    .filter(|&i| i + k < members.start || i >= members.end + k)
                    .filter(|&i| !tried.contains(&(s0, i)))
                    .filter_map(|i| {
                        let nearest = members
                            .clone()
                            .min_by(|&a, &b| (along[a] - along[i]).abs().total_cmp(&(along[b] - along[i]).abs()))?;
                        let travelled = (along[nearest] - along[i]).abs();
                        let w = Window {
                            linear_m: (cfg.window_base_m + cfg.window_per_m * travelled).min(cfg.window_max_m),
                            angular_rad: (cfg.angular_window_base_rad + cfg.angular_window_per_m * travelled)
                                .min(cfg.angular_window_max_rad),
                        };
                        let close = members
                            .clone()
                            .any(|m| (est[m].x_m - est[i].x_m).hypot(est[m].y_m - est[i].y_m) <= w.linear_m + 1.0);
                        close.then(|| (i, anchor_est.between(&est[i]), w))
                    })
                    .collect();
                // Visits: runs of candidates less than a submap apart; a few evenly spaced of each.
                let mut cands = Vec::new();
                let mut visit: Vec<(usize, Pose2, Window)> = Vec::new();
                for c in all.into_iter().chain(std::iter::once((
                    usize::MAX,
                    Pose2::default(),
                    Window { linear_m: 0.0, angular_rad: 0.0 },
                ))) {
                    if visit.last().is_some_and(|l| c.0 == usize::MAX || c.0 >= l.0 + k) {
                        let m = visit.len();
                        let take = cfg.max_per_visit.min(m);
                        for t in 0..take {
                            // Evenly spaced, centred: (2t + 1)·m / (2·take).
                            cands.push(visit[((2 * t + 1) * m) / (2 * take)]);
                        }
                        visit.clear();
                    }
                    if c.0 != usize::MAX {
                        visit.push(c);
                    }
                }
                if cands.is_empty() {
                    return None;
                }
                let t_build = std::time::Instant::now();
                let mut grid = Grid::new(fcfg.resolution_m);
                for m in members.clone() {
                    let local = anchor.between(&front[m]);
                    let sm = scan(m);
                    GridSlam::integrate(&mut grid, &local, sm.origin, &sm.beams, &fcfg.log_odds);
                }
                let lookup = LookupGrid::new(&grid, fcfg.matcher.occupied_log_odds, cfg.depth)?;
                let build_s = t_build.elapsed().as_secs_f64();
                let mut matched = Vec::new();
                for &(i, initial, w) in &cands {
                    let Some(m) = correlative::search(&lookup, &points[i], &initial, w, cfg.min_score) else {
                        continue;
                    };
                    // Refine with the filter's matcher on the submap's grid.
                    let (refined, _) = matcher::optimize(&grid, &scan(i).points, &m.pose, &fcfg.matcher);
                    let moved = (refined.x_m - m.pose.x_m).hypot(refined.y_m - m.pose.y_m);
                    let pose = if moved <= 2.0 * fcfg.resolution_m
                        && omni::wrap_angle(refined.theta_rad - m.pose.theta_rad).abs() < 0.02
                    {
                        refined
                    } else {
                        m.pose
                    };
                    matched.push((s0, i, pose));
                }
                let pairs: Vec<(usize, usize)> = cands.iter().map(|&(i, _, _)| (s0, i)).collect();
                Some((matched, pairs, build_s))
            };
            let t_phase = std::time::Instant::now();
            let next = std::sync::atomic::AtomicUsize::new(0);
            let results = std::sync::Mutex::new(Vec::new());
            std::thread::scope(|scope| {
                for _ in 0..threads.min(starts.len()).max(1) {
                    scope.spawn(|| {
                        loop {
                            let c = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            let Some(&s0) = starts.get(c) else { break };
                            if let Some(r) = search_submap(s0)
                                && let Ok(mut all) = results.lock()
                            {
                                all.push((s0, r));
                            }
                        }
                    });
                }
            });
            report.search_s += t_phase.elapsed().as_secs_f64();
            let mut results = results.into_inner().unwrap_or_default();
            results.sort_by_key(|r| r.0);
            let mut found = Vec::new();
            for (_, (matched, pairs, build_s)) in results {
                report.submaps_s += build_s;
                report.searched += pairs.len();
                tried.extend(pairs);
                found.extend(matched);
            }
            report.matches += found.len();
            let new_edges = found.len();
            found.sort_by_key(|f| (f.0, f.1));
            edges.extend(found.into_iter().map(|(s0, i, pose)| Edge {
                from: s0,
                to: i,
                measured: pose,
                information: loop_info,
                kernel: Kernel::Huber(cfg.huber),
            }));
            if new_edges == 0 && edges.len() == chain {
                break;
            }
            // Optimise from the front end's poses, drop loop constraints that stay far off, again.
            let t_opt = std::time::Instant::now();
            est = front.clone();
            let r = posegraph::optimize(&mut est, &edges, &params)?;
            report.iterations += r.iterations;
            let before = edges.len();
            let mut k_edge = 0;
            edges.retain(|e| {
                k_edge += 1;
                k_edge <= chain || e.chi2(&est) <= cfg.outlier_chi2
            });
            let dropped = before - edges.len();
            report.rejected += dropped;
            if dropped > 0 {
                let r = posegraph::optimize(&mut est, &edges, &params)?;
                report.iterations += r.iterations;
            }
            report.optimise_s += t_opt.elapsed().as_secs_f64();
        }
        report.loop_constraints = edges.len() - chain;
        let moves: Vec<f64> = est.iter().zip(&front).map(|(a, b)| (a.x_m - b.x_m).hypot(a.y_m - b.y_m)).collect();
        report.max_correction_m = moves.iter().copied().fold(0.0, f64::max);
        report.mean_correction_m = if n > 0 { moves.iter().sum::<f64>() / n as f64 } else { 0.0 };
        // The grid from the nodes' scans at the optimised poses.
        let mut grid = Grid::new(fcfg.resolution_m);
        for (i, pose) in est.iter().enumerate() {
            let sc = scan(i);
            GridSlam::integrate(&mut grid, pose, sc.origin, &sc.beams, &fcfg.log_odds);
        }
        let mut nodes = vec![None; path.len()];
        for (j, &k) in ids.iter().enumerate() {
            nodes[k] = Some(est[j]);
        }
        Ok(BackEndResult { nodes, grid, report })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Updates without a pose or a scan (a filter restored from a snapshot) are refused with a
    /// reason, as is a path too short to optimise; bad settings name their key.
    #[test]
    fn incomplete_paths_and_bad_settings_are_refused() {
        let cfg = GridSlamConfig::default();
        let mut b = BackEnd::new(BackEndConfig::default()).expect("defaults are valid");
        let p = Pose2::default();
        b.add_node(1, &[]);
        b.add_node(2, &[]);
        let e = b.optimize(&[None, Some(p), Some(p)], &cfg, |_| PreparedScan::default()).unwrap_err().to_string();
        assert!(e.contains("1 of 3") && e.contains("snapshot"), "{e}");
        let e = b.optimize(&[Some(p), Some(p), Some(p)], &cfg, |_| PreparedScan::default()).unwrap_err().to_string();
        assert!(e.contains("1 of 3"), "update 0 has no scan: {e}");
        let mut one = BackEnd::new(BackEndConfig::default()).expect("valid");
        one.add_node(0, &[]);
        let e = one.optimize(&[Some(p)], &cfg, |_| PreparedScan::default()).unwrap_err();
        assert!(e.to_string().contains("nothing to optimise"), "{e}");
        let bad = BackEndConfig { min_score: 1.5, ..Default::default() };
        assert!(BackEnd::new(bad).unwrap_err().to_string().contains("pose_graph.min_score"));
        let bad = BackEndConfig { angular_window_max_rad: 4.0, ..Default::default() };
        assert!(BackEnd::new(bad).unwrap_err().to_string().contains("angular_window_max_rad"));
    }
}

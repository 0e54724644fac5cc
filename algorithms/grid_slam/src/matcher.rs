//! Scan matching against a particle's own grid (gmapping's matcher, docs/EQUATIONS.md §8 step 1): each beam's
//! end point is scored by its distance to the surface through the mean hit points of the nearest
//! occupied cells in a small window whose cell one step nearer along the beam is not occupied (so
//! a wall is matched from the side the beam saw it). Pattern search over x, y, θ at the first
//! step size, then Gauss-Newton on the same score to a step below 1 mm and 1 mrad (gmapping
//! halves the pattern search's steps instead: `MatcherParams::gauss_newton = false`).
//!
//! Two departures from gmapping, both measured (`cargo run --release -p grid_slam --example
//! indoor_eval -- --probe`: scans matched from their true pose on a map built at the true poses):
//! - the "one step nearer" cell is the beam's direction quantised to the 8 neighbours, the same
//!   whichever cell the end point falls in. gmapping takes the cell of the point one cell nearer
//!   along the beam, which jumps (and on diagonal beams can be the end point's own cell, so the beam
//!   matches nothing) as the end point crosses a cell border: the score then has steps of several
//!   beams every few millimetres and hill climbing stops on them, 1.7 cm (2.9 cm with a noiseless
//!   laser) from the truth in the probe; with the fixed direction, 1.1 cm (0.7 cm);
//! - the distance is to the line through the two nearest mean hit points (when they are at least
//!   half a cell apart), not to the nearest point, so where along a wall the end point falls does
//!   not count (indoor mission: mean ATE 0.037 against 0.045 m over six runs).

use crate::grid::{Grid, TileRef};
use omni::Pose2;

/// Matcher settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MatcherParams {
    /// Half-width of the search window around each end point, cells (1: 3×3).
    pub kernel_cells: i32,
    /// Std dev of the hill-climbing score's Gaussian, m.
    pub score_sigma_m: f64,
    /// Std dev of the likelihood's Gaussian per beam, m.
    pub likelihood_sigma_m: f64,
    /// Log-likelihood of a beam that matches nothing (bounded, so one unexplained beam cannot
    /// veto a pose), in units of the per-beam log-likelihood.
    pub null_log_likelihood: f64,
    /// Initial translation step of hill climbing, m.
    pub linear_step_m: f64,
    /// Initial rotation step of hill climbing, rad.
    pub angular_step_rad: f64,
    /// Step halvings before hill climbing stops.
    pub refinements: u32,
    /// Use every n-th beam (1: all).
    pub beam_stride: usize,
    /// A matching point closer than this to the last one kept along the scan is left out
    /// (0: every point). Neighbouring beams that end in the same cell carry one wall's
    /// evidence twice: scoring them as independent makes the likelihood too peaked and
    /// costs time (Cartographer's voxel filter, Hess et al. 2016 §V; docs/EQUATIONS.md §8).
    pub min_point_spacing_m: f64,
    /// Hill climbing's first `coarse_refinements` step sizes poll only every
    /// `coarse_stride`-th point (1: all points at every step size); the finer steps, which set
    /// the result, use all.
    pub coarse_stride: usize,
    /// How many of the step sizes, from the first, are coarse (see `coarse_stride`).
    pub coarse_refinements: u32,
    /// Log-odds above which a cell counts as occupied.
    pub occupied_log_odds: f32,
    /// A match is accepted when its score is at least this share of the beams used.
    pub min_score_share: f64,
    /// Distance of an end point to the surface: to the line through the two nearest occupied
    /// cells' mean hit points (`true`), or to the nearest mean hit point (gmapping's, `false`).
    pub point_to_line: bool,
    /// Hill climbing polls at its first step size only, and Gauss-Newton on the same score
    /// finishes the match (iteratively reweighted least squares, each beam weighted by its
    /// exp(−d²/2σ_s²); Gauss-Newton scan matching as in Kohlbrecher et al. 2011 and Hess et
    /// al. 2016; docs/EQUATIONS.md §8). `false`: hill climbing halves its steps `refinements`
    /// times, as gmapping does (about 3 times the fits for the same optimum).
    pub gauss_newton: bool,
}

impl Default for MatcherParams {
    fn default() -> Self {
        Self {
            kernel_cells: 1,
            score_sigma_m: 0.1,
            likelihood_sigma_m: 0.075,
            null_log_likelihood: -0.5,
            linear_step_m: 0.05,
            angular_step_rad: 0.05,
            refinements: 5,
            beam_stride: 1,
            min_point_spacing_m: 0.0,
            coarse_stride: 1,
            coarse_refinements: 0,
            occupied_log_odds: 0.0,
            min_score_share: 0.15,
            point_to_line: true,
            gauss_newton: true,
        }
    }
}

/// One beam's end point in the sensor frame and the point one cell nearer along it.
#[derive(Debug, Clone, Copy)]
pub struct BeamPoint {
    /// End point, m (body frame: already through the laser's mounting).
    pub hit: (f64, f64),
    /// One cell nearer the sensor along the beam, m (body frame).
    pub free: (f64, f64),
}

/// A scan's usable end points in the body frame.
#[derive(Debug, Clone, Default)]
pub struct ScanPoints {
    /// Points used for matching (every `beam_stride`-th valid beam within the usable range).
    pub points: Vec<BeamPoint>,
}

/// The score (for hill climbing) and log-likelihood (for the proposal) of a pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fit {
    /// Σ exp(−d²/2σ_s²) over the beams.
    pub score: f64,
    /// Σ log-likelihood over the beams.
    pub log_likelihood: f64,
    /// Beams that matched an occupied cell.
    pub matched: usize,
}

/// Scores `pose` (world_from_body) against `grid`.
pub fn fit(grid: &Grid, scan: &ScanPoints, pose: &Pose2, p: &MatcherParams) -> Fit {
    fit_every(grid, scan, 1, pose, p, true)
}

/// [`fit`]'s log-likelihood alone (the same value; the score's exponentials, a fifth of a
/// fit's time, are skipped): what the proposal's samples need.
pub fn log_likelihood(grid: &Grid, scan: &ScanPoints, pose: &Pose2, p: &MatcherParams) -> f64 {
    fit_every(grid, scan, 1, pose, p, false).log_likelihood
}

/// [`fit`] over every `stride`-th point of `scan`; the score only `with_score` (0 otherwise).
fn fit_every(grid: &Grid, scan: &ScanPoints, stride: usize, pose: &Pose2, p: &MatcherParams, with_score: bool) -> Fit {
    let sc = pose.theta_rad.sin_cos();
    let inv_score = 1.0 / (2.0 * p.score_sigma_m * p.score_sigma_m);
    let inv_lik = 1.0 / (2.0 * p.likelihood_sigma_m * p.likelihood_sigma_m);
    let (mut score, mut ll, mut matched) = (0.0, 0.0, 0usize);
    for b in scan.points.iter().step_by(stride.max(1)) {
        match nearest_surface(grid, p, pose, sc, b) {
            Some(near) => {
                if with_score {
                    score += exp_neg(near.d2 * inv_score);
                }
                ll += -near.d2 * inv_lik;
                matched += 1;
            }
            None => ll += p.null_log_likelihood,
        }
    }
    Fit { score, log_likelihood: ll, matched }
}

/// [`fit`] at `pose` with the normal equations of its score there: H = Σ w JᵀJ and g = Σ w Jᵀr
/// over the matched beams, r the end point's offset from its surface (the distance to the line
/// through the two nearest mean points, or the offset from the nearest), J = ∂r/∂(x, y, θ),
/// w = exp(−d²/2σ_s²): a step −H⁻¹g is the reweighted least-squares step towards the score's
/// maximum (docs/EQUATIONS.md §8).
///
/// Also the log-likelihood's own Gauss-Newton model there ([`LikelihoodModel`]: the same
/// residuals and Jacobians, unweighted, scaled by 1/σ_l²), which the proposal can take instead of
/// evaluating its lattice.
fn linearize(grid: &Grid, scan: &ScanPoints, pose: &Pose2, p: &MatcherParams) -> Linearized {
    let (s, c) = pose.theta_rad.sin_cos();
    let inv_score = 1.0 / (2.0 * p.score_sigma_m * p.score_sigma_m);
    let inv_lik = 1.0 / (2.0 * p.likelihood_sigma_m * p.likelihood_sigma_m);
    let (mut score, mut ll, mut matched) = (0.0, 0.0, 0usize);
    let mut h = [[0.0; 3]; 3];
    let mut g = [0.0; 3];
    // Σ JᵀJ and Σ J r over the matched beams, unweighted (the log-likelihood's model).
    let mut hl = [[0.0; 3]; 3];
    let mut gl = [0.0; 3];
    let mut add = |w: f64, r: f64, j: [f64; 3]| {
        for a in 0..3 {
            g[a] += w * j[a] * r;
            gl[a] += j[a] * r;
            for b in 0..3 {
                h[a][b] += w * j[a] * j[b];
                hl[a][b] += j[a] * j[b];
            }
        }
    };
    for b in &scan.points {
        let Some(near) = nearest_surface(grid, p, pose, (s, c), b) else {
            ll += p.null_log_likelihood;
            continue;
        };
        let w = exp_neg(near.d2 * inv_score);
        score += w;
        ll += -near.d2 * inv_lik;
        matched += 1;
        // ∂hit/∂θ = (−(hit_y − y), hit_x − x).
        let dth = (-(near.hit.1 - pose.y_m), near.hit.0 - pose.x_m);
        match near.line {
            Some((ux, uy, len2)) => {
                let len = len2.sqrt();
                let n = (-uy / len, ux / len);
                let r = n.0 * (near.hit.0 - near.m1.0) + n.1 * (near.hit.1 - near.m1.1);
                add(w, r, [n.0, n.1, n.0 * dth.0 + n.1 * dth.1]);
            }
            None => {
                add(w, near.hit.0 - near.m1.0, [1.0, 0.0, dth.0]);
                add(w, near.hit.1 - near.m1.1, [0.0, 1.0, dth.1]);
            }
        }
    }
    // ll = −Σ r²/2σ_l²: its gradient is −Σ J r/σ_l², the Hessian of −ll ≈ Σ JᵀJ/σ_l².
    let k = 2.0 * inv_lik;
    let model = LikelihoodModel {
        log_likelihood: ll,
        gradient: gl.map(|v| -k * v),
        curvature: hl.map(|row| row.map(|v| k * v)),
    };
    Linearized { fit: Fit { score, log_likelihood: ll, matched }, h, g, model }
}

/// What [`linearize`] gives at a pose.
struct Linearized {
    fit: Fit,
    /// The score's normal equations (weighted): H and g.
    h: [[f64; 3]; 3],
    g: [f64; 3],
    /// The log-likelihood's quadratic model.
    model: LikelihoodModel,
}

/// The log-likelihood's Gauss-Newton model around a pose: ln p(z | m, x + δ) ≈ ℓ + gᵀδ −
/// ½ δᵀCδ, δ = (dx, dy, dθ) in the world frame with the rotation about the pose's own origin
/// (docs/EQUATIONS.md §8). The beams keep the surfaces they matched at the pose, and the beams
/// that matched nothing keep their constant term.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LikelihoodModel {
    /// ℓ, the log-likelihood at the pose ([`Fit::log_likelihood`]).
    pub log_likelihood: f64,
    /// g = ∂ℓ/∂(x, y, θ), per m and per rad.
    pub gradient: [f64; 3],
    /// C = Σ JᵀJ / σ_l², the Gauss-Newton curvature of −ℓ (positive semi-definite).
    pub curvature: [[f64; 3]; 3],
}

impl LikelihoodModel {
    /// The model's log-likelihood at offset `d` = (dx m, dy m, dθ rad).
    pub fn at(&self, d: [f64; 3]) -> f64 {
        let mut q = 0.0;
        for a in 0..3 {
            for b in 0..3 {
                q += d[a] * self.curvature[a][b] * d[b];
            }
        }
        self.log_likelihood + self.gradient[0] * d[0] + self.gradient[1] * d[1] + self.gradient[2] * d[2] - 0.5 * q
    }
}

/// What a beam's end point matched: the end point (world), the nearest mean point, the line's
/// direction to the second nearest and its squared length where the distance is to that line,
/// and the squared distance.
struct Nearest {
    hit: (f64, f64),
    m1: (f64, f64),
    line: Option<(f64, f64, f64)>,
    d2: f64,
}

/// The surface beam `b` ends nearest to at `pose` ((sin θ, cos θ) given), as [`fit_every`]
/// finds it; `None` where it matches nothing.
#[inline(always)]
fn nearest_surface(grid: &Grid, p: &MatcherParams, pose: &Pose2, (s, c): (f64, f64), b: &BeamPoint) -> Option<Nearest> {
    let (hit, free) = end_points(pose, (s, c), b);
    let (hi, hj) = grid.cell_of(hit.0, hit.1);
    let k = p.kernel_cells;
    // Within one tile (the window and the cells beside it): no tile search per cell.
    let tile = grid.tile_around(hi, hj, k + 1);
    if matches!(tile, Some(TileRef::Empty)) {
        return None;
    }
    let cell = |i: i32, j: i32| match &tile {
        Some(t) => t.cell(i, j),
        None => grid.cell(i, j),
    };
    nearest_in_window(
        p,
        grid.resolution_m(),
        hit,
        (hi, hj),
        beam_direction(hit, free),
        |i, j| cell(i, j).and_then(|c| grid.mean_of(c, i, j, p.occupied_log_odds)),
        |i, j| cell(i, j).is_some_and(|f| f.log_odds > p.occupied_log_odds),
    )
}

/// Beam `b`'s end point and the point one cell nearer, in the world at `pose` ((sin θ, cos θ)
/// given).
#[inline(always)]
fn end_points(pose: &Pose2, (s, c): (f64, f64), b: &BeamPoint) -> ((f64, f64), (f64, f64)) {
    let to_world = |q: (f64, f64)| (pose.x_m + c * q.0 - s * q.1, pose.y_m + s * q.0 + c * q.1);
    (to_world(b.hit), to_world(b.free))
}

/// One cell towards the sensor, from the beam's direction quantised to the 8 neighbours (the
/// same whichever cell the end point falls in, so the score has no jumps where it crosses a
/// cell border).
#[inline(always)]
fn beam_direction(hit: (f64, f64), free: (f64, f64)) -> (i32, i32) {
    let (bx, by) = (free.0 - hit.0, free.1 - hit.1);
    let t = 0.414 * bx.abs().max(by.abs());
    (if bx.abs() >= t { bx.signum() as i32 } else { 0 }, if by.abs() >= t { by.signum() as i32 } else { 0 })
}

/// The nearest surface to the end point `hit` in cell (hi, hj): among the occupied cells of the
/// window of `kernel_cells` around it whose neighbour towards the sensor (`dir`) is not occupied,
/// the nearest mean hit point, and the line through the two nearest. `mean` gives an occupied
/// cell's mean hit point (`None` if not occupied), `occupied` whether a cell is occupied.
#[inline(always)]
fn nearest_in_window(
    p: &MatcherParams,
    resolution_m: f64,
    hit: (f64, f64),
    (hi, hj): (i32, i32),
    (di, dj): (i32, i32),
    mean: impl Fn(i32, i32) -> Option<(f64, f64)>,
    occupied: impl Fn(i32, i32) -> bool,
) -> Option<Nearest> {
    let k = p.kernel_cells;
    let mut two = TwoNearest::new(hit);
    for yy in -k..=k {
        for xx in -k..=k {
            let (i, j) = (hi + xx, hj + yy);
            let Some(m) = mean(i, j) else { continue };
            if occupied(i + di, j + dj) {
                continue;
            }
            two.push(m);
        }
    }
    two.surface(resolution_m, p.point_to_line)
}

/// The two mean hit points nearest to an end point, as they are offered.
struct TwoNearest {
    hit: (f64, f64),
    best: f64,
    m1: (f64, f64),
    second: f64,
    m2: (f64, f64),
}

impl TwoNearest {
    #[inline(always)]
    fn new(hit: (f64, f64)) -> Self {
        Self { hit, best: f64::INFINITY, m1: (0.0, 0.0), second: f64::INFINITY, m2: (0.0, 0.0) }
    }

    /// Offers mean hit point `m` (ties keep the earlier).
    #[inline(always)]
    fn push(&mut self, m: (f64, f64)) {
        let d2 = (m.0 - self.hit.0).powi(2) + (m.1 - self.hit.1).powi(2);
        if d2 < self.best {
            (self.second, self.m2) = (self.best, self.m1);
            (self.best, self.m1) = (d2, m);
        } else if d2 < self.second {
            (self.second, self.m2) = (d2, m);
        }
    }

    /// The surface: the nearest point, or the line through the two nearest when
    /// `point_to_line` and they are at least half a cell apart and the line is nearer; `None`
    /// if no point was offered.
    #[inline(always)]
    fn surface(self, resolution_m: f64, point_to_line: bool) -> Option<Nearest> {
        let Self { hit, mut best, m1, second, m2 } = self;
        if !best.is_finite() {
            return None;
        }
        let mut line = None;
        if point_to_line && second.is_finite() {
            // The surface through the two nearest mean points; only when they are apart enough
            // to give it a direction.
            let (ux, uy) = (m2.0 - m1.0, m2.1 - m1.1);
            let len2 = ux * ux + uy * uy;
            if len2 > 0.25 * resolution_m * resolution_m {
                let cross = ux * (hit.1 - m1.1) - uy * (hit.0 - m1.0);
                let line2 = cross * cross / len2;
                if line2 < best {
                    best = line2;
                    line = Some((ux, uy, len2));
                }
            }
        }
        Some(Nearest { hit, m1, line, d2: best })
    }
}

/// Side of the largest window of cells [`log_likelihood_lattice`] reads once for the nine
/// translations of a beam (wider windows: the cells are read per pose).
const LATTICE_WINDOW: usize = 8;

/// [`log_likelihood`] at the 27 poses of a lattice around `center`: (x + a·step_m, y + b·step_m,
/// θ + t·step_rad) for a, b, t in −1, 0, 1, at index 9(a+1) + 3(b+1) + (t+1). The same values as
/// 27 calls, to the last bit; each beam's window of cells is read once per rotation and shared by
/// the nine translations (the proposal's samples, docs/EQUATIONS.md §8).
pub fn log_likelihood_lattice(
    grid: &Grid,
    scan: &ScanPoints,
    center: &Pose2,
    p: &MatcherParams,
    step_m: f64,
    step_rad: f64,
) -> [f64; 27] {
    let inv_lik = 1.0 / (2.0 * p.likelihood_sigma_m * p.likelihood_sigma_m);
    let k = p.kernel_cells;
    let mut out = [0.0; 27];
    let mut poses = [Pose2::default(); 9];
    for t in -1..=1 {
        let theta = omni::wrap_angle(center.theta_rad + t as f64 * step_rad);
        let sc = theta.sin_cos();
        for (n, pose) in poses.iter_mut().enumerate() {
            let (a, b) = (n as i32 / 3 - 1, n as i32 % 3 - 1);
            *pose =
                Pose2 { x_m: center.x_m + a as f64 * step_m, y_m: center.y_m + b as f64 * step_m, theta_rad: theta };
        }
        let index = |n: usize| 3 * n + (t + 1) as usize;
        let mut candidates = [(0, 0, (0.0, 0.0)); LATTICE_WINDOW * LATTICE_WINDOW];
        for beam in &scan.points {
            let mut ends = [((0.0, 0.0), (0, 0), (0, 0)); 9];
            let (mut lo, mut hi) = ((i32::MAX, i32::MAX), (i32::MIN, i32::MIN));
            for (end, pose) in ends.iter_mut().zip(&poses) {
                let (hit, free) = end_points(pose, sc, beam);
                let cell = grid.cell_of(hit.0, hit.1);
                (lo, hi) = ((lo.0.min(cell.0), lo.1.min(cell.1)), (hi.0.max(cell.0), hi.1.max(cell.1)));
                *end = (hit, cell, beam_direction(hit, free));
            }
            // Every cell a translation's window or its neighbours towards the sensor can touch.
            let (i0, j0) = (lo.0 - k - 1, lo.1 - k - 1);
            let (i1, j1) = (hi.0 + k + 1, hi.1 + k + 1);
            let (w, h) = ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize);
            if w > LATTICE_WINDOW || h > LATTICE_WINDOW {
                for (n, pose) in poses.iter().enumerate() {
                    out[index(n)] += match nearest_surface(grid, p, pose, sc, beam) {
                        Some(near) => -near.d2 * inv_lik,
                        None => p.null_log_likelihood,
                    };
                }
                continue;
            }
            let tile = grid.tile_holding((i0, j0), (i1, j1));
            if matches!(tile, Some(TileRef::Empty)) {
                for n in 0..9 {
                    out[index(n)] += p.null_log_likelihood;
                }
                continue;
            }
            // The window's matchable cells (occupied, the neighbour towards the sensor not), in
            // the order nearest_in_window visits them; the nine translations' directions agree
            // unless rounding splits them, and then each reads its own.
            let dir = ends[0].2;
            let shared_dir = ends.iter().all(|e| e.2 == dir);
            let cell_at = |i: i32, j: i32| match &tile {
                Some(t) => t.cell(i, j),
                None => grid.cell(i, j),
            };
            let mut count = 0;
            if shared_dir {
                for j in j0 + 1..j1 {
                    for i in i0 + 1..i1 {
                        let Some(m) = cell_at(i, j).and_then(|c| grid.mean_of(c, i, j, p.occupied_log_odds)) else {
                            continue;
                        };
                        if cell_at(i + dir.0, j + dir.1).is_some_and(|f| f.log_odds > p.occupied_log_odds) {
                            continue;
                        }
                        candidates[count] = (i, j, m);
                        count += 1;
                    }
                }
            }
            for (n, &(hit, (hi, hj), d)) in ends.iter().enumerate() {
                let near = if shared_dir {
                    let mut two = TwoNearest::new(hit);
                    for &(i, j, m) in &candidates[..count] {
                        if (i - hi).abs() <= k && (j - hj).abs() <= k {
                            two.push(m);
                        }
                    }
                    two.surface(grid.resolution_m(), p.point_to_line)
                } else {
                    nearest_in_window(
                        p,
                        grid.resolution_m(),
                        hit,
                        (hi, hj),
                        d,
                        |i, j| cell_at(i, j).and_then(|c| grid.mean_of(c, i, j, p.occupied_log_odds)),
                        |i, j| cell_at(i, j).is_some_and(|c| c.log_odds > p.occupied_log_odds),
                    )
                };
                out[index(n)] += match near {
                    Some(near) => -near.d2 * inv_lik,
                    None => p.null_log_likelihood,
                };
            }
        }
    }
    out
}

/// Gauss-Newton converges when a step, whole or halved, moves the pose by less than this (m)
/// and turns it by less than [`STEP_TOLERANCE_RAD`]: a fiftieth of a 0.05 m cell, and below
/// the proposal's lattice (0.02 m, 0.01 rad), which spreads the particles round the match.
/// Before 2026-12-06 it went on to 0.1 mm and 0.1 mrad: 10.1 linearisations a match on fr079
/// instead of 4.5, for the same scores (docs/grid_slam.md, "Gauss-Newton to 1 mm and 1 mrad").
const STEP_TOLERANCE_M: f64 = 1e-3;
/// See [`STEP_TOLERANCE_M`], rad.
const STEP_TOLERANCE_RAD: f64 = 1e-3;

/// What [`gauss_newton`] ended with.
struct GaussNewton {
    pose: Pose2,
    fit: Fit,
    /// The log-likelihood's model at `pose`.
    model: LikelihoodModel,
    /// It converged or raised the score (`false`: `pose` is the start, where no step raised the
    /// score).
    done: bool,
    /// Poses linearised, the start's included (what the tests count).
    #[cfg_attr(not(test), allow(dead_code))]
    evaluations: u32,
}

/// Gauss-Newton on the score from `start`: steps −H⁻¹g, halved until the score rises (at most
/// 4 times), until a step, whole or halved, is below `tolerance` (m, rad; such a step is not
/// evaluated: the pose has converged, or not if it is `start` and only halving made the step
/// that small), no halving raises the score, or after `MAX_ITERATIONS`.
fn gauss_newton(
    grid: &Grid,
    scan: &ScanPoints,
    start: &Pose2,
    p: &MatcherParams,
    tolerance: (f64, f64),
) -> GaussNewton {
    const MAX_ITERATIONS: u32 = 20;
    let (mut pose, mut lin) = (*start, linearize(grid, scan, start, p));
    let mut evaluations = 1;
    let converged = |scale: f64, step: &[f64; 3]| {
        scale * step[0].hypot(step[1]) < tolerance.0 && (scale * step[2]).abs() < tolerance.1
    };
    let mut done = false;
    for _ in 0..MAX_ITERATIONS {
        let Linearized { fit: f, h, g, .. } = &lin;
        // Levenberg's damping, relative to the diagonal, keeps a step defined where the scan
        // constrains a direction weakly (a corridor's length).
        let mut a = *h;
        for (d, row) in a.iter_mut().enumerate() {
            row[d] += 1e-6 + 1e-3 * row[d];
        }
        let Some(step) = solve3(&a, g) else { break };
        let mut scale = 1.0;
        let mut accepted = false;
        for _ in 0..5 {
            if converged(scale, &step) {
                // Converged, unless no step has raised the score from the start yet: a whole step
                // of more than the tolerance that no halving took leaves it to the pattern search.
                done |= scale == 1.0;
                break;
            }
            let cand = Pose2 {
                x_m: pose.x_m - scale * step[0],
                y_m: pose.y_m - scale * step[1],
                theta_rad: omni::wrap_angle(pose.theta_rad - scale * step[2]),
            };
            let next = linearize(grid, scan, &cand, p);
            evaluations += 1;
            if next.fit.score > f.score {
                (pose, lin) = (cand, next);
                done = true;
                accepted = true;
                break;
            }
            scale *= 0.5;
        }
        if !accepted || converged(scale, &step) {
            break;
        }
    }
    GaussNewton { pose, fit: lin.fit, model: lin.model, done, evaluations }
}

/// Lower Cholesky factor of a 3×3 symmetric matrix; `None` if it is not positive definite.
pub(crate) fn cholesky3(a: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let mut l = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..=i {
            let s: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
            if i == j {
                let d = a[i][i] - s;
                if d.is_nan() || d <= 0.0 {
                    return None;
                }
                l[i][j] = d.sqrt();
            } else {
                l[i][j] = (a[i][j] - s) / l[j][j];
            }
        }
    }
    Some(l)
}

/// x with a·x = b for a symmetric positive definite 3×3 `a`; `None` if it is not.
fn solve3(a: &[[f64; 3]; 3], b: &[f64; 3]) -> Option<[f64; 3]> {
    let l = cholesky3(a)?;
    let mut y = [0.0; 3];
    for i in 0..3 {
        y[i] = (b[i] - (0..i).map(|k| l[i][k] * y[k]).sum::<f64>()) / l[i][i];
    }
    let mut x = [0.0; 3];
    for i in (0..3).rev() {
        x[i] = (y[i] - (i + 1..3).map(|k| l[k][i] * x[k]).sum::<f64>()) / l[i][i];
    }
    Some(x)
}

/// e^(−y) for y ≥ 0, to a relative error below 1e-8 (against libm's `exp`, which took a tenth
/// of the matcher's time as a library call): y = n·ln 2 + r with |r| ≤ ln 2 / 2, e^(−r) by its
/// Taylor series to the 8th power, 2^(−n) from the exponent bits. 0 beyond y = 700.
#[inline(always)]
pub fn exp_neg(y: f64) -> f64 {
    if y.is_nan() {
        return f64::NAN;
    }
    if y >= 700.0 {
        return 0.0;
    }
    let y = y.max(0.0);
    let n = (y * std::f64::consts::LOG2_E + 0.5) as i64;
    let r = n as f64 * std::f64::consts::LN_2 - y;
    // e^r, |r| ≤ 0.347: Horner over 1/k!.
    let p = 1.0
        + r * (1.0
            + r * (1.0 / 2.0
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0
                        + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0 + r * (1.0 / 40320.0))))))));
    p * f64::from_bits(((1023 - n) as u64) << 52)
}

/// Pattern search from `start`: poll the six moves (±x, ±y, ±θ) starting with the last one that
/// improved, take the first that improves the score; when none does, with `gauss_newton`,
/// Gauss-Newton on the score from there (the match, unless no step of it raises the score),
/// else halve the steps; stop after `refinements` halvings. gmapping takes the best of the six in each round: on a smooth score
/// this visits the same optimum with about 63 instead of 82 fits per match (indoor mission).
/// Returns the best pose found and its fit.
pub fn optimize(grid: &Grid, scan: &ScanPoints, start: &Pose2, p: &MatcherParams) -> (Pose2, Fit) {
    let (pose, fit, _) = search(grid, scan, start, p);
    (pose, fit)
}

/// [`optimize`], with the log-likelihood's quadratic model at the match (Gauss-Newton's last
/// linearisation, or one more where the match did not end by Gauss-Newton).
pub fn optimize_modelled(
    grid: &Grid,
    scan: &ScanPoints,
    start: &Pose2,
    p: &MatcherParams,
) -> (Pose2, Fit, LikelihoodModel) {
    let (pose, fit, model) = search(grid, scan, start, p);
    let model = model.unwrap_or_else(|| linearize(grid, scan, &pose, p).model);
    (pose, fit, model)
}

/// [`optimize`]'s search; the log-likelihood's model at the result where Gauss-Newton ended it.
fn search(grid: &Grid, scan: &ScanPoints, start: &Pose2, p: &MatcherParams) -> (Pose2, Fit, Option<LikelihoodModel>) {
    let mut current = *start;
    // Coarse to fine: the first `coarse_refinements` step sizes poll every `coarse_stride`-th
    // point, the finer ones all of them.
    let coarse = p.coarse_stride.max(1) > 1 && p.coarse_refinements > 0;
    let mut stride = if coarse { p.coarse_stride } else { 1 };
    let mut current_fit = fit_every(grid, scan, stride, &current, p, true);
    let (mut ld, mut ad) = (p.linear_step_m, p.angular_step_rad);
    let mut refinement = 0u32;
    let mut first = 0usize;
    let mut evaluations = 0u32;
    let mut gauss_newton_tried = false;
    loop {
        let moves = [(ld, 0.0, 0.0), (-ld, 0.0, 0.0), (0.0, ld, 0.0), (0.0, -ld, 0.0), (0.0, 0.0, ad), (0.0, 0.0, -ad)];
        let mut improved = false;
        for k in 0..moves.len() {
            let m = (first + k) % moves.len();
            let (dx, dy, dth) = moves[m];
            let cand = Pose2 {
                x_m: current.x_m + dx,
                y_m: current.y_m + dy,
                theta_rad: omni::wrap_angle(current.theta_rad + dth),
            };
            let f = fit_every(grid, scan, stride, &cand, p, true);
            evaluations += 1;
            if f.score > current_fit.score {
                (current, current_fit) = (cand, f);
                first = m;
                improved = true;
                break;
            }
        }
        if !improved {
            if p.gauss_newton && !gauss_newton_tried {
                // Gauss-Newton from the first step size's optimum; where it cannot raise the
                // score (a ridge of the score, a correspondence that flips), the steps are
                // halved as without it.
                gauss_newton_tried = true;
                let gn = gauss_newton(grid, scan, &current, p, (STEP_TOLERANCE_M, STEP_TOLERANCE_RAD));
                if gn.done {
                    return (gn.pose, gn.fit, Some(gn.model));
                }
            }
            if refinement >= p.refinements {
                break;
            }
            refinement += 1;
            ld *= 0.5;
            ad *= 0.5;
            if stride > 1 && refinement >= p.coarse_refinements {
                stride = 1;
                current_fit = fit(grid, scan, &current, p);
            }
        }
        // A bound on the work: the steps are halved often enough long before this.
        if evaluations > 1200 {
            break;
        }
    }
    if stride > 1 {
        current_fit = fit(grid, scan, &current, p);
    }
    (current, current_fit, None)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::LogOddsParams;

    /// A room 6 × 4 m scanned from its middle: the grid and the body-frame points.
    fn room() -> (Grid, ScanPoints) {
        let lp = LogOddsParams::default();
        let mut g = Grid::new(0.05);
        let mut pts = ScanPoints::default();
        let walls = |a: f64| -> f64 {
            // Distance from (0,0) along direction a to the box's walls.
            let (s, c) = a.sin_cos();
            // Walls off the cell borders (3.02, 2.02 m).
            let tx = if c.abs() > 1e-9 { 3.02 / c.abs() } else { f64::INFINITY };
            let ty = if s.abs() > 1e-9 { 2.02 / s.abs() } else { f64::INFINITY };
            tx.min(ty)
        };
        for k in 0..360 {
            let a = (k as f64).to_radians();
            let r = walls(a);
            let (s, c) = a.sin_cos();
            for _ in 0..3 {
                g.cast((0.0, 0.0), (r * c, r * s), true, &lp);
            }
            pts.points.push(BeamPoint { hit: (r * c, r * s), free: ((r - 0.05) * c, (r - 0.05) * s) });
        }
        (g, pts)
    }

    #[test]
    fn exp_neg_agrees_with_libm() {
        let mut y = 0.0;
        while y < 700.0 {
            let (a, b) = (exp_neg(y), (-y).exp());
            assert!((a - b).abs() <= 1e-8 * b, "y {y}: {a} against {b}");
            y += 0.0137;
        }
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(800.0), 0.0);
        assert_eq!(exp_neg(f64::INFINITY), 0.0);
        assert!(exp_neg(f64::NAN).is_nan());
    }

    #[test]
    fn hill_climbing_recovers_a_displaced_pose() {
        let (g, pts) = room();
        let p = MatcherParams::default();
        let start = Pose2 { x_m: 0.06, y_m: -0.04, theta_rad: 0.02 };
        let (best, f) = optimize(&g, &pts, &start, &p);
        assert!(best.x_m.abs() < 0.01 && best.y_m.abs() < 0.01 && best.theta_rad.abs() < 0.005, "{best:?}");
        assert!(f.matched > 340, "{f:?}");
        let at_truth = fit(&g, &pts, &Pose2::default(), &p);
        assert!(at_truth.log_likelihood > fit(&g, &pts, &start, &p).log_likelihood);
    }

    #[test]
    fn coarse_steps_on_a_subset_end_where_all_points_do_and_the_fit_is_over_all() {
        let (g, pts) = room();
        let start = Pose2 { x_m: 0.06, y_m: -0.04, theta_rad: 0.02 };
        let fine = MatcherParams::default();
        let coarse = MatcherParams { coarse_stride: 8, coarse_refinements: 3, ..fine };
        let (a, fa) = optimize(&g, &pts, &start, &fine);
        let (b, fb) = optimize(&g, &pts, &start, &coarse);
        assert!((a.x_m - b.x_m).abs() < 0.005 && (a.y_m - b.y_m).abs() < 0.005, "{a:?} against {b:?}");
        assert!((a.theta_rad - b.theta_rad).abs() < 0.003, "{a:?} against {b:?}");
        // The returned fit is over every point, as the fine one.
        assert_eq!(fb, fit(&g, &pts, &b, &fine));
        assert!((fb.score - fa.score).abs() < 0.02 * fa.score, "{fa:?} against {fb:?}");
        assert_eq!(log_likelihood(&g, &pts, &b, &fine), fb.log_likelihood);
    }

    #[test]
    fn solve3_solves_a_positive_definite_system_and_refuses_an_indefinite_one() {
        let a = [[4.0, 1.0, 0.5], [1.0, 3.0, -0.2], [0.5, -0.2, 2.0]];
        let x = [0.3, -1.2, 2.5];
        let b = [0, 1, 2].map(|r| (0..3).map(|c| a[r][c] * x[c]).sum::<f64>());
        let got = solve3(&a, &b).expect("positive definite");
        for k in 0..3 {
            assert!((got[k] - x[k]).abs() < 1e-12, "{got:?}");
        }
        assert!(solve3(&[[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]], &b).is_none());
    }

    #[test]
    fn gauss_newton_ends_where_hill_climbing_does() {
        // From displaced starts (up to 7 cm and 0.06 rad), Gauss-Newton from the start and
        // gmapping's step halving reach the same optimum: within its step tolerance of each
        // other and a score as high.
        let (g, pts) = room();
        let gn = MatcherParams::default();
        assert!(gn.gauss_newton);
        let hill = MatcherParams { gauss_newton: false, ..gn };
        for (dx, dy, dth) in [(0.06, -0.04, 0.02), (-0.03, 0.07, -0.04), (0.02, 0.01, 0.06)] {
            let start = Pose2 { x_m: dx, y_m: dy, theta_rad: dth };
            let (a, fa) = optimize(&g, &pts, &start, &gn);
            let (b, fb) = optimize(&g, &pts, &start, &hill);
            assert!((a.x_m - b.x_m).abs() < 1e-3 && (a.y_m - b.y_m).abs() < 1e-3, "{a:?} against {b:?}");
            assert!((a.theta_rad - b.theta_rad).abs() < 1e-3, "{a:?} against {b:?}");
            assert!(fa.score >= fb.score - 1e-3 * fb.score, "{fa:?} against {fb:?}");
            assert!(a.x_m.abs() < 0.01 && a.y_m.abs() < 0.01 && a.theta_rad.abs() < 0.005, "{a:?}");
            // The returned fit is the fit at the returned pose.
            assert_eq!(fa, fit(&g, &pts, &a, &gn));
        }
    }

    #[test]
    fn gauss_newton_stops_at_its_tolerance_near_the_full_optimum_with_fewer_evaluations() {
        // Run to a step of 1e-9 m and rad, Gauss-Newton reaches the score's optimum to machine
        // precision; stopped at the tolerance it ends within it, in fewer evaluations.
        let (g, mut pts) = room();
        // Range noise (±1 cm, deterministic): the optimum is not where every residual is zero.
        for (k, b) in pts.points.iter_mut().enumerate() {
            let e = 0.01 * (k as f64 * 12.9898).sin();
            let r = b.hit.0.hypot(b.hit.1);
            b.hit = (b.hit.0 * (1.0 + e / r), b.hit.1 * (1.0 + e / r));
        }
        let p = MatcherParams::default();
        let tolerance = (STEP_TOLERANCE_M, STEP_TOLERANCE_RAD);
        for start in
            [Pose2 { x_m: 0.03, y_m: -0.02, theta_rad: 0.015 }, Pose2 { x_m: -0.04, y_m: 0.01, theta_rad: -0.03 }]
        {
            let full = gauss_newton(&g, &pts, &start, &p, (1e-9, 1e-9));
            let gn = gauss_newton(&g, &pts, &start, &p, tolerance);
            assert!(full.done && gn.done);
            assert!(gn.evaluations < full.evaluations, "{} against {}", gn.evaluations, full.evaluations);
            let e = full.pose.between(&gn.pose);
            assert!(e.x_m.hypot(e.y_m) < tolerance.0 && e.theta_rad.abs() < tolerance.1, "{e:?}");
            assert_eq!(gn.fit, fit(&g, &pts, &gn.pose, &p));
            // From the optimum, the first step is below the tolerance: no pose is evaluated.
            let again = gauss_newton(&g, &pts, &full.pose, &p, tolerance);
            assert!(again.done);
            assert_eq!((again.pose, again.evaluations), (full.pose, 1));
        }
    }

    #[test]
    fn the_normal_equations_point_downhill() {
        // The step −H⁻¹g from a displaced pose moves towards the true pose in every coordinate
        // the room constrains.
        let (g, pts) = room();
        let p = MatcherParams::default();
        let start = Pose2 { x_m: 0.02, y_m: -0.015, theta_rad: 0.01 };
        let Linearized { fit: f, h, g: grad, .. } = linearize(&g, &pts, &start, &p);
        assert_eq!(f, fit(&g, &pts, &start, &p));
        let step = solve3(&h, &grad).expect("positive definite");
        let after = [start.x_m - step[0], start.y_m - step[1], start.theta_rad - step[2]];
        assert!(after[0].abs() < 0.5 * start.x_m.abs(), "{after:?}");
        assert!(after[1].abs() < 0.5 * start.y_m.abs(), "{after:?}");
        assert!(after[2].abs() < 0.5 * start.theta_rad.abs(), "{after:?}");
    }

    #[test]
    fn the_lattice_evaluation_equals_27_evaluations_to_the_last_bit() {
        // The shared-window evaluation of the proposal's lattice gives what 27 calls of
        // log_likelihood give, exactly: around the room's centre (windows across tile borders
        // and inside tiles), with steps wider than the shared window (read per pose), and with
        // point-to-point distances.
        let (g, pts) = room();
        let p = MatcherParams::default();
        let centres =
            [Pose2 { x_m: 0.013, y_m: -0.021, theta_rad: 0.004 }, Pose2 { x_m: -0.4, y_m: 0.3, theta_rad: 2.9 }];
        for params in [p, MatcherParams { point_to_line: false, kernel_cells: 2, ..p }] {
            for centre in &centres {
                for (sm, sr) in [(0.02, 0.01), (0.2, 0.05)] {
                    let got = log_likelihood_lattice(&g, &pts, centre, &params, sm, sr);
                    for a in -1..=1 {
                        for b in -1..=1 {
                            for t in -1..=1 {
                                let x = Pose2 {
                                    x_m: centre.x_m + a as f64 * sm,
                                    y_m: centre.y_m + b as f64 * sm,
                                    theta_rad: omni::wrap_angle(centre.theta_rad + t as f64 * sr),
                                };
                                let want = log_likelihood(&g, &pts, &x, &params);
                                let n = (9 * (a + 1) + 3 * (b + 1) + (t + 1)) as usize;
                                assert_eq!(
                                    got[n].to_bits(),
                                    want.to_bits(),
                                    "{x:?} ({sm}, {sr}): {} against {want}",
                                    got[n]
                                );
                            }
                        }
                    }
                }
            }
        }
        // Beyond the mapped area every beam matches nothing.
        let far = Pose2 { x_m: 100.0, y_m: 100.0, theta_rad: 0.0 };
        let got = log_likelihood_lattice(&g, &pts, &far, &p, 0.02, 0.01);
        assert!(got.iter().all(|&l| l == p.null_log_likelihood * pts.points.len() as f64), "{got:?}");
    }

    #[test]
    fn the_likelihood_model_is_the_evaluated_likelihood_near_the_match() {
        // At the match the model's value is the fit's own; over the proposal's lattice (2 cm,
        // 0.01 rad) it follows the evaluated log-likelihood's drop from there to a fifth (the
        // beams keep the surfaces they matched); its curvature is positive definite where the
        // room constrains every direction. With hill climbing alone the model is made at its
        // own match.
        let (g, pts) = room();
        let p = MatcherParams::default();
        let start = Pose2 { x_m: 0.03, y_m: -0.02, theta_rad: 0.015 };
        for params in [p, MatcherParams { gauss_newton: false, ..p }] {
            let (star, f, model) = optimize_modelled(&g, &pts, &start, &params);
            assert_eq!((star, f), optimize(&g, &pts, &start, &params));
            assert_eq!(model.log_likelihood, f.log_likelihood);
            assert!(cholesky3(&model.curvature).is_some(), "{model:?}");
            let evaluated = log_likelihood_lattice(&g, &pts, &star, &params, 0.02, 0.01);
            for (n, &want) in evaluated.iter().enumerate() {
                let d =
                    [0.02 * ((n / 9) as f64 - 1.0), 0.02 * (((n / 3) % 3) as f64 - 1.0), 0.01 * ((n % 3) as f64 - 1.0)];
                let got = model.at(d);
                let drop = f.log_likelihood - want;
                assert!(
                    (got - want).abs() <= 0.2 * drop.abs() + 0.5,
                    "{d:?}: model {got}, evaluated {want} (at the match {})",
                    f.log_likelihood
                );
            }
        }
    }

    /// A room 8 × 5 m turned 17° against the grid, scanned (360 beams, noiseless) at `pose`.
    fn turned_room_scan(pose: &Pose2, res: f64) -> (Vec<(f64, f64)>, ScanPoints) {
        let turn = 17f64.to_radians();
        let (hx, hy) = (4.0, 2.5);
        let mut ends = Vec::new();
        let mut pts = ScanPoints::default();
        for k in 0..360 {
            let a = (k as f64).to_radians();
            // The beam in the room's frame.
            let (s, c) = (pose.theta_rad + a - turn).sin_cos();
            let (ct, st) = (turn.cos(), turn.sin());
            let (ox, oy) = (ct * pose.x_m + st * pose.y_m, -st * pose.x_m + ct * pose.y_m);
            let tx = if c > 1e-9 {
                (hx - ox) / c
            } else if c < -1e-9 {
                (-hx - ox) / c
            } else {
                f64::INFINITY
            };
            let ty = if s > 1e-9 {
                (hy - oy) / s
            } else if s < -1e-9 {
                (-hy - oy) / s
            } else {
                f64::INFINITY
            };
            let r = tx.min(ty);
            let (bs, bc) = a.sin_cos();
            ends.push((r * bc, r * bs));
            pts.points.push(BeamPoint { hit: (r * bc, r * bs), free: ((r - res) * bc, (r - res) * bs) });
        }
        (ends, pts)
    }

    #[test]
    fn a_scan_matched_from_its_true_pose_stays_there_to_a_fraction_of_a_cell() {
        // Walls at an angle to the grid, a map built from scans at known poses, new scans from
        // poses at arbitrary places within their cells matched from the truth: the match must not
        // walk off on steps of the score (gmapping's "one cell nearer" cell jumps as end points
        // cross cell borders; with it this error was 2-3 cm).
        let (res, lp, p) = (0.05, LogOddsParams::default(), MatcherParams::default());
        let mut g = Grid::new(res);
        let world = |pose: &Pose2, q: (f64, f64)| {
            let (s, c) = pose.theta_rad.sin_cos();
            (pose.x_m + c * q.0 - s * q.1, pose.y_m + s * q.0 + c * q.1)
        };
        for k in 0..12 {
            let pose =
                Pose2 { x_m: -2.5 + 0.43 * k as f64, y_m: 0.3 * ((k % 3) as f64 - 1.0), theta_rad: 0.2 * k as f64 };
            let (ends, _) = turned_room_scan(&pose, res);
            for e in ends {
                g.cast((pose.x_m, pose.y_m), world(&pose, e), true, &lp);
            }
        }
        let (mut sum2, mut worst) = (0.0, 0.0f64);
        let n = 24;
        for k in 0..n {
            let f = k as f64;
            let truth = Pose2 { x_m: -2.0 + 0.1731 * f, y_m: -0.6 + 0.0517 * f, theta_rad: -1.0 + 0.0913 * f };
            let (_, pts) = turned_room_scan(&truth, res);
            let (m, _) = optimize(&g, &pts, &truth, &p);
            let e = (m.x_m - truth.x_m).hypot(m.y_m - truth.y_m);
            sum2 += e * e;
            worst = worst.max(e);
        }
        let rms = (sum2 / n as f64).sqrt();
        assert!(rms < 0.008 && worst < 0.02, "rms {rms:.4} m, worst {worst:.4} m");
    }
}

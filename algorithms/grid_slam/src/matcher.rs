//! Scan matching against a particle's own grid (gmapping's matcher, SPEC §8 step 1): each beam's
//! end point is scored by its distance to the mean hit point of the nearest occupied cell in a
//! small window whose cell one step nearer along the beam is not occupied (so a wall is matched
//! from the side the beam saw it). Hill climbing over x, y, θ with step halving.

use crate::grid::Grid;
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
    /// Log-odds above which a cell counts as occupied.
    pub occupied_log_odds: f32,
    /// A match is accepted when its score is at least this share of the beams used.
    pub min_score_share: f64,
}

impl Default for MatcherParams {
    fn default() -> Self {
        Self {
            kernel_cells: 1,
            score_sigma_m: 0.1,
            likelihood_sigma_m: 0.15,
            null_log_likelihood: -0.5,
            linear_step_m: 0.05,
            angular_step_rad: 0.05,
            refinements: 5,
            beam_stride: 1,
            occupied_log_odds: 0.0,
            min_score_share: 0.15,
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
    let (s, c) = pose.theta_rad.sin_cos();
    let to_world = |q: (f64, f64)| (pose.x_m + c * q.0 - s * q.1, pose.y_m + s * q.0 + c * q.1);
    let inv_score = 1.0 / (2.0 * p.score_sigma_m * p.score_sigma_m);
    let inv_lik = 1.0 / (2.0 * p.likelihood_sigma_m * p.likelihood_sigma_m);
    let (mut score, mut ll, mut matched) = (0.0, 0.0, 0usize);
    let k = p.kernel_cells;
    for b in &scan.points {
        let hit = to_world(b.hit);
        let free = to_world(b.free);
        let (hi, hj) = grid.cell_of(hit.0, hit.1);
        let (fi, fj) = grid.cell_of(free.0, free.1);
        let (di, dj) = (fi - hi, fj - hj);
        let mut best = f64::INFINITY;
        for yy in -k..=k {
            for xx in -k..=k {
                let (i, j) = (hi + xx, hj + yy);
                let Some((mx, my)) = grid.occupied_mean(i, j, p.occupied_log_odds) else { continue };
                if grid.log_odds(i + di, j + dj) > p.occupied_log_odds {
                    continue;
                }
                let d2 = (mx - hit.0).powi(2) + (my - hit.1).powi(2);
                if d2 < best {
                    best = d2;
                }
            }
        }
        if best.is_finite() {
            score += (-best * inv_score).exp();
            ll += -best * inv_lik;
            matched += 1;
        } else {
            ll += p.null_log_likelihood;
        }
    }
    Fit { score, log_likelihood: ll, matched }
}

/// Hill climbing from `start`: the best pose found and its fit.
pub fn optimize(grid: &Grid, scan: &ScanPoints, start: &Pose2, p: &MatcherParams) -> (Pose2, Fit) {
    let mut current = *start;
    let mut current_fit = fit(grid, scan, &current, p);
    let (mut ld, mut ad) = (p.linear_step_m, p.angular_step_rad);
    let mut refinement = 0u32;
    let mut best_score = f64::NEG_INFINITY;
    // gmapping's loop: halve the steps whenever a round brings no improvement.
    let mut rounds = 0;
    loop {
        if best_score >= current_fit.score {
            refinement += 1;
            ld *= 0.5;
            ad *= 0.5;
        }
        best_score = current_fit.score;
        let mut best_local = current;
        let mut best_local_fit = current_fit;
        let moves = [(ld, 0.0, 0.0), (-ld, 0.0, 0.0), (0.0, ld, 0.0), (0.0, -ld, 0.0), (0.0, 0.0, ad), (0.0, 0.0, -ad)];
        for (dx, dy, dth) in moves {
            let cand = Pose2 {
                x_m: current.x_m + dx,
                y_m: current.y_m + dy,
                theta_rad: omni::wrap_angle(current.theta_rad + dth),
            };
            let f = fit(grid, scan, &cand, p);
            if f.score > best_local_fit.score {
                best_local = cand;
                best_local_fit = f;
            }
        }
        current = best_local;
        current_fit = best_local_fit;
        rounds += 1;
        if !(current_fit.score > best_score || refinement < p.refinements) || rounds > 200 {
            break;
        }
    }
    (current, current_fit)
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
}

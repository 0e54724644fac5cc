//! Sparse 2-D pose-graph optimisation (the back end of Cartographer, Hess et al. 2016 §V, and of
//! Karto's sparse pose adjustment, Konolige et al. 2010), docs/EQUATIONS.md §8.
//!
//! Variables: poses `map_from_body` (x, y in m, θ in rad). An [`Edge`] from `i` to `j` measures
//! `z = x_i⁻¹ ⊕ x_j` (the pose of `j` in the frame of `i`) with a diagonal information (1/σ²
//! for x, y in the frame of `z`, and θ). The error is `e = z⁻¹ ⊕ (x_i⁻¹ ⊕ x_j)` written out as
//!
//! ```text
//! e_xy = R_zᵀ (R_iᵀ (t_j − t_i) − t_z),   e_θ = wrap(θ_j − θ_i − θ_z)
//! ```
//!
//! and minimised by Levenberg–Marquardt over Σ ρ(eᵀ Ω e): the normal equations are sparse (one
//! 3×3 block per pose and per edge) and solved by a sparse Cholesky factorisation with a
//! fill-reducing ordering (`faer`, see the README's note on the choice). Edges may carry a
//! robust kernel ([`Kernel`]): iteratively reweighted least squares, so a false loop closure
//! whose error stays large weighs little. One pose is held fixed (the gauge).

use crate::GridSlamError;
use omni::Pose2;
use std::collections::HashMap;

/// A robust kernel ρ(s) over the squared whitened error s = eᵀ Ω e; its scale `k` is in
/// whitened units (standard deviations).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Kernel {
    /// Quadratic: every edge weighs alike whatever its error.
    None,
    /// Huber: quadratic up to `k`, linear beyond.
    Huber(f64),
    /// Cauchy: ρ(s) = k² ln(1 + s/k²); weight 1/(1 + s/k²).
    Cauchy(f64),
}

impl Kernel {
    /// ρ(s).
    pub fn cost(&self, s: f64) -> f64 {
        match *self {
            Kernel::None => s,
            Kernel::Huber(k) => {
                let r = s.sqrt();
                if r <= k { s } else { 2.0 * k * r - k * k }
            }
            Kernel::Cauchy(k) => k * k * (s / (k * k)).ln_1p(),
        }
    }

    /// ρ'(s): the weight of the edge in the reweighted least squares.
    pub fn weight(&self, s: f64) -> f64 {
        match *self {
            Kernel::None => 1.0,
            Kernel::Huber(k) => {
                let r = s.sqrt();
                if r <= k { 1.0 } else { k / r }
            }
            Kernel::Cauchy(k) => 1.0 / (1.0 + s / (k * k)),
        }
    }
}

/// A relative-pose measurement between two poses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Edge {
    /// Index of the pose the measurement is expressed in.
    pub from: usize,
    /// Index of the pose measured.
    pub to: usize,
    /// `from_from_to`: the pose of `to` in the frame of `from`.
    pub measured: Pose2,
    /// Diagonal information (1/σ²) of x, y (m⁻²) and θ (rad⁻²).
    pub information: [f64; 3],
    /// Robust kernel.
    pub kernel: Kernel,
}

impl Edge {
    /// The error `e` at `poses` (x, y in the measurement's frame, m; θ, rad).
    pub fn error(&self, poses: &[Pose2]) -> [f64; 3] {
        let (xi, xj) = (&poses[self.from], &poses[self.to]);
        let z = &self.measured;
        let (si, ci) = xi.theta_rad.sin_cos();
        let (sz, cz) = z.theta_rad.sin_cos();
        let (dx, dy) = (xj.x_m - xi.x_m, xj.y_m - xi.y_m);
        // R_iᵀ (t_j − t_i) − t_z, then R_zᵀ.
        let (ax, ay) = (ci * dx + si * dy - z.x_m, -si * dx + ci * dy - z.y_m);
        [cz * ax + sz * ay, -sz * ax + cz * ay, omni::wrap_angle(xj.theta_rad - xi.theta_rad - z.theta_rad)]
    }

    /// The squared whitened error eᵀ Ω e.
    pub fn chi2(&self, poses: &[Pose2]) -> f64 {
        let e = self.error(poses);
        e[0] * e[0] * self.information[0] + e[1] * e[1] * self.information[1] + e[2] * e[2] * self.information[2]
    }

    /// The error and its Jacobians with respect to pose `from` (A) and pose `to` (B), row-major.
    fn linearise(&self, poses: &[Pose2]) -> ([f64; 3], [[f64; 3]; 3], [[f64; 3]; 3]) {
        let (xi, xj) = (&poses[self.from], &poses[self.to]);
        let (si, ci) = xi.theta_rad.sin_cos();
        let (sz, cz) = self.measured.theta_rad.sin_cos();
        let (dx, dy) = (xj.x_m - xi.x_m, xj.y_m - xi.y_m);
        // M = R_zᵀ R_iᵀ = R(−(θ_i + θ_z)).
        let (sm, cm) = (xi.theta_rad + self.measured.theta_rad).sin_cos();
        let m = [[cm, sm], [-sm, cm]];
        // R_zᵀ · dR_iᵀ/dθ_i · (t_j − t_i), dR_iᵀ/dθ = [[−s, c], [−c, −s]].
        let (gx, gy) = (-si * dx + ci * dy, -ci * dx - si * dy);
        let (hx, hy) = (cz * gx + sz * gy, -sz * gx + cz * gy);
        let a = [[-m[0][0], -m[0][1], hx], [-m[1][0], -m[1][1], hy], [0.0, 0.0, -1.0]];
        let b = [[m[0][0], m[0][1], 0.0], [m[1][0], m[1][1], 0.0], [0.0, 0.0, 1.0]];
        (self.error(poses), a, b)
    }
}

/// Settings of [`optimize`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OptimizeParams {
    /// Levenberg–Marquardt iterations at most.
    pub max_iterations: usize,
    /// Stop when the relative decrease of the cost falls below this.
    pub relative_tolerance: f64,
    /// The pose held fixed.
    pub fixed: usize,
}

impl Default for OptimizeParams {
    fn default() -> Self {
        Self { max_iterations: 30, relative_tolerance: 1e-6, fixed: 0 }
    }
}

/// What [`optimize`] did.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct OptimizeReport {
    /// Iterations run (accepted and rejected steps).
    pub iterations: usize,
    /// Σ ρ(eᵀ Ω e) before.
    pub initial_cost: f64,
    /// ... and after.
    pub final_cost: f64,
}

/// Total robust cost at `poses`.
pub fn cost(poses: &[Pose2], edges: &[Edge]) -> f64 {
    edges.iter().map(|e| e.kernel.cost(e.chi2(poses))).sum()
}

/// Minimises Σ ρ(eᵀ Ω e) over `poses` (all but `params.fixed`) in place.
///
/// Errors: an edge names a pose that does not exist, a value is not finite, or the normal
/// equations are not positive definite (a pose no edge constrains).
pub fn optimize(poses: &mut [Pose2], edges: &[Edge], params: &OptimizeParams) -> Result<OptimizeReport, GridSlamError> {
    let n = poses.len();
    let bad = |why: String| GridSlamError::Optimisation { why };
    if n == 0 || params.fixed >= n {
        return Err(bad(format!("{n} poses, fixed pose {} does not exist", params.fixed)));
    }
    for (k, e) in edges.iter().enumerate() {
        if e.from >= n || e.to >= n || e.from == e.to {
            return Err(bad(format!("edge {k} joins poses {} and {} of {n}", e.from, e.to)));
        }
        let finite = [e.measured.x_m, e.measured.y_m, e.measured.theta_rad].iter().all(|v| v.is_finite())
            && e.information.iter().all(|v| v.is_finite() && *v > 0.0);
        if !finite {
            return Err(bad(format!("edge {k} ({} -> {}) has a non-finite measurement or information", e.from, e.to)));
        }
    }
    // Variable index of each pose (the fixed one has none).
    let var = |p: usize| -> Option<usize> {
        match p.cmp(&params.fixed) {
            std::cmp::Ordering::Less => Some(p),
            std::cmp::Ordering::Equal => None,
            std::cmp::Ordering::Greater => Some(p - 1),
        }
    };
    let dim = 3 * (n - 1);
    if dim == 0 {
        let c = cost(poses, edges);
        return Ok(OptimizeReport { iterations: 0, initial_cost: c, final_cost: c });
    }
    // The sparsity pattern (lower blocks), fixed over the iterations.
    let mut blocks: HashMap<(usize, usize), usize> = HashMap::new();
    for v in 0..n - 1 {
        let next = blocks.len();
        blocks.entry((v, v)).or_insert(next);
    }
    for e in edges {
        if let (Some(a), Some(b)) = (var(e.from), var(e.to)) {
            let key = if a >= b { (a, b) } else { (b, a) };
            let next = blocks.len();
            blocks.entry(key).or_insert(next);
        }
    }
    let mut order: Vec<((usize, usize), usize)> = blocks.iter().map(|(k, v)| (*k, *v)).collect();
    order.sort_by_key(|x| x.1);
    let mut symbolic: Option<faer::sparse::linalg::solvers::SymbolicLlt<usize>> = None;

    let initial_cost = cost(poses, edges);
    let mut current_cost = initial_cost;
    let mut lambda = 1e-4;
    let mut iterations = 0;
    let mut values = vec![[[0.0f64; 3]; 3]; blocks.len()];
    let mut rhs = vec![0.0f64; dim];
    while iterations < params.max_iterations {
        iterations += 1;
        for v in values.iter_mut() {
            *v = [[0.0; 3]; 3];
        }
        rhs.iter_mut().for_each(|r| *r = 0.0);
        for e in edges {
            let (err, ja, jb) = e.linearise(poses);
            let s = err[0] * err[0] * e.information[0]
                + err[1] * err[1] * e.information[1]
                + err[2] * err[2] * e.information[2];
            let w = e.kernel.weight(s);
            let om = [w * e.information[0], w * e.information[1], w * e.information[2]];
            let jac = [(var(e.from), ja), (var(e.to), jb)];
            for (vr, jr) in &jac {
                let Some(r) = *vr else { continue };
                // b_r += J_rᵀ Ω e
                for a in 0..3 {
                    rhs[3 * r + a] += (0..3).map(|k| jr[k][a] * om[k] * err[k]).sum::<f64>();
                }
                for (vc, jc) in &jac {
                    let Some(c) = *vc else { continue };
                    if r < c {
                        continue;
                    }
                    let slot = blocks[&(r, c)];
                    for a in 0..3 {
                        for b in 0..3 {
                            values[slot][a][b] += (0..3).map(|k| jr[k][a] * om[k] * jc[k][b]).sum::<f64>();
                        }
                    }
                }
            }
        }
        // Solve (H + λ diag H) δ = −b, retrying with a larger λ while the cost rises.
        let mut accepted = false;
        while iterations <= params.max_iterations {
            let mut triplets = Vec::with_capacity(order.len() * 9);
            for &((r, c), slot) in &order {
                for (a, block_row) in values[slot].iter().enumerate() {
                    for (b, &value) in block_row.iter().enumerate() {
                        let (row, col) = (3 * r + a, 3 * c + b);
                        if row < col {
                            continue;
                        }
                        let mut v = value;
                        if row == col {
                            v += lambda * v + 1e-9;
                        }
                        triplets.push(faer::sparse::Triplet::new(row, col, v));
                    }
                }
            }
            let h = faer::sparse::SparseColMat::<usize, f64>::try_new_from_triplets(dim, dim, &triplets)
                .map_err(|e| bad(format!("normal equations: {e:?}")))?;
            let sym = match &symbolic {
                Some(s) => s.clone(),
                None => {
                    let s = faer::sparse::linalg::solvers::SymbolicLlt::try_new(h.symbolic(), faer::Side::Lower)
                        .map_err(|e| bad(format!("symbolic factorisation: {e:?}")))?;
                    symbolic = Some(s.clone());
                    s
                }
            };
            let llt = faer::sparse::linalg::solvers::Llt::try_new_with_symbolic(sym, h.as_ref(), faer::Side::Lower)
                .map_err(|e| {
                    bad(format!("the normal equations are not positive definite ({e:?}): a pose is unconstrained"))
                })?;
            let b = faer::Mat::<f64>::from_fn(dim, 1, |i, _| -rhs[i]);
            let delta = faer::linalg::solvers::Solve::solve(&llt, &b);
            let mut trial = poses.to_vec();
            for (p, pose) in trial.iter_mut().enumerate() {
                if let Some(v) = var(p) {
                    pose.x_m += delta[(3 * v, 0)];
                    pose.y_m += delta[(3 * v + 1, 0)];
                    pose.theta_rad = omni::wrap_angle(pose.theta_rad + delta[(3 * v + 2, 0)]);
                }
            }
            let trial_cost = cost(&trial, edges);
            if !trial_cost.is_finite() {
                return Err(bad("the cost is not finite".to_string()));
            }
            if trial_cost <= current_cost {
                poses.copy_from_slice(&trial);
                let decrease = (current_cost - trial_cost) / current_cost.max(1e-300);
                current_cost = trial_cost;
                lambda = (lambda * 0.3).max(1e-9);
                accepted = true;
                if decrease < params.relative_tolerance {
                    return Ok(OptimizeReport { iterations, initial_cost, final_cost: current_cost });
                }
                break;
            }
            lambda *= 10.0;
            iterations += 1;
            if lambda > 1e8 {
                break;
            }
        }
        if !accepted {
            break;
        }
    }
    Ok(OptimizeReport { iterations, initial_cost, final_cost: current_cost })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(x: f64, y: f64, t: f64) -> Pose2 {
        Pose2 { x_m: x, y_m: y, theta_rad: t }
    }

    /// Numerical Jacobians agree with the analytic ones.
    #[test]
    fn jacobians_match_finite_differences() {
        let poses = vec![p(0.3, -1.2, 0.7), p(2.1, 0.4, -2.5)];
        let e = Edge { from: 0, to: 1, measured: p(0.5, 1.1, 0.3), information: [1.0; 3], kernel: Kernel::None };
        let (_, a, b) = e.linearise(&poses);
        let h = 1e-6;
        for (which, jac) in [(0usize, a), (1, b)] {
            for k in 0..3 {
                let mut plus = poses.clone();
                let mut minus = poses.clone();
                for (q, d) in [(&mut plus, h), (&mut minus, -h)] {
                    let v = &mut q[which];
                    match k {
                        0 => v.x_m += d,
                        1 => v.y_m += d,
                        _ => v.theta_rad += d,
                    }
                }
                let (ep, em) = (e.error(&plus), e.error(&minus));
                for (r, row) in jac.iter().enumerate() {
                    let num = (ep[r] - em[r]) / (2.0 * h);
                    assert!((num - row[k]).abs() < 1e-6, "pose {which} d{r}/d{k}: {num} vs {}", row[k]);
                }
            }
        }
    }

    /// A square loop with drifted odometry closes on one loop edge; a false loop edge under a
    /// robust kernel hardly moves it, without the kernel it bends the loop.
    #[test]
    fn loop_closes_and_false_edge_is_down_weighted() {
        // Truth: 40 poses around a 10 m square, heading along the path.
        let mut truth = Vec::new();
        for side in 0..4 {
            for k in 0..10 {
                let th = side as f64 * std::f64::consts::FRAC_PI_2;
                let (s, c) = th.sin_cos();
                let (ox, oy) = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)][side];
                truth.push(p(ox + c * k as f64, oy + s * k as f64, th));
            }
        }
        let odo_info = [1.0 / 0.01f64.powi(2), 1.0 / 0.01f64.powi(2), 1.0 / 0.005f64.powi(2)];
        let mut edges = Vec::new();
        let mut est = vec![truth[0]];
        for i in 0..truth.len() - 1 {
            let z = truth[i].between(&truth[i + 1]);
            // Biased odometry: heading creeps 0.01 rad per step, length +2 %.
            let zd = p(z.x_m * 1.02, z.y_m, z.theta_rad + 0.01);
            est.push(est[i].compose(&zd));
            edges.push(Edge { from: i, to: i + 1, measured: zd, information: odo_info, kernel: Kernel::None });
        }
        let loop_info = [1.0 / 0.02f64.powi(2), 1.0 / 0.02f64.powi(2), 1.0 / 0.01f64.powi(2)];
        let last = truth.len() - 1;
        edges.push(Edge {
            from: 0,
            to: last,
            measured: truth[0].between(&truth[last]),
            information: loop_info,
            kernel: Kernel::Huber(1.0),
        });
        let err = |q: &[Pose2]| -> f64 {
            q.iter().zip(&truth).map(|(a, b)| (a.x_m - b.x_m).hypot(a.y_m - b.y_m)).fold(0.0, f64::max)
        };
        let drift = err(&est);
        let mut closed = est.clone();
        optimize(&mut closed, &edges, &OptimizeParams::default()).unwrap();
        let after = err(&closed);
        assert!(drift > 2.0, "the drift should be large: {drift}");
        assert!(after < 0.4 * drift, "loop not closed: {drift} -> {after}");
        // A false closure: pose 15 claimed at pose 35's place.
        let false_edge =
            Edge { from: 35, to: 15, measured: p(0.0, 0.0, 0.0), information: loop_info, kernel: Kernel::Huber(1.0) };
        let mut robust = est.clone();
        let mut with_false = edges.clone();
        with_false.push(false_edge);
        optimize(&mut robust, &with_false, &OptimizeParams::default()).unwrap();
        let mut plain = est.clone();
        let mut quadratic = with_false.clone();
        for e in quadratic.iter_mut() {
            e.kernel = Kernel::None;
        }
        optimize(&mut plain, &quadratic, &OptimizeParams::default()).unwrap();
        assert!(err(&robust) < err(&plain), "robust {} vs quadratic {}", err(&robust), err(&plain));
        assert!(
            err(&robust) < 1.5 * after + 0.5,
            "the false edge moved the robust solution: {} vs {after}",
            err(&robust)
        );
    }

    /// Bad input is refused with a named error, not a panic.
    #[test]
    fn bad_edges_are_refused() {
        let mut poses = vec![p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0)];
        let e = Edge { from: 0, to: 5, measured: p(1.0, 0.0, 0.0), information: [1.0; 3], kernel: Kernel::None };
        assert!(optimize(&mut poses, &[e], &OptimizeParams::default()).is_err());
        let e = Edge { from: 0, to: 1, measured: p(f64::NAN, 0.0, 0.0), information: [1.0; 3], kernel: Kernel::None };
        assert!(optimize(&mut poses, &[e], &OptimizeParams::default()).is_err());
        // Pose 2 unconstrained.
        let mut poses = vec![p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(2.0, 0.0, 0.0)];
        let e = Edge { from: 0, to: 1, measured: p(1.0, 0.0, 0.0), information: [1.0; 3], kernel: Kernel::None };
        let r = optimize(&mut poses, &[e], &OptimizeParams::default());
        // A tiny diagonal keeps the factorisation from failing; the free pose must not move.
        if r.is_ok() {
            assert!((poses[2].x_m - 2.0).abs() < 1e-6);
        }
    }
}

//! Least-squares initialisation of the buoy estimator (EQUATIONS §5: "initialise by least-squares
//! trilateration from the first ranges").
//!
//! - [`trilaterate`]: position from ranges to known buoys, 2-D (with a known height difference)
//!   or 3-D (optionally with a depth constraint, which resolves the mirror ambiguity of buoys that
//!   all float at the surface). A linearised closed-form solution seeds a robust (Huber)
//!   Gauss-Newton.
//!
//! Degenerate problems are refused with a [`TrilaterationError`] (too few distinct buoys, buoys on
//! one line or in one plane, an ill-conditioned normal matrix, a poor fit) so the caller can wait
//! for more ranges. The result carries the sensitivity ∂x̂/∂rᵢ of the solution to each range,
//! from which a caller propagates range biases it did not solve for (a "consider" covariance).

#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector, Matrix2, Matrix3, SymmetricEigen, Vector2, Vector3};

use crate::error::TrilaterationError;

/// One range to a buoy at a known position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeObs {
    /// Buoy id (distinct ids count as distinct buoys).
    pub buoy_id: u32,
    /// Buoy position, m.
    pub buoy_m: Vector3<f64>,
    /// Measured range, m.
    pub range_m: f64,
    /// σ of the range, m (> 0).
    pub sigma_m: f64,
}

/// The unknowns of a trilateration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Geometry {
    /// Solve for (x, y); the vehicle is at z = `height_m`.
    Planar {
        /// The vehicle's z, m.
        height_m: f64,
    },
    /// Solve for (x, y, z), optionally with a measurement z = `depth.0` ± `depth.1` (from a
    /// pressure depth d: z = −d).
    Spatial {
        /// (z, σ) in m.
        z_constraint: Option<(f64, f64)>,
    },
}

/// Acceptance limits of a solution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    /// Distinct buoys needed (at least 3; 3-D without a z constraint needs at least 4).
    pub min_buoys: usize,
    /// Largest accepted condition number of the normal matrix.
    pub max_condition: f64,
    /// Largest accepted normalised RMS residual of the inliers (|e| ≤ 3).
    pub max_normalised_rms: f64,
    /// Huber constant of the robust weights (0: plain least squares).
    pub huber_k: f64,
}

impl Default for Limits {
    fn default() -> Self {
        Self { min_buoys: 3, max_condition: 1e8, max_normalised_rms: 3.0, huber_k: 1.345 }
    }
}

/// A trilateration result.
#[derive(Debug, Clone, PartialEq)]
pub struct Trilateration {
    /// Position, m (planar: z is the configured height).
    pub position_m: Vector3<f64>,
    /// Its covariance, m² (planar: the z row and column are 0).
    pub covariance_m2: Matrix3<f64>,
    /// ∂x̂/∂rᵢ: D × m (D = 2 planar, 3 spatial), one column per input range.
    pub sensitivity: DMatrix<f64>,
    /// Normalised RMS residual of the inliers.
    pub normalised_rms: f64,
    /// Distinct buoys used.
    pub buoys: usize,
}

/// Robust Gauss-Newton on normalised residuals eᵢ = (zᵢ − hᵢ(x))/σᵢ.
struct GnSolution {
    x: DVector<f64>,
    /// Jᵀ W J at the solution (J normalised).
    A: DMatrix<f64>,
    /// A⁻¹ Jᵀ W (normalised columns; divide column i by σᵢ for ∂x/∂zᵢ).
    gain: DMatrix<f64>,
    e: DVector<f64>,
}

fn huber_weight(e: f64, k: f64) -> f64 {
    if k > 0.0 && e.abs() > k { k / e.abs() } else { 1.0 }
}

fn huber_cost(e: f64, k: f64) -> f64 {
    if k > 0.0 && e.abs() > k { 2.0 * k * e.abs() - k * k } else { e * e }
}

fn gauss_newton(
    x0: DVector<f64>,
    huber_k: f64,
    max_condition: f64,
    residuals: impl Fn(&DVector<f64>) -> (DVector<f64>, DMatrix<f64>),
) -> Result<GnSolution, TrilaterationError> {
    const MAX_ITERATIONS: usize = 50;
    let cost_of = |e: &DVector<f64>| e.iter().map(|&ei| huber_cost(ei, huber_k)).sum::<f64>();
    let mut x = x0;
    let (mut e, mut J) = residuals(&x);
    let mut cost = cost_of(&e);
    for iteration in 0..=MAX_ITERATIONS {
        let w = DVector::from_iterator(e.len(), e.iter().map(|&ei| huber_weight(ei, huber_k)));
        let JtW = {
            let mut m = J.transpose();
            for (mut col, wi) in m.column_iter_mut().zip(w.iter()) {
                col *= *wi;
            }
            m
        };
        let A = &JtW * &J;
        let g = &JtW * &e;
        let Some(chol) = A.clone().cholesky() else {
            return Err(TrilaterationError::IllConditioned { condition: f64::INFINITY, max: max_condition });
        };
        let dx = chol.solve(&g);
        let converged = dx.norm() <= 1e-9 * (1.0 + x.norm());
        if converged || iteration == MAX_ITERATIONS {
            if !converged {
                return Err(TrilaterationError::NotConverged(MAX_ITERATIONS));
            }
            let gain = chol.solve(&JtW);
            return Ok(GnSolution { x, A, gain, e });
        }
        // Step halving keeps the (robust) cost from increasing.
        let mut step = 1.0;
        loop {
            let xn = &x + &dx * step;
            let (en, Jn) = residuals(&xn);
            let cn = cost_of(&en);
            if cn.is_finite() && (cn <= cost || step < 1e-3) {
                x = xn;
                e = en;
                J = Jn;
                cost = cn;
                break;
            }
            step *= 0.5;
        }
    }
    unreachable!("the loop returns at MAX_ITERATIONS")
}

fn condition_number(A: &DMatrix<f64>) -> f64 {
    let eig = SymmetricEigen::new(A.clone()).eigenvalues;
    let (lo, hi) = (eig.min(), eig.max());
    if lo <= 0.0 { f64::INFINITY } else { hi / lo }
}

/// Normalised RMS of the inliers (|e| ≤ 3); `PoorFit` when it exceeds `max` or when fewer
/// than half the residuals (or fewer than `min_inliers`) are inliers.
fn check_fit(e: &DVector<f64>, min_inliers: usize, max: f64) -> Result<f64, TrilaterationError> {
    let inliers: Vec<f64> = e.iter().copied().filter(|x| x.abs() <= 3.0).collect();
    let rms = if inliers.is_empty() {
        f64::INFINITY
    } else {
        (inliers.iter().map(|x| x * x).sum::<f64>() / inliers.len() as f64).sqrt()
    };
    if inliers.len() < min_inliers || 2 * inliers.len() < e.len() || rms > max {
        return Err(TrilaterationError::PoorFit { rms, max });
    }
    Ok(rms)
}

fn validate_ranges(obs: &[RangeObs]) -> Result<(), TrilaterationError> {
    for o in obs {
        if !(o.buoy_m.iter().all(|c| c.is_finite()) && o.range_m.is_finite()) {
            return Err(TrilaterationError::InvalidInput("non-finite buoy position or range"));
        }
        if !(o.sigma_m.is_finite() && o.sigma_m > 0.0) {
            return Err(TrilaterationError::InvalidInput("range σ must be positive"));
        }
        if o.range_m < 0.0 {
            return Err(TrilaterationError::InvalidInput("negative range"));
        }
    }
    Ok(())
}

/// Distinct buoys (by id): their positions.
fn distinct_buoys(obs: &[RangeObs]) -> Vec<Vector3<f64>> {
    let mut ids: Vec<(u32, Vector3<f64>)> = Vec::new();
    for o in obs {
        if !ids.iter().any(|(id, _)| *id == o.buoy_id) {
            ids.push((o.buoy_id, o.buoy_m));
        }
    }
    ids.into_iter().map(|(_, b)| b).collect()
}

/// Smallest over largest eigenvalue of the scatter of `points` (0 when degenerate).
pub(crate) fn spread_ratio<const D: usize>(points: &[nalgebra::SVector<f64, D>]) -> f64 {
    let n = points.len() as f64;
    let mean = points.iter().fold(nalgebra::SVector::<f64, D>::zeros(), |a, p| a + p) / n;
    let mut scatter = DMatrix::zeros(D, D);
    for p in points {
        let d = DVector::from_column_slice((p - mean).as_slice());
        scatter += &d * d.transpose();
    }
    let eig = SymmetricEigen::new(scatter).eigenvalues;
    if eig.max() <= 0.0 { 0.0 } else { eig.min().max(0.0) / eig.max() }
}

/// Relative spread below which buoys count as collinear (2-D) or coplanar (3-D): (1e-3)².
pub(crate) const DEGENERATE_SPREAD: f64 = 1e-6;

/// Position from ranges (see the module docs). The ranges must already be corrected for any
/// known bias; an unknown one is the caller's to propagate through [`Trilateration::sensitivity`].
pub fn trilaterate(obs: &[RangeObs], geometry: Geometry, limits: &Limits) -> Result<Trilateration, TrilaterationError> {
    validate_ranges(obs)?;
    let buoys = distinct_buoys(obs);
    let (dims, needed) = match geometry {
        Geometry::Planar { height_m } => {
            if !height_m.is_finite() {
                return Err(TrilaterationError::InvalidInput("non-finite height"));
            }
            (2, limits.min_buoys.max(3))
        }
        Geometry::Spatial { z_constraint: Some((z, s)) } => {
            if !(z.is_finite() && s.is_finite() && s > 0.0) {
                return Err(TrilaterationError::InvalidInput("z constraint must be finite with σ > 0"));
            }
            (3, limits.min_buoys.max(3))
        }
        Geometry::Spatial { z_constraint: None } => (3, limits.min_buoys.max(4)),
    };
    if buoys.len() < needed {
        return Err(TrilaterationError::TooFewBuoys { got: buoys.len(), needed });
    }
    let xy: Vec<Vector2<f64>> = buoys.iter().map(|b| b.xy()).collect();
    if spread_ratio(&xy) < DEGENERATE_SPREAD {
        return Err(TrilaterationError::DegenerateGeometry("the buoys lie on one line (seen from above)"));
    }
    let z_constraint = match geometry {
        Geometry::Spatial { z_constraint: None } => {
            if spread_ratio(&buoys) < DEGENERATE_SPREAD {
                return Err(TrilaterationError::DegenerateGeometry(
                    "the buoys lie in one plane: a depth reading is needed to pick the side",
                ));
            }
            None
        }
        Geometry::Spatial { z_constraint } => z_constraint,
        Geometry::Planar { .. } => None,
    };
    let fixed_z = match geometry {
        Geometry::Planar { height_m } => Some(height_m),
        Geometry::Spatial { z_constraint } => z_constraint.map(|c| c.0),
    };

    // Seed: linearised least squares 2(bᵢ − b̄)·p = |bᵢ|² − ρᵢ² − mean, in the plane at the fixed
    // z when there is one (ρᵢ² = rᵢ² − Δzᵢ²), else in 3-D.
    let seed = linear_seed(obs, fixed_z).unwrap_or_else(|| {
        let c = buoys.iter().fold(Vector3::zeros(), |a, b| a + b) / buoys.len() as f64;
        Vector3::new(c.x, c.y, fixed_z.unwrap_or(c.z))
    });
    let x0 = DVector::from_iterator(dims, seed.iter().take(dims).copied());
    let m = obs.len();
    let planar_z = match geometry {
        Geometry::Planar { height_m } => Some(height_m),
        Geometry::Spatial { .. } => None,
    };
    let rows = m + usize::from(z_constraint.is_some());
    let residuals = |x: &DVector<f64>| {
        let p = Vector3::new(x[0], x[1], planar_z.unwrap_or_else(|| x[2]));
        let mut e = DVector::zeros(rows);
        let mut J = DMatrix::zeros(rows, dims);
        for (i, o) in obs.iter().enumerate() {
            let u = p - o.buoy_m;
            let d = u.norm().max(1e-9);
            e[i] = (o.range_m - d) / o.sigma_m;
            for k in 0..dims {
                J[(i, k)] = u[k] / d / o.sigma_m;
            }
        }
        if let Some((z, s)) = z_constraint {
            e[m] = (z - p.z) / s;
            J[(m, 2)] = 1.0 / s;
        }
        (e, J)
    };
    let sol = gauss_newton(x0, limits.huber_k, limits.max_condition, residuals)?;
    let condition = condition_number(&sol.A);
    if condition > limits.max_condition {
        return Err(TrilaterationError::IllConditioned { condition, max: limits.max_condition });
    }
    // The inliers must over-determine the position by one (the spare that shows a wrong range):
    // with `needed` distinct buoys ranged, one of them may be that wrong range.
    let unknowns = if z_constraint.is_some() || planar_z.is_some() { 2 } else { 3 };
    let min_inliers = (unknowns + 1).max(needed.saturating_sub(1)).min(needed);
    let rms = check_fit(&sol.e.rows(0, m).into_owned(), min_inliers, limits.max_normalised_rms)?;
    let cov = sol
        .A
        .clone()
        .try_inverse()
        .ok_or(TrilaterationError::IllConditioned { condition, max: limits.max_condition })?;
    let mut covariance_m2 = Matrix3::zeros();
    covariance_m2.view_mut((0, 0), (dims, dims)).copy_from(&cov);
    let mut sensitivity = sol.gain.columns(0, m).into_owned();
    for (i, o) in obs.iter().enumerate() {
        sensitivity.column_mut(i).scale_mut(1.0 / o.sigma_m);
    }
    let position_m = Vector3::new(sol.x[0], sol.x[1], planar_z.unwrap_or_else(|| sol.x[2]));
    Ok(Trilateration { position_m, covariance_m2, sensitivity, normalised_rms: rms, buoys: buoys.len() })
}

/// Closed-form seed; `None` when the linear system is singular.
fn linear_seed(obs: &[RangeObs], fixed_z: Option<f64>) -> Option<Vector3<f64>> {
    let n = obs.len() as f64;
    match fixed_z {
        Some(z) => {
            let rho2: Vec<f64> = obs.iter().map(|o| (o.range_m.powi(2) - (o.buoy_m.z - z).powi(2)).max(0.0)).collect();
            let c: Vec<f64> = obs.iter().zip(&rho2).map(|(o, r2)| o.buoy_m.xy().norm_squared() - r2).collect();
            let bbar = obs.iter().fold(Vector2::zeros(), |a, o| a + o.buoy_m.xy()) / n;
            let cbar = c.iter().sum::<f64>() / n;
            let (mut A, mut g) = (Matrix2::zeros(), Vector2::zeros());
            for (o, ci) in obs.iter().zip(&c) {
                let a = 2.0 * (o.buoy_m.xy() - bbar);
                A += a * a.transpose();
                g += a * (ci - cbar);
            }
            A.try_inverse().map(|inv| {
                let p = inv * g;
                Vector3::new(p.x, p.y, z)
            })
        }
        None => {
            let c: Vec<f64> = obs.iter().map(|o| o.buoy_m.norm_squared() - o.range_m.powi(2)).collect();
            let bbar = obs.iter().fold(Vector3::zeros(), |a, o| a + o.buoy_m) / n;
            let cbar = c.iter().sum::<f64>() / n;
            let (mut A, mut g) = (Matrix3::zeros(), Vector3::zeros());
            for (o, ci) in obs.iter().zip(&c) {
                let a = 2.0 * (o.buoy_m - bbar);
                A += a * a.transpose();
                g += a * (ci - cbar);
            }
            A.try_inverse().map(|inv| inv * g)
        }
    }
    .filter(|p| p.iter().all(|c| c.is_finite()))
}

/// Wraps an angle into (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let two_pi = 2.0 * std::f64::consts::PI;
    let r = a.rem_euclid(two_pi);
    if r > std::f64::consts::PI { r - two_pi } else { r }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn buoys() -> Vec<Vector3<f64>> {
        [[0.0, 0.0, 0.0], [80.0, 0.0, 0.0], [80.0, 60.0, 0.0], [0.0, 60.0, 0.0], [40.0, 90.0, 0.0]]
            .iter()
            .map(|b| Vector3::from(*b))
            .collect()
    }

    fn ranges(truth: &Vector3<f64>, buoys: &[Vector3<f64>], sigma: f64, per_buoy: usize, seed: u64) -> Vec<RangeObs> {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let n = Normal::new(0.0, sigma).unwrap();
        (0..per_buoy)
            .flat_map(|_| buoys.iter().enumerate().map(|(i, b)| (i, *b)).collect::<Vec<_>>())
            .map(|(i, b)| RangeObs {
                buoy_id: i as u32,
                buoy_m: b,
                range_m: (truth - b).norm() + n.sample(&mut rng),
                sigma_m: sigma,
            })
            .collect()
    }

    #[test]
    fn recovers_a_known_position_under_noise() {
        let truth = Vector3::new(23.0, 41.0, 0.0);
        let obs = ranges(&truth, &buoys(), 0.3, 4, 1);
        let sol = trilaterate(&obs, Geometry::Planar { height_m: 0.0 }, &Limits::default()).unwrap();
        let err = sol.position_m - truth;
        assert!(err.norm() < 0.3, "error {err}");
        assert_eq!(sol.position_m.z, 0.0);
        assert_eq!(sol.covariance_m2[(2, 2)], 0.0);
        let p2 = sol.covariance_m2.fixed_view::<2, 2>(0, 0).into_owned();
        let nees = err.xy().dot(&(p2.try_inverse().unwrap() * err.xy()));
        assert!(nees < 13.8, "consistent: NEES {nees}");
        assert!(sol.normalised_rms < 1.5, "{}", sol.normalised_rms);
        assert_eq!(sol.buoys, 5);
    }

    #[test]
    fn surface_buoys_in_3d_need_a_depth_constraint_which_picks_the_side() {
        let truth = Vector3::new(30.0, 20.0, -15.0);
        let obs = ranges(&truth, &buoys(), 0.1, 2, 2);
        let e = trilaterate(&obs, Geometry::Spatial { z_constraint: None }, &Limits::default()).unwrap_err();
        assert!(matches!(e, TrilaterationError::DegenerateGeometry(_)), "{e}");
        let sol =
            trilaterate(&obs, Geometry::Spatial { z_constraint: Some((-15.1, 0.1)) }, &Limits::default()).unwrap();
        assert!((sol.position_m - truth).norm() < 0.3, "{}", sol.position_m);
        // Buoys at different heights: 3-D without depth works.
        let mut b = buoys();
        b[4].z = -20.0;
        b[2].z = -8.0;
        let obs = ranges(&truth, &b, 0.1, 2, 3);
        let sol = trilaterate(&obs, Geometry::Spatial { z_constraint: None }, &Limits::default()).unwrap();
        assert!((sol.position_m - truth).norm() < 0.5, "{}", sol.position_m);
    }

    #[test]
    fn collinear_buoys_are_degenerate() {
        let line: Vec<Vector3<f64>> =
            (0..4).map(|i| Vector3::new(10.0 * f64::from(i), 5.0 * f64::from(i), 0.0)).collect();
        let obs = ranges(&Vector3::new(3.0, 20.0, 0.0), &line, 0.1, 1, 4);
        let e = trilaterate(&obs, Geometry::Planar { height_m: 0.0 }, &Limits::default()).unwrap_err();
        assert_eq!(e, TrilaterationError::DegenerateGeometry("the buoys lie on one line (seen from above)"));
    }

    #[test]
    fn too_few_buoys_and_ill_conditioning_are_refused() {
        let obs = ranges(&Vector3::new(3.0, 20.0, 0.0), &buoys()[..3], 0.1, 3, 5);
        let limits = Limits { min_buoys: 4, ..Limits::default() };
        let e = trilaterate(&obs, Geometry::Planar { height_m: 0.0 }, &limits).unwrap_err();
        assert_eq!(e, TrilaterationError::TooFewBuoys { got: 3, needed: 4 });
        // Nearly collinear buoys, the vehicle far along their line: badly conditioned.
        let thin = [Vector3::new(0.0, 0.0, 0.0), Vector3::new(50.0, 0.5, 0.0), Vector3::new(100.0, 0.0, 0.0)];
        let obs = ranges(&Vector3::new(300.0, 2.0, 0.0), &thin, 0.1, 2, 6);
        let e =
            trilaterate(&obs, Geometry::Planar { height_m: 0.0 }, &Limits { max_condition: 1e4, ..Limits::default() })
                .unwrap_err();
        assert!(matches!(e, TrilaterationError::IllConditioned { .. }), "{e}");
    }

    #[test]
    fn invalid_inputs_are_errors() {
        let mut obs = ranges(&Vector3::new(3.0, 20.0, 0.0), &buoys(), 0.1, 1, 7);
        obs[1].range_m = f64::NAN;
        assert!(matches!(
            trilaterate(&obs, Geometry::Planar { height_m: 0.0 }, &Limits::default()),
            Err(TrilaterationError::InvalidInput(_))
        ));
        obs[1].range_m = 5.0;
        obs[2].sigma_m = 0.0;
        assert!(matches!(
            trilaterate(&obs, Geometry::Planar { height_m: 0.0 }, &Limits::default()),
            Err(TrilaterationError::InvalidInput(_))
        ));
    }

    #[test]
    fn one_gross_outlier_among_redundant_ranges_is_down_weighted() {
        let truth = Vector3::new(50.0, 30.0, 0.0);
        let mut obs = ranges(&truth, &buoys(), 0.3, 4, 8);
        obs[3].range_m += 10.0;
        let sol = trilaterate(&obs, Geometry::Planar { height_m: 0.0 }, &Limits::default()).unwrap();
        assert!((sol.position_m - truth).norm() < 0.5, "{}", sol.position_m);
    }

    #[test]
    fn the_sensitivity_is_the_derivative_of_the_solution_by_each_range() {
        // Exact ranges: at zero residual the Gauss-Newton sensitivity is the exact derivative.
        let mut obs = ranges(&Vector3::new(23.0, 41.0, 0.0), &buoys(), 1e-12, 1, 9);
        for o in &mut obs {
            o.range_m = (o.range_m.powi(2) + 4.0).sqrt(); // the vehicle 2 m above the buoys
            o.sigma_m = 0.3;
        }
        let limits = Limits { huber_k: 0.0, ..Limits::default() }; // smooth in the ranges
        let geometry = Geometry::Planar { height_m: 2.0 };
        let sol = trilaterate(&obs, geometry, &limits).unwrap();
        let h = 1e-5;
        for i in 0..obs.len() {
            let (mut a, mut b) = (obs.clone(), obs.clone());
            a[i].range_m += h;
            b[i].range_m -= h;
            let d = (trilaterate(&a, geometry, &limits).unwrap().position_m
                - trilaterate(&b, geometry, &limits).unwrap().position_m)
                / (2.0 * h);
            assert!(
                (d.xy() - sol.sensitivity.column(i)).norm() < 1e-6,
                "range {i}: {d} vs {}",
                sol.sensitivity.column(i)
            );
        }
    }
}

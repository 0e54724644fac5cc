//! The geometry behind a motion hypothesis: Gauss-Newton covariances, rigid-pair checks, the
//! agreeing set of a hypothesis, and the motion moved from the camera into the body frame.

#![allow(non_snake_case)]

use super::*;

/// The covariance of the left perturbation of `T` from the pairs (inverse Gauss-Newton
/// information, scaled up by the reduced χ² when it exceeds 1) and the reduced χ².
pub(super) fn gn_covariance(
    prev: &Frame,
    cur: &Frame,
    T: &Isometry3<f64>,
    pairs: &Pairs,
) -> Option<(Matrix6<f64>, f64)> {
    let mut H = Matrix6::zeros();
    let mut chi2 = 0.0;
    for &(i, j, _) in pairs {
        let (nu, S, Jx) = residual(T, &prev.pts[i as usize], &cur.pts[j as usize]);
        let Some(c) = Chol3::new(&S) else { continue };
        H += Jx.transpose() * c.inverse() * Jx;
        chi2 += c.mahalanobis(&nu);
    }
    let dof = (3 * pairs.len()).saturating_sub(6).max(1) as f64;
    // The gate truncates the χ² distribution: inliers of a right model average E[m | m ≤ gate]
    // < 3 per point. Only scale up.
    let chi2_per_dof = chi2 / dof;
    let cov = Cholesky::new(H)?.inverse() * chi2_per_dof.max(1.0);
    Some(((cov + cov.transpose()) * 0.5, chi2_per_dof))
}

/// Largest rotation σ of a base triple of the prior-free search (from its geometry), rad.
pub(super) const SEED_ROTATION_SIGMA_RAD: f64 = 0.025;

/// A hypothesis precise enough to score: translation σ ≤ 0.5 m, rotation σ ≤ 3° (traces).
pub(super) fn plausible(cov: &Matrix6<f64>) -> bool {
    let st = cov.fixed_view::<3, 3>(0, 0).trace();
    let sr = cov.fixed_view::<3, 3>(3, 3).trace();
    st <= 0.25 && sr <= 3f64.to_radians().powi(2)
}

/// The pairs (first per previous point) whose residual at `T`, widened by `prior`, passes `gate`.
pub(super) fn agreeing(
    prev: &Frame,
    cur: &Frame,
    pairs: &Pairs,
    T: &Isometry3<f64>,
    prior: Option<&Matrix6<f64>>,
    gate: f64,
    seen: &mut [bool],
) -> Pairs {
    seen.iter_mut().for_each(|a| *a = false);
    let mut out = vec![];
    for &(i, j, _) in pairs {
        if seen[i as usize] {
            continue;
        }
        let (nu, mut S, Jx) = residual(T, &prev.pts[i as usize], &cur.pts[j as usize]);
        if let Some(c) = prior {
            S += Jx * c * Jx.transpose();
        }
        if let Some(m) = mahalanobis_within(&nu, &S, gate) {
            seen[i as usize] = true;
            out.push((i, j, m));
        }
    }
    out
}

/// Covariance of the left perturbation of `T` (cur_from_prev) fitted to the `pairs` (previous,
/// current) by Horn/Umeyama: the inverse information of the 3-D residuals Q − T·P with
/// covariance C_Q + R·C_P·Rᵀ. `None` for degenerate pairs.
pub(super) fn hypothesis_covariance(
    prev: &Frame,
    cur: &Frame,
    pairs: &[(u32, u32)],
    T: &Isometry3<f64>,
) -> Option<Matrix6<f64>> {
    let R = T.rotation.to_rotation_matrix().into_inner();
    let mut H = Matrix6::zeros();
    for &(i, j) in pairs {
        let (P, Q) = (&prev.pts[i as usize], &cur.pts[j as usize]);
        let p = R * P.p + T.translation.vector;
        let W = Chol3::new(&(Q.C + R * P.C * R.transpose()))?.inverse();
        let mut J = Matrix3x6::zeros();
        J.fixed_view_mut::<3, 3>(0, 0).copy_from(&Matrix3::identity());
        J.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-p.cross_matrix()));
        H += J.transpose() * W * J;
    }
    let c = Cholesky::new(H)?.inverse();
    Some((c + c.transpose()) * 0.5)
}

/// True when the distance between previous points i and k agrees with the distance between
/// current points j and l within 3.5 σ (σ from the points' covariances along the pair's line),
/// and the pair's direction turned by at most `max_angle_rad` (plus 3.5 σ of its direction).
pub(super) fn rigid_pair_ok(
    prev: &Frame,
    cur: &Frame,
    (i, j): (u32, u32),
    (k, l): (u32, u32),
    max_angle_rad: f64,
) -> bool {
    let (P1, P2) = (&prev.pts[i as usize], &prev.pts[k as usize]);
    let (Q1, Q2) = (&cur.pts[j as usize], &cur.pts[l as usize]);
    let dp = P2.p - P1.p;
    let dq = Q2.p - Q1.p;
    let (np, nq) = (dp.norm(), dq.norm());
    if np < 1e-9 || nq < 1e-9 {
        return false;
    }
    let up = dp / np;
    let uq = dq / nq;
    let (Cp, Cq) = (P1.C + P2.C, Q1.C + Q2.C);
    let var = up.dot(&(Cp * up)) + uq.dot(&(Cq * uq));
    if (np - nq).abs() > 3.5 * var.sqrt() + 1e-3 {
        return false;
    }
    if max_angle_rad >= std::f64::consts::PI {
        return true;
    }
    // Direction noise: the covariance across the line over the length (trace minus along).
    let var_dir =
        (Cp.trace() - up.dot(&(Cp * up))).max(0.0) / (np * np) + (Cq.trace() - uq.dot(&(Cq * uq))).max(0.0) / (nq * nq);
    up.dot(&uq).clamp(-1.0, 1.0).acos() <= max_angle_rad + 3.5 * var_dir.sqrt()
}

pub(super) fn shuffle_pairs(v: &mut [(u32, u32)], rng: &mut Xoshiro256PlusPlus) {
    for i in (1..v.len()).rev() {
        let j = rng.random_range(0..=i);
        v.swap(i, j);
    }
}

pub(super) fn shuffle(v: &mut [u32], rng: &mut Xoshiro256PlusPlus) {
    for i in (1..v.len()).rev() {
        let j = rng.random_range(0..=i);
        v.swap(i, j);
    }
}

/// Adjoint of `body_from_camera` for perturbations (δt, δθ): a right perturbation ε of a camera
/// motion is the right perturbation Ad·ε of the same motion in the body frame.
pub fn adjoint(body_from_camera: &Isometry3<f64>) -> Matrix6<f64> {
    let R = body_from_camera.rotation.to_rotation_matrix().into_inner();
    let t = body_from_camera.translation.vector;
    let mut A = Matrix6::zeros();
    A.fixed_view_mut::<3, 3>(0, 0).copy_from(&R);
    A.fixed_view_mut::<3, 3>(0, 3).copy_from(&(t.cross_matrix() * R));
    A.fixed_view_mut::<3, 3>(3, 3).copy_from(&R);
    A
}

/// A registration's motion and covariance in the body frame: `prev_body_from_cur_body` and the
/// covariance of its right perturbation in the current body frame.
pub fn motion_in_body(r: &Registration, body_from_camera: &Isometry3<f64>) -> (Isometry3<f64>, Matrix6<f64>) {
    let m = body_from_camera * r.prev_from_cur * body_from_camera.inverse();
    let A = adjoint(body_from_camera);
    let c = A * r.covariance * A.transpose();
    (m, (c + c.transpose()) * 0.5)
}

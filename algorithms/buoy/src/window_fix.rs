//! Robust planar fix from a window of ranges taken while moving: positions propagated by
//! odometry, outliers found by sampling (MSAC), the heading solved with the position.
//!
//! Each range i in the window carries the odometry's pose o_i = (x, y, ψ) at its time (dead
//! reckoning in an arbitrary frame) and the path length travelled since the window started.
//! Relative to the newest range n, the vehicle was at d_i = R(−ψ_n)(o_i − o_n) in the newest
//! body frame; the unknowns are the newest world pose (p, ψ): range i reads
//! r_i = ‖(p + R(ψ)d_i, h_i) − b_i‖ with h_i the vehicle's known height at that time (planar
//! mode: its fixed height; underwater: from the depth sensor). Odometry error grows
//! with the path between range i and the newest, so each range's σ becomes
//! σ_i² + (`drift_fraction` · path_i→n)².
//!
//! For each heading on a grid of `heading_steps` (one, when the vehicle has stood still, i.e.
//! moved less than the ranges' median σ: then d_i is taken as 0 and its length added to σ_i; a
//! vehicle that moved more than that but less than `min_travel_for_heading_m` is waited for), the
//! ranges become ranges to "virtual buoys" b_i − R(ψ)d_i, and triples of them give candidate
//! positions in closed form; each candidate is scored over the whole window by the truncated
//! quadratic cost Σ min(e_i², k²) of the normalised residuals e_i (MSAC, k = `inlier_k`). The best
//! candidate is refined by Gauss-Newton on (p, ψ) over its inliers, and accepted when it
//! explains enough ranges (`min_inliers`, `min_inlier_fraction`) to at least `min_buoys` buoys,
//! and no distinct pose (more than 1 m or 30° away, refined the same way) fits nearly as well
//! (truncated cost within `ambiguity_margin` outliers' worth). The triples are drawn deterministically (the same window gives the
//! same answer).

#![allow(non_snake_case)]

use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};

use crate::error::TrilaterationError;
use crate::trilaterate::wrap_angle;

/// A range in the window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowRange {
    /// Odometry pose (x m, y m, ψ rad) at the range's time, in the odometry's own frame.
    pub odom_pose: [f64; 3],
    /// Path length travelled by the odometry up to the range's time (from any origin), m.
    pub path_m: f64,
    /// The vehicle's height z at the range's time, m (planar mode: `planar_height_m`; spatial
    /// mode: from the latest depth reading).
    pub height_m: f64,
    /// Buoy id.
    pub buoy_id: u32,
    /// Buoy position, m.
    pub buoy_m: Vector3<f64>,
    /// Range, m (corrected for any known scale and bias).
    pub range_m: f64,
    /// σ of the range, m (> 0).
    pub sigma_m: f64,
}

/// Settings of [`window_fix`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowLimits {
    /// Distinct buoys needed among the inliers (at least 3).
    pub min_buoys: usize,
    /// Inliers needed.
    pub min_inliers: usize,
    /// Share of the window's ranges that must be inliers.
    pub min_inlier_fraction: f64,
    /// Inlier threshold on the normalised residual.
    pub inlier_k: f64,
    /// Odometry error per metre of path (σ added to a range per metre between it and the
    /// newest range).
    pub drift_fraction: f64,
    /// Headings tried when the heading is observable.
    pub heading_steps: usize,
    /// Triples scored per heading.
    pub samples_per_heading: usize,
    /// The heading counts as observable once the odometry positions in the window spread over
    /// this distance from the newest, or over 5 range σ if that is shorter, m.
    pub min_travel_for_heading_m: f64,
    /// A distinct pose whose truncated cost is within this many outliers' worth (k² each) of
    /// the best makes the fix ambiguous.
    pub ambiguity_margin: f64,
}

impl Default for WindowLimits {
    fn default() -> Self {
        Self {
            min_buoys: 3,
            min_inliers: 8,
            min_inlier_fraction: 0.6,
            inlier_k: 3.0,
            drift_fraction: 0.05,
            heading_steps: 72,
            samples_per_heading: 48,
            min_travel_for_heading_m: 1.0,
            ambiguity_margin: 1.0,
        }
    }
}

/// The heading counts as observable once the path spreads over this many range σ (or
/// `min_travel_for_heading_m`, whichever is shorter).
const HEADING_TRAVEL_SIGMAS: f64 = 5.0;

/// A robust fix.
#[derive(Debug, Clone, PartialEq)]
pub struct WindowFix {
    /// Position at the newest range's time, m (z = the newest range's height).
    pub position_m: Vector3<f64>,
    /// Its covariance, m² (the z row and column are 0).
    pub covariance_m2: Matrix3<f64>,
    /// Heading at the newest range's time, rad, when the path made it observable.
    pub heading_rad: Option<f64>,
    /// σ of the heading, rad (π when not observable).
    pub heading_sigma_rad: f64,
    /// Covariance of the position (x, y) with the heading, m·rad (zero when the heading is not
    /// observable). The window fixes where the path was better than where it ends: a heading
    /// error swings the newest position about the window's middle, so the two are correlated,
    /// and a filter started without this term corrects the heading later but keeps the
    /// position the wrong heading put it at.
    pub position_heading_cov_m_rad: Vector2<f64>,
    /// Which of the window's ranges are inliers, in window order.
    pub inliers: Vec<bool>,
    /// Distinct buoys among the inliers.
    pub buoys: usize,
    /// Normalised RMS residual of the inliers.
    pub normalised_rms: f64,
}

/// A deterministic index generator (SplitMix64).
struct Draw(u64);

impl Draw {
    fn below(&mut self, n: usize) -> usize {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z % n as u64) as usize
    }
}

fn rot(psi: f64, v: Vector2<f64>) -> Vector2<f64> {
    let (s, c) = psi.sin_cos();
    Vector2::new(c * v.x - s * v.y, s * v.x + c * v.y)
}

/// Per-range data prepared once.
struct Prepared {
    /// The vehicle's height, m.
    h: f64,
    /// Offset in the newest body frame, m.
    d: Vector2<f64>,
    b: Vector3<f64>,
    r: f64,
    sigma: f64,
    /// Horizontal range (r² − Δz²)^½, m.
    rho: f64,
}

fn residual(p: &Prepared, pos: Vector2<f64>, psi: f64) -> f64 {
    let q = pos + rot(psi, p.d);
    let dist = Vector3::new(q.x - p.b.x, q.y - p.b.y, p.h - p.b.z).norm();
    (p.r - dist) / p.sigma
}

/// Candidate position from three virtual buoys (closed form; `None` when nearly collinear).
fn from_triple(v: [Vector2<f64>; 3], rho: [f64; 3]) -> Option<Vector2<f64>> {
    let A = Matrix2::new(
        2.0 * (v[1].x - v[0].x),
        2.0 * (v[1].y - v[0].y),
        2.0 * (v[2].x - v[0].x),
        2.0 * (v[2].y - v[0].y),
    );
    let scale = (v[1] - v[0]).norm() * (v[2] - v[0]).norm();
    if scale <= 1e-12 || A.determinant().abs() < 0.05 * 4.0 * scale {
        return None; // the three lie nearly on a line: the position is ill-determined
    }
    let g = Vector2::new(
        v[1].norm_squared() - v[0].norm_squared() - rho[1] * rho[1] + rho[0] * rho[0],
        v[2].norm_squared() - v[0].norm_squared() - rho[2] * rho[2] + rho[0] * rho[0],
    );
    A.try_inverse().map(|inv| inv * g).filter(|p| p.iter().all(|c| c.is_finite()))
}

/// A scored candidate.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    cost: f64,
    inliers: usize,
    pos: Vector2<f64>,
    psi: f64,
}

/// The robust fix of a window (see the module docs).
pub fn window_fix(obs: &[WindowRange], limits: &WindowLimits) -> Result<WindowFix, TrilaterationError> {
    for o in obs {
        let ok = o.odom_pose.iter().all(|c| c.is_finite())
            && o.path_m.is_finite()
            && o.height_m.is_finite()
            && o.buoy_m.iter().all(|c| c.is_finite())
            && o.range_m.is_finite()
            && o.range_m >= 0.0;
        if !ok {
            return Err(TrilaterationError::InvalidInput("non-finite pose, buoy or range, or a negative range"));
        }
        if !(o.sigma_m.is_finite() && o.sigma_m > 0.0) {
            return Err(TrilaterationError::InvalidInput("range σ must be positive"));
        }
    }
    let needed = limits.min_inliers.max(3);
    let mut ids: Vec<u32> = obs.iter().map(|o| o.buoy_id).collect();
    ids.sort_unstable();
    ids.dedup();
    if ids.len() < limits.min_buoys.max(3) {
        return Err(TrilaterationError::TooFewBuoys { got: ids.len(), needed: limits.min_buoys.max(3) });
    }
    if obs.len() < needed {
        return Err(TrilaterationError::TooFewRanges { got: obs.len(), needed });
    }
    let newest = obs[obs.len() - 1];
    let on = Vector2::new(newest.odom_pose[0], newest.odom_pose[1]);
    let offsets: Vec<Vector2<f64>> =
        obs.iter().map(|o| rot(-newest.odom_pose[2], Vector2::new(o.odom_pose[0], o.odom_pose[1]) - on)).collect();
    let travel = offsets.iter().map(|d| d.norm()).fold(0.0, f64::max);
    // Between standing still (moved less than the ranges' noise) and a path that shows the
    // heading (a path long against the ranges' noise), the offsets cannot be placed: wait.
    let mut sigmas: Vec<f64> = obs.iter().map(|o| o.sigma_m).collect();
    sigmas.sort_by(f64::total_cmp);
    let median_sigma = sigmas[sigmas.len() / 2];
    let heading_observable =
        travel >= limits.min_travel_for_heading_m.min(HEADING_TRAVEL_SIGMAS * median_sigma.max(0.05));
    let still = travel <= median_sigma.max(0.05);
    if !heading_observable && !still {
        return Err(TrilaterationError::Moving { travel_m: travel, needed_m: limits.min_travel_for_heading_m });
    }
    let prepared: Vec<Prepared> = obs
        .iter()
        .zip(&offsets)
        .map(|(o, d)| {
            let drift = limits.drift_fraction * (newest.path_m - o.path_m).abs();
            let (d, extra) = if heading_observable { (*d, 0.0) } else { (Vector2::zeros(), d.norm()) };
            let dz = o.buoy_m.z - o.height_m;
            Prepared {
                h: o.height_m,
                d,
                b: o.buoy_m,
                r: o.range_m,
                sigma: (o.sigma_m.powi(2) + drift.powi(2) + extra.powi(2)).sqrt(),
                rho: (o.range_m.powi(2) - dz * dz).max(0.0).sqrt(),
            }
        })
        .collect();
    let n = prepared.len();
    let k2 = limits.inlier_k * limits.inlier_k;
    let score = |pos: Vector2<f64>, psi: f64| {
        let (mut cost, mut inliers) = (0.0, 0usize);
        for p in &prepared {
            let e2 = residual(p, pos, psi).powi(2);
            if e2 <= k2 {
                inliers += 1;
                cost += e2;
            } else {
                cost += k2;
            }
        }
        Candidate { cost, inliers, pos, psi }
    };

    // Triples: all of them when few, else a deterministic sample (the same for every heading).
    let total = n * (n - 1) * (n - 2) / 6;
    let mut triples: Vec<[usize; 3]> = Vec::new();
    if total <= limits.samples_per_heading.max(1) {
        for a in 0..n {
            for b in a + 1..n {
                for c in b + 1..n {
                    triples.push([a, b, c]);
                }
            }
        }
    } else {
        let mut draw = Draw(0x5EED_0000 + n as u64);
        let mut guard = 0;
        while triples.len() < limits.samples_per_heading && guard < 100 * limits.samples_per_heading {
            guard += 1;
            let (a, b, c) = (draw.below(n), draw.below(n), draw.below(n));
            if a != b && b != c && a != c {
                triples.push([a, b, c]);
            }
        }
    }
    let steps = if heading_observable { limits.heading_steps.max(1) } else { 1 };
    let mut best_per_heading: Vec<Candidate> = Vec::with_capacity(steps);
    for s in 0..steps {
        let psi = wrap_angle(2.0 * std::f64::consts::PI * s as f64 / steps as f64);
        let virt: Vec<Vector2<f64>> = prepared.iter().map(|p| p.b.xy() - rot(psi, p.d)).collect();
        let mut best: Option<Candidate> = None;
        for t in &triples {
            let Some(pos) = from_triple(
                [virt[t[0]], virt[t[1]], virt[t[2]]],
                [prepared[t[0]].rho, prepared[t[1]].rho, prepared[t[2]].rho],
            ) else {
                continue;
            };
            let c = score(pos, psi);
            if best.is_none_or(|b| c.cost < b.cost) {
                best = Some(c);
            }
        }
        if let Some(b) = best {
            best_per_heading.push(b);
        }
    }
    let Some(&coarse) = best_per_heading.iter().min_by(|a, b| a.cost.total_cmp(&b.cost)) else {
        return Err(TrilaterationError::DegenerateGeometry("every triple of ranges is collinear"));
    };

    // Refine (p, ψ) by Gauss-Newton over the inliers, re-selecting them twice.
    let refine = |mut pos: Vector2<f64>, mut psi: f64| {
        let mut info = Matrix3::zeros();
        for _round in 0..3 {
            let inl: Vec<&Prepared> =
                prepared.iter().filter(|p| residual(p, pos, psi).abs() <= limits.inlier_k).collect();
            for _it in 0..10 {
                let (mut A, mut g) = (Matrix3::zeros(), Vector3::zeros());
                for p in &inl {
                    let q = pos + rot(psi, p.d);
                    let u = Vector3::new(q.x - p.b.x, q.y - p.b.y, p.h - p.b.z);
                    let dist = u.norm().max(1e-9);
                    let e = (p.r - dist) / p.sigma;
                    // ∂dist/∂p = u_xy/dist; ∂dist/∂ψ = u_xy · ∂(R(ψ)d)/∂ψ / dist.
                    let dq_dpsi = rot(psi + std::f64::consts::FRAC_PI_2, p.d);
                    let mut J = Vector3::new(u.x / dist, u.y / dist, (u.x * dq_dpsi.x + u.y * dq_dpsi.y) / dist);
                    if !heading_observable {
                        J.z = 0.0;
                    }
                    J /= p.sigma;
                    A += J * J.transpose();
                    g += J * e;
                }
                if !heading_observable {
                    A[(2, 2)] = 1.0;
                }
                let Some(inv) = A.try_inverse() else { break };
                let step = inv * g;
                pos += step.xy();
                psi = wrap_angle(psi + step.z);
                info = A;
                if step.norm() < 1e-6 {
                    break;
                }
            }
        }
        (pos, psi, info)
    };
    let (pos, psi, info) = refine(coarse.pos, coarse.psi);
    let residuals: Vec<f64> = prepared.iter().map(|p| residual(p, pos, psi)).collect();
    let inliers: Vec<bool> = residuals.iter().map(|e| e.abs() <= limits.inlier_k).collect();
    let count = inliers.iter().filter(|&&b| b).count();
    let mut inlier_ids: Vec<u32> = obs.iter().zip(&inliers).filter(|(_, i)| **i).map(|(o, _)| o.buoy_id).collect();
    inlier_ids.sort_unstable();
    inlier_ids.dedup();
    let needed_count = needed.max((limits.min_inlier_fraction * n as f64).ceil() as usize);
    if count < needed_count || inlier_ids.len() < limits.min_buoys.max(3) {
        return Err(TrilaterationError::TooFewInliers {
            inliers: count,
            ranges: n,
            buoys: inlier_ids.len(),
            needed: needed_count,
            min_share: limits.min_inlier_fraction * 100.0,
        });
    }
    // A distinct pose explaining nearly as many ranges: ambiguous. The best few distinct
    // candidates are refined first (a coarse neighbour of the best converges onto it).
    let distinct = |p2: Vector2<f64>, psi2: f64| {
        (p2 - pos).norm() > 1.0 || (heading_observable && wrap_angle(psi2 - psi).abs() > 30f64.to_radians())
    };
    let mut rivals: Vec<&Candidate> = best_per_heading.iter().filter(|c| distinct(c.pos, c.psi)).collect();
    rivals.sort_by(|a, b| a.cost.total_cmp(&b.cost));
    for c in rivals.into_iter().take(4) {
        let (p2, psi2, _) = refine(c.pos, c.psi);
        if !distinct(p2, psi2) {
            continue;
        }
        let (best_c, rival_c) = (score(pos, psi), score(p2, psi2));
        if rival_c.cost <= best_c.cost + limits.ambiguity_margin * k2 {
            return Err(TrilaterationError::Ambiguous {
                best: count,
                runner_up: rival_c.inliers,
                cost_gap: (rival_c.cost - best_c.cost) / k2,
            });
        }
    }
    let cov = info.try_inverse().ok_or(TrilaterationError::IllConditioned { condition: f64::INFINITY, max: 1e8 })?;
    let rms =
        (residuals.iter().zip(&inliers).filter(|(_, i)| **i).map(|(e, _)| e * e).sum::<f64>() / count as f64).sqrt();
    let mut covariance_m2 = Matrix3::zeros();
    covariance_m2.view_mut((0, 0), (2, 2)).copy_from(&cov.view((0, 0), (2, 2)));
    Ok(WindowFix {
        position_m: Vector3::new(pos.x, pos.y, newest.height_m),
        covariance_m2,
        heading_rad: heading_observable.then_some(psi),
        heading_sigma_rad: if heading_observable { cov[(2, 2)].max(0.0).sqrt() } else { std::f64::consts::PI },
        position_heading_cov_m_rad: if heading_observable {
            Vector2::new(cov[(0, 2)], cov[(1, 2)])
        } else {
            Vector2::zeros()
        },
        inliers,
        buoys: inlier_ids.len(),
        normalised_rms: rms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const BUOYS: [[f64; 3]; 3] = [[0.2, 0.3, 1.04], [6.8, 0.5, 1.94], [3.2, 4.8, 1.49]];

    /// A window along an arc with the odometry frame rotated and shifted from the world, one
    /// range per step round robin; `bad` indices read 2 m long or short.
    fn window(bad: &[usize], moving: bool) -> (Vec<WindowRange>, Vector2<f64>, f64) {
        let (frame_rot, frame_shift) = (1.1, Vector2::new(-3.0, 2.0));
        let mut out = Vec::new();
        let (mut x, mut y, mut psi, mut path): (f64, f64, f64, f64) = (1.5, 1.0, 0.4, 0.0);
        for i in 0..24 {
            if moving {
                let v = 0.3;
                x += v * psi.cos();
                y += v * psi.sin();
                psi += 0.12;
                path += v;
            }
            let j = i % 3;
            let b = Vector3::from(BUOYS[j]);
            let mut r = (Vector3::new(x, y, 1.12) - b).norm() + 0.02 * ((i * 7 % 5) as f64 - 2.0);
            if bad.contains(&i) {
                r = if i % 2 == 0 || r < 2.0 { r + 2.0 } else { r - 1.2 };
            }
            // Odometry frame: world rotated by −frame_rot and shifted.
            let o = rot(-frame_rot, Vector2::new(x, y)) + frame_shift;
            out.push(WindowRange {
                odom_pose: [o.x, o.y, psi - frame_rot],
                path_m: path,
                height_m: 1.12,
                buoy_id: j as u32 + 1,
                buoy_m: b,
                range_m: r,
                sigma_m: 0.1,
            });
        }
        (out, Vector2::new(x, y), psi)
    }

    #[test]
    fn finds_position_and_heading_through_a_quarter_of_gross_errors() {
        let bad = [1, 4, 9, 13, 17, 22];
        let (w, truth, psi) = window(&bad, true);
        let fix = window_fix(&w, &WindowLimits::default()).unwrap();
        assert!((fix.position_m.xy() - truth).norm() < 0.1, "{:?} vs {truth:?}", fix.position_m);
        let h = fix.heading_rad.expect("moved: heading observable");
        assert!(wrap_angle(h - psi).abs() < 0.05, "{h} vs {psi}");
        for (i, inl) in fix.inliers.iter().enumerate() {
            assert_eq!(*inl, !bad.contains(&i), "range {i}");
        }
        assert_eq!(fix.buoys, 3);
    }

    #[test]
    fn the_position_heading_covariance_matches_the_spread_of_fixes() {
        // Many noise draws of one short arc (σ 0.1 m, no odometry error, so no drift allowance):
        // the fix's claimed position-heading covariance is the spread's, sign and size.
        let limits = WindowLimits { drift_fraction: 0.0, ambiguity_margin: 0.0, ..WindowLimits::default() };
        let mut draw = Draw(7);
        let mut gauss = || {
            let u1 = (draw.below(1 << 30) as f64 + 0.5) / (1u64 << 30) as f64;
            let u2 = draw.below(1 << 30) as f64 / (1u64 << 30) as f64;
            (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
        };
        let (clean, truth, psi) = window(&[], true);
        let n = 400;
        let (mut errors, mut claimed) = (Vec::new(), Vector3::zeros());
        for _ in 0..n {
            let mut w = clean.clone();
            for o in &mut w {
                o.range_m += 0.1 * gauss();
            }
            let fix = window_fix(&w, &limits).unwrap();
            let e = Vector3::new(
                fix.position_m.x - truth.x,
                fix.position_m.y - truth.y,
                wrap_angle(fix.heading_rad.unwrap() - psi),
            );
            errors.push(e);
            claimed += Vector3::new(
                fix.position_heading_cov_m_rad.x,
                fix.position_heading_cov_m_rad.y,
                fix.heading_sigma_rad.powi(2),
            ) / n as f64;
        }
        let mean = errors.iter().sum::<Vector3<f64>>() / n as f64;
        let cov = |a: usize, b: usize| {
            errors.iter().map(|e| (e[a] - mean[a]) * (e[b] - mean[b])).sum::<f64>() / (n - 1) as f64
        };
        let var_psi = cov(2, 2);
        assert!((claimed.z / var_psi - 1.0).abs() < 0.3, "heading variance {} claimed, {var_psi} seen", claimed.z);
        for a in 0..2 {
            let seen = cov(a, 2);
            // Relative to the scale of the terms (σ_a σ_ψ): the correlation coefficients agree.
            let unit = (cov(a, a) * var_psi).sqrt();
            assert!(
                ((claimed[a] - seen) / unit).abs() < 0.15,
                "axis {a}: position-heading covariance {} claimed, {seen} seen (unit {unit})",
                claimed[a]
            );
        }
        // The arc makes them strongly correlated: the test would catch a dropped term.
        assert!(
            (cov(0, 2) / (cov(0, 0) * var_psi).sqrt()).abs() > 0.3
                || (cov(1, 2) / (cov(1, 1) * var_psi).sqrt()).abs() > 0.3
        );
    }

    #[test]
    fn standing_still_gives_a_position_without_heading() {
        let (w, truth, _) = window(&[2, 11], false);
        let fix = window_fix(&w, &WindowLimits::default()).unwrap();
        assert!((fix.position_m.xy() - truth).norm() < 0.1);
        assert_eq!(fix.heading_rad, None);
    }

    #[test]
    fn too_many_outliers_or_too_few_ranges_wait_with_the_reason() {
        let (w, _, _) = window(&(0..24).filter(|i| i % 2 == 0).collect::<Vec<_>>(), true);
        assert!(matches!(window_fix(&w, &WindowLimits::default()), Err(TrilaterationError::TooFewInliers { .. })));
        let (w, _, _) = window(&[], true);
        assert!(matches!(
            window_fix(&w[..5], &WindowLimits::default()),
            Err(TrilaterationError::TooFewRanges { got: 5, needed: 8 })
        ));
        let mut two = w.clone();
        two.retain(|o| o.buoy_id != 3);
        assert!(matches!(window_fix(&two, &WindowLimits::default()), Err(TrilaterationError::TooFewBuoys { .. })));
        let mut nan = w;
        nan[3].range_m = f64::NAN;
        assert!(matches!(window_fix(&nan, &WindowLimits::default()), Err(TrilaterationError::InvalidInput(_))));
    }
}

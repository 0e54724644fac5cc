//! Geometry shared by the pipeline's estimators and sensor models (EQUATIONS §0-2, §7):
//! Euler-angle rotations in the project's convention, the robot process model, the stereo
//! camera model with first-order triangulation covariance, and camera extrinsics.
//!
//! Conventions: right-handed; world z up; body x forward, y left, z up; camera (optical) x right,
//! y down, z forward. Orientation is R = Rz(θz)·Ry(θy)·Rx(θx), mapping body to world
//! (`world_from_body`). Angles in rad, lengths in m, pixels in px.

#![allow(non_snake_case)]

pub mod gaussian;
pub mod stats;
pub mod trajectory;
pub mod tum;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Errors of the geometric models.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    /// Stereo disparity uL − uR must be positive.
    #[error("non-positive stereo disparity {disparity_px} px")]
    NonPositiveDisparity {
        /// The disparity.
        disparity_px: f64,
    },
    /// An input was NaN or infinite.
    #[error("non-finite input: {0}")]
    NonFinite(&'static str),
}

/// R = Rz(θz)·Ry(θy)·Rx(θx) (EQUATIONS §0, [3D] eq 3): body to world.
pub fn rotation_from_euler_zyx(theta_rad: &Vector3<f64>) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::z_axis(), theta_rad.z)
        * Rotation3::from_axis_angle(&Vector3::y_axis(), theta_rad.y)
        * Rotation3::from_axis_angle(&Vector3::x_axis(), theta_rad.x)
}

/// The inverse of [`rotation_from_euler_zyx`]: (θx, θy, θz) with θy in [−π/2, π/2].
pub fn euler_zyx_from_rotation(r: &Rotation3<f64>) -> Vector3<f64> {
    let (roll, pitch, yaw) = r.euler_angles(); // nalgebra: R = Rz(yaw)·Ry(pitch)·Rx(roll)
    Vector3::new(roll, pitch, yaw)
}

/// Input U = (v, δθx, δθy, δθz) over δt (EQUATIONS §1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProcessInput {
    /// Forward speed along body x, m/s.
    pub v_mps: f64,
    /// Body-frame rotation increment (applied as R(δθ) = Rz·Ry·Rx of these angles), rad.
    pub delta_theta_rad: Vector3<f64>,
    /// Sampling time δt, s.
    pub dt_s: f64,
}

/// The process model (EQUATIONS §1, [3D] eq 1-7 with erratum §9): position moves along the body's
/// forward axis at the *current* orientation, p(k+1) = p(k) + R(k)·e_x·v·δt, then the orientation
/// turns by the body-frame increment, R(k+1) = R(k)·R(δθ).
pub fn propagate(world_from_body: &Isometry3<f64>, u: &ProcessInput) -> Isometry3<f64> {
    let r = world_from_body.rotation;
    let p = world_from_body.translation.vector + r * Vector3::x() * (u.v_mps * u.dt_s);
    let dr = UnitQuaternion::from_rotation_matrix(&rotation_from_euler_zyx(&u.delta_theta_rad));
    Isometry3::from_parts(Translation3::from(p), r * dr)
}

/// Pixel coordinates of a point in a rectified stereo pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoPixels {
    /// Column in the left image, px.
    pub u_left_px: f64,
    /// Column in the right image, px.
    pub u_right_px: f64,
    /// Row (same in both images), px.
    pub v_px: f64,
}

/// A rectified stereo pair (EQUATIONS §2): square pixels with focal length `f_px`, principal point
/// (`cx_px`, `cy_px`), baseline `baseline_m`; the left camera's optical frame is the camera frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StereoRig {
    /// Focal length, px.
    pub f_px: f64,
    /// Principal point column, px.
    pub cx_px: f64,
    /// Principal point row, px.
    pub cy_px: f64,
    /// Baseline, m.
    pub baseline_m: f64,
    /// Image width, px.
    pub width_px: u32,
    /// Image height, px.
    pub height_px: u32,
}

impl StereoRig {
    /// Projects a point of the camera frame into both images; `None` when it is behind the
    /// camera or outside either image.
    pub fn project(&self, p_cam_m: &Vector3<f64>) -> Option<StereoPixels> {
        if p_cam_m.z <= 1e-6 {
            return None;
        }
        let u_left_px = self.cx_px + self.f_px * p_cam_m.x / p_cam_m.z;
        let u_right_px = self.cx_px + self.f_px * (p_cam_m.x - self.baseline_m) / p_cam_m.z;
        let v_px = self.cy_px + self.f_px * p_cam_m.y / p_cam_m.z;
        let (w, h) = (self.width_px as f64, self.height_px as f64);
        let inside = |u: f64| (0.0..w).contains(&u);
        (inside(u_left_px) && inside(u_right_px) && (0.0..h).contains(&v_px)).then_some(StereoPixels {
            u_left_px,
            u_right_px,
            v_px,
        })
    }

    /// Triangulates (EQUATIONS §2): d = uL − uR, Z = f·b/d, X = (uL − cx)·Z/f, Y = (v − cy)·Z/f.
    pub fn triangulate(&self, px: &StereoPixels) -> Result<Vector3<f64>, GeometryError> {
        if !(px.u_left_px.is_finite() && px.u_right_px.is_finite() && px.v_px.is_finite()) {
            return Err(GeometryError::NonFinite("stereo pixels"));
        }
        let d = px.u_left_px - px.u_right_px;
        if d <= 0.0 {
            return Err(GeometryError::NonPositiveDisparity { disparity_px: d });
        }
        let z = self.f_px * self.baseline_m / d;
        Ok(Vector3::new((px.u_left_px - self.cx_px) * z / self.f_px, (px.v_px - self.cy_px) * z / self.f_px, z))
    }

    /// Jacobian ∂(X, Y, Z)/∂(uL, uR, v) of [`StereoRig::triangulate`].
    pub fn triangulation_jacobian(&self, px: &StereoPixels) -> Result<Matrix3<f64>, GeometryError> {
        let p = self.triangulate(px)?;
        let d = px.u_left_px - px.u_right_px;
        let f = self.f_px;
        let dZ_duL = -f * self.baseline_m / (d * d);
        let dZ_duR = -dZ_duL;
        let xu = (px.u_left_px - self.cx_px) / f;
        let yv = (px.v_px - self.cy_px) / f;
        Ok(Matrix3::new(
            p.z / f + xu * dZ_duL,
            xu * dZ_duR,
            0.0,
            yv * dZ_duL,
            yv * dZ_duR,
            p.z / f,
            dZ_duL,
            dZ_duR,
            0.0,
        ))
    }

    /// First-order covariance of the triangulated point for independent pixel noise σ on uL, uR
    /// and v: Σ = J·diag(σ²)·Jᵀ (depth σ grows as Z²·σ·√2/(f·b)).
    pub fn triangulation_covariance(&self, px: &StereoPixels, sigma_px: f64) -> Result<Matrix3<f64>, GeometryError> {
        let J = self.triangulation_jacobian(px)?;
        Ok(J * J.transpose() * (sigma_px * sigma_px))
    }
}

/// Rotation taking camera-optical coordinates to body coordinates for a camera looking along body
/// x (optical z → body x, optical x → body −y, optical y → body −z), then pitched down by
/// `pitch_down_rad` about body y.
pub fn body_from_camera_rotation(pitch_down_rad: f64) -> Rotation3<f64> {
    let level = Rotation3::from_matrix_unchecked(Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0));
    // Pitching the nose down is a positive rotation about body y (x toward −z).
    Rotation3::from_axis_angle(&Vector3::y_axis(), pitch_down_rad) * level
}

/// `body_from_camera` extrinsic from a mounting offset (body frame, m) and a down pitch.
pub fn body_from_camera(offset_m: &Vector3<f64>, pitch_down_rad: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(*offset_m),
        UnitQuaternion::from_rotation_matrix(&body_from_camera_rotation(pitch_down_rad)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn rig() -> StereoRig {
        StereoRig { f_px: 500.0, cx_px: 320.0, cy_px: 240.0, baseline_m: 0.12, width_px: 640, height_px: 480 }
    }

    #[test]
    fn euler_convention_is_z_then_y_then_x() {
        let r = rotation_from_euler_zyx(&Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2));
        assert!((r * Vector3::x() - Vector3::y()).norm() < 1e-12, "yaw 90° turns x into y");
        let r = rotation_from_euler_zyx(&Vector3::new(0.0, std::f64::consts::FRAC_PI_2, 0.0));
        assert!((r * Vector3::x() + Vector3::z()).norm() < 1e-12, "pitch 90° turns x into −z");
        let t = Vector3::new(0.3, -0.4, 2.0);
        assert!((euler_zyx_from_rotation(&rotation_from_euler_zyx(&t)) - t).norm() < 1e-12);
    }

    #[test]
    fn process_model_moves_along_the_current_heading_then_turns_in_the_body_frame() {
        let start = Isometry3::identity();
        let u = ProcessInput { v_mps: 2.0, delta_theta_rad: Vector3::new(0.0, 0.0, 0.5), dt_s: 0.5 };
        let next = propagate(&start, &u);
        assert!((next.translation.vector - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
        let next2 = propagate(&next, &ProcessInput { delta_theta_rad: Vector3::zeros(), ..u });
        let dir = Vector3::new(0.5f64.cos(), 0.5f64.sin(), 0.0);
        assert!((next2.translation.vector - (Vector3::x() + dir)).norm() < 1e-12);
        // Body-frame increment: after pitching up 90°, a yaw increment turns about body z (world −x).
        let pitched =
            Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_euler_angles(0.0, -1.0, 0.0));
        let turned = propagate(&pitched, &ProcessInput { v_mps: 0.0, delta_theta_rad: Vector3::z() * 0.3, dt_s: 1.0 });
        let body_z = pitched.rotation * Vector3::z();
        assert!((turned.rotation * Vector3::z() - body_z).norm() < 1e-12, "rotation about body z keeps body z");
    }

    #[test]
    fn triangulation_inverts_projection_and_rejects_bad_disparity() {
        let p = Vector3::new(0.5, -0.3, 4.0);
        let px = rig().project(&p).unwrap();
        assert!((rig().triangulate(&px).unwrap() - p).norm() < 1e-9);
        let bad = StereoPixels { u_left_px: 100.0, u_right_px: 101.0, v_px: 10.0 };
        assert!(matches!(rig().triangulate(&bad), Err(GeometryError::NonPositiveDisparity { .. })));
        let nan = StereoPixels { u_left_px: f64::NAN, ..bad };
        assert_eq!(rig().triangulate(&nan), Err(GeometryError::NonFinite("stereo pixels")));
    }

    proptest! {
        #[test]
        fn triangulation_jacobian_matches_finite_differences(x in -2.0..2.0f64, y in -1.5..1.5f64, z in 1.0..30.0f64) {
            let r = rig();
            let Some(px) = r.project(&Vector3::new(x, y, z)) else { return Ok(()) };
            let J = r.triangulation_jacobian(&px).unwrap();
            let h = 1e-4;
            for (col, bump) in [(0, [h, 0.0, 0.0]), (1, [0.0, h, 0.0]), (2, [0.0, 0.0, h])] {
                let plus = StereoPixels { u_left_px: px.u_left_px + bump[0], u_right_px: px.u_right_px + bump[1], v_px: px.v_px + bump[2] };
                let minus = StereoPixels { u_left_px: px.u_left_px - bump[0], u_right_px: px.u_right_px - bump[1], v_px: px.v_px - bump[2] };
                let fd = (r.triangulate(&plus).unwrap() - r.triangulate(&minus).unwrap()) / (2.0 * h);
                let scale = 1.0 + fd.norm();
                prop_assert!((J.column(col) - fd).norm() < 1e-4 * scale, "column {col}: {} vs {}", J.column(col), fd);
            }
        }
    }

    #[test]
    fn triangulation_covariance_matches_monte_carlo() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let r = rig();
        let px = r.project(&Vector3::new(0.8, -0.4, 6.0)).unwrap();
        let sigma = 0.5;
        let cov = r.triangulation_covariance(&px, sigma).unwrap();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        let n = Normal::new(0.0, sigma).unwrap();
        let samples: Vec<Vector3<f64>> = (0..40_000)
            .map(|_| {
                let noisy = StereoPixels {
                    u_left_px: px.u_left_px + n.sample(&mut rng),
                    u_right_px: px.u_right_px + n.sample(&mut rng),
                    v_px: px.v_px + n.sample(&mut rng),
                };
                r.triangulate(&noisy).unwrap()
            })
            .collect();
        let mean = samples.iter().sum::<Vector3<f64>>() / samples.len() as f64;
        let mc = samples.iter().map(|s| (s - mean) * (s - mean).transpose()).sum::<Matrix3<f64>>()
            / (samples.len() - 1) as f64;
        for i in 0..3 {
            let rel = (mc[(i, i)] - cov[(i, i)]).abs() / cov[(i, i)];
            assert!(rel < 0.06, "variance {i}: Monte Carlo {} vs first order {}", mc[(i, i)], cov[(i, i)]);
        }
        let corr_mc = mc[(0, 2)] / (mc[(0, 0)] * mc[(2, 2)]).sqrt();
        let corr = cov[(0, 2)] / (cov[(0, 0)] * cov[(2, 2)]).sqrt();
        assert!((corr_mc - corr).abs() < 0.05, "x-z correlation {corr_mc} vs {corr}");
    }

    #[test]
    fn a_level_camera_looks_along_body_x_and_pitch_tilts_it_down() {
        let r = body_from_camera_rotation(0.0);
        assert!((r * Vector3::z() - Vector3::x()).norm() < 1e-12);
        assert!((r * Vector3::x() + Vector3::y()).norm() < 1e-12);
        assert!((r * Vector3::y() + Vector3::z()).norm() < 1e-12);
        let down = body_from_camera_rotation(std::f64::consts::FRAC_PI_4) * Vector3::z();
        assert!(down.z < -0.7 && down.x > 0.7, "{down}");
    }
}

/// Least-squares rigid transform `dst_from_src` (rotation and translation, no scale) mapping the
/// points `src` onto `dst` with per-pair `weights` (Horn 1987 / Umeyama 1991, by SVD). `None`
/// with fewer than 3 pairs or degenerate (collinear) geometry.
pub fn align_rigid(src: &[Vector3<f64>], dst: &[Vector3<f64>], weights: &[f64]) -> Option<Isometry3<f64>> {
    if src.len() < 3 || src.len() != dst.len() || weights.len() != src.len() {
        return None;
    }
    let wsum: f64 = weights.iter().sum();
    if wsum.is_nan() || wsum <= 0.0 {
        return None;
    }
    let ms: Vector3<f64> = src.iter().zip(weights).map(|(p, w)| p * *w).sum::<Vector3<f64>>() / wsum;
    let md: Vector3<f64> = dst.iter().zip(weights).map(|(p, w)| p * *w).sum::<Vector3<f64>>() / wsum;
    let mut cov = Matrix3::zeros();
    for ((s, d), w) in src.iter().zip(dst).zip(weights) {
        cov += (d - md) * (s - ms).transpose() * *w;
    }
    let mut svd = cov.svd(true, true);
    svd.sort_by_singular_values(); // descending: the reflection fix goes on the smallest
    let (u, vt) = (svd.u?, svd.v_t?);
    let sv = svd.singular_values;
    if sv[1] < 1e-9 * sv[0].max(1e-300) {
        return None; // collinear: the rotation about the line is unobservable
    }
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = Rotation3::from_matrix_unchecked(u * d * vt);
    let t = md - r * ms;
    Some(Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&r)))
}

#[cfg(test)]
mod align_tests {
    use super::*;

    #[test]
    fn alignment_recovers_a_known_transform_and_refuses_collinear_points() {
        let truth =
            Isometry3::from_parts(Translation3::new(3.0, -2.0, 1.0), UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1));
        let src: Vec<Vector3<f64>> = (0..20)
            .map(|i| Vector3::new((i as f64).sin() * 5.0, (i as f64 * 0.7).cos() * 3.0, i as f64 * 0.1))
            .collect();
        let dst: Vec<Vector3<f64>> = src.iter().map(|p| truth.transform_point(&(*p).into()).coords).collect();
        let est = align_rigid(&src, &dst, &[1.0; 20]).unwrap();
        assert!((est.translation.vector - truth.translation.vector).norm() < 1e-9, "{est} vs {truth}");
        assert!(est.rotation.angle_to(&truth.rotation) < 1e-9);
        let line: Vec<Vector3<f64>> = (0..10).map(|i| Vector3::new(i as f64, 2.0 * i as f64, 0.0)).collect();
        assert!(align_rigid(&line, &line, &[1.0; 10]).is_none());
    }
}

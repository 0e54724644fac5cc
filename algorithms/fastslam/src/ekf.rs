//! The per-landmark EKF of FastSLAM (EQUATIONS §2-4), in the literature's names.
//!
//! Measurement of landmark L from a body pose (p, R), in the body frame (EQUATIONS §2, [3D] eq 11 with
//! erratum §9): z = h(p, R, L) = Rᵀ·(L − p) + η, η ~ N(0, Rz). Jacobians: H_L = ∂h/∂L = Rᵀ, and
//! for the body-frame pose perturbation (p = p̂ + δp, R = R̂·Exp(δφ)) H_x = ∂h/∂(δp, δφ) =
//! [−R̂ᵀ, [ẑ]×]. Updates use the Joseph form; a covariance that is not positive definite is an
//! error, never a panic.

#![allow(non_snake_case)]

use nalgebra::{Cholesky, Isometry3, Matrix3, Matrix3x6, Vector3};

use crate::sym3::Chol3;

/// Smallest depth in the camera at which a landmark is predicted with the stereo model, m.
pub const MIN_STEREO_DEPTH_M: f64 = 0.05;

/// Errors of the filter mathematics.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    /// A covariance that must be positive definite is not.
    #[error("{0} is not positive definite")]
    NotPositiveDefinite(&'static str),
    /// A value is NaN or infinite.
    #[error("non-finite {0}")]
    NonFinite(&'static str),
    /// A landmark predicted behind (or at) the camera cannot be compared with a stereo
    /// observation.
    #[error("landmark behind the camera")]
    BehindCamera,
}

/// One landmark's Gaussian estimate and bookkeeping.
#[derive(Debug, Clone, PartialEq)]
pub struct LandmarkEkf {
    /// Mean position in the local-map frame, m.
    pub mean_m: Vector3<f64>,
    /// Covariance, m².
    pub cov_m2: Matrix3<f64>,
    /// Descriptor, when the observations carry one.
    pub descriptor: Option<[u8; 32]>,
    /// Times observed (including the first).
    pub hits: u32,
    /// Frame of the last observation.
    pub last_seen_frame: u32,
    /// For a landmark first seen by a stereo camera: its estimate in anchored inverse depth
    /// ([`InverseDepth`]), which the stereo updates work on; `mean_m` and `cov_m2` are then its
    /// first-order Cartesian view, kept in step.
    pub inverse_depth: Option<InverseDepth>,
}

/// A landmark in anchored inverse depth (Civera, Davison, Montiel 2008), anchored at the camera
/// pose it was first seen from (in FastSLAM a particle's pose, exact given the path): s = (a, b,
/// w) with the point at `world_from_anchor`·(a/w, b/w, 1/w). A stereo observation's normalised
/// coordinates are this very parametrisation, so the first observation is an exact Gaussian
/// prior at any depth, and later stereo observations are nearly linear in it, where a Cartesian
/// landmark far away is neither.
#[derive(Debug, Clone, PartialEq)]
pub struct InverseDepth {
    /// The anchor camera (optical frame) in the map.
    pub world_from_anchor: Isometry3<f64>,
    /// (a, b, w): direction (a, b, 1) in the anchor frame and inverse depth w, 1/m.
    pub s: Vector3<f64>,
    /// Covariance of `s`.
    pub cov: Matrix3<f64>,
}

/// Smallest inverse depth of the Cartesian view of an inverse-depth landmark, 1/m (1 km).
const MIN_VIEW_INVERSE_DEPTH: f64 = 1e-3;

impl InverseDepth {
    /// The Cartesian mean and first-order covariance in the map.
    pub fn cartesian(&self) -> (Vector3<f64>, Matrix3<f64>) {
        self.cartesian_with(&self.world_from_anchor.rotation.to_rotation_matrix().into_inner())
    }

    /// [`InverseDepth::cartesian`] with the anchor's rotation matrix R_wa at hand.
    fn cartesian_with(&self, R: &Matrix3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        let (a, b, w) = (self.s.x, self.s.y, self.s.z.max(MIN_VIEW_INVERSE_DEPTH));
        let p = Vector3::new(a / w, b / w, 1.0 / w);
        let Jp = Matrix3::new(1.0 / w, 0.0, -a / (w * w), 0.0, 1.0 / w, -b / (w * w), 0.0, 0.0, -1.0 / (w * w));
        let J = R * Jp;
        let c = J * self.cov * J.transpose();
        (R * p + self.world_from_anchor.translation.vector, (c + c.transpose()) * 0.5)
    }

    /// The predicted stereo coordinates from a camera at `world_from_camera` and their
    /// Jacobian with respect to (a, b, w) ([`Projection::predict`]). `None` when the landmark is
    /// not in front of the camera.
    pub fn predict(&self, world_from_camera: &Isometry3<f64>) -> Option<(Vector3<f64>, Matrix3<f64>)> {
        Projection::new(world_from_camera, &self.world_from_anchor).predict(&self.s)
    }
}

/// The part of an inverse-depth landmark's projection that depends only on the anchor and the
/// camera, not on (a, b, w): h = M·(a, b, 1) + w·d with M = R_cᵀ·R_a and d = R_cᵀ·(t_a − t_c).
/// Made once, it predicts the landmark at any (a, b, w) with a matrix-vector product (the
/// iterated update relinearises several times from the same camera).
#[derive(Debug, Clone, Copy)]
pub struct Projection {
    M: Matrix3<f64>,
    d: Vector3<f64>,
}

impl Projection {
    /// The projection from a camera at `world_from_camera` of landmarks anchored at `world_from_anchor`.
    pub fn new(world_from_camera: &Isometry3<f64>, world_from_anchor: &Isometry3<f64>) -> Self {
        Self::from_camera(&CameraPose::new(world_from_camera), world_from_anchor)
    }

    /// [`Projection::new`] from a camera whose rotation matrix is already at hand.
    pub fn from_camera(camera: &CameraPose, world_from_anchor: &Isometry3<f64>) -> Self {
        Self::from_rotations(camera, world_from_anchor, &world_from_anchor.rotation.to_rotation_matrix().into_inner())
    }

    /// ... and the anchor's rotation matrix R_wa too.
    fn from_rotations(camera: &CameraPose, world_from_anchor: &Isometry3<f64>, Ra: &Matrix3<f64>) -> Self {
        let Rct = &camera.camera_from_world_rot;
        Self {
            M: Rct * Ra,
            d: Rct * (world_from_anchor.translation.vector - camera.world_from_camera.translation.vector),
        }
    }

    /// The predicted stereo coordinates of s = (a, b, w) and their Jacobian with respect to it,
    /// in the homogeneous form that stays finite as w → 0: h = M·(a, b, 1) + w·d, s = (h_x/h_z,
    /// h_y/h_z, w/h_z). `None` when the landmark is not in front of the camera.
    pub fn predict(&self, s: &Vector3<f64>) -> Option<(Vector3<f64>, Matrix3<f64>)> {
        let (M, dt) = (&self.M, &self.d);
        let (a, b, w) = (s.x, s.y, s.z);
        let h = M * Vector3::new(a, b, 1.0) + dt * w;
        // In front: depth 1/w·h_z above the minimum (h_z > 0 and w·MIN < h_z).
        if !(h.z > 0.0 && h.z > w * MIN_STEREO_DEPTH_M) {
            return None;
        }
        let iz = 1.0 / h.z;
        let s = Vector3::new(h.x * iz, h.y * iz, w * iz);
        let ds_dh = Matrix3::new(iz, 0.0, -h.x * iz * iz, 0.0, iz, -h.y * iz * iz, 0.0, 0.0, -w * iz * iz);
        let dh = Matrix3::from_columns(&[M.column(0).into_owned(), M.column(1).into_owned(), *dt]);
        let mut H = ds_dh * dh;
        H[(2, 2)] += iz;
        Some((s, H))
    }
}

/// A camera's [`Projection`] for the landmarks of one anchor, with the anchor's rotation matrix:
/// what every landmark anchored at one camera pose shares (in FastSLAM, those one particle's
/// line created in one frame).
#[derive(Debug, Clone, Copy)]
pub struct AnchorView {
    anchor: Isometry3<f64>,
    Ra: Matrix3<f64>,
    proj: Projection,
}

impl AnchorView {
    /// `camera`'s view of the landmarks anchored at `world_from_anchor`.
    pub fn new(camera: &CameraPose, world_from_anchor: &Isometry3<f64>) -> Self {
        let Ra = world_from_anchor.rotation.to_rotation_matrix().into_inner();
        Self { anchor: *world_from_anchor, Ra, proj: Projection::from_rotations(camera, world_from_anchor, &Ra) }
    }
}

/// The last [`AnchorView`] of one camera, kept while the landmarks looked at share its anchor
/// (landmarks visited in id order mostly do): the same numbers as computing it each time.
#[derive(Debug, Clone, Default)]
pub struct AnchorMemo {
    last: Option<AnchorView>,
}

impl AnchorMemo {
    /// `camera`'s view of the landmarks anchored at `world_from_anchor` (one camera per memo).
    pub fn get(&mut self, camera: &CameraPose, world_from_anchor: &Isometry3<f64>) -> &AnchorView {
        match &mut self.last {
            Some(v) if v.anchor == *world_from_anchor => {}
            slot => *slot = Some(AnchorView::new(camera, world_from_anchor)),
        }
        self.last.as_ref().expect("set above")
    }
}

/// A camera pose with its world-to-camera rotation as a matrix: what predicting many landmarks
/// from one camera shares.
#[derive(Debug, Clone, Copy)]
pub struct CameraPose {
    /// `world_from_camera` (optical frame).
    pub world_from_camera: Isometry3<f64>,
    /// R_wcᵀ.
    camera_from_world_rot: Matrix3<f64>,
}

impl CameraPose {
    /// The camera at `world_from_camera`.
    pub fn new(world_from_camera: &Isometry3<f64>) -> Self {
        Self {
            world_from_camera: *world_from_camera,
            camera_from_world_rot: world_from_camera.rotation.inverse().to_rotation_matrix().into_inner(),
        }
    }
}

/// A body pose and a camera on it, with the rotations as matrices: what the stereo predictions
/// and pose Jacobians of one particle's observations in one frame share.
#[derive(Debug, Clone, Copy)]
pub struct StereoRig {
    /// `world_from_body`.
    pub world_from_body: Isometry3<f64>,
    /// `body_from_camera`.
    pub body_from_camera: Isometry3<f64>,
    /// The camera in the world.
    pub camera: CameraPose,
    /// R_wbᵀ.
    body_from_world_rot: Matrix3<f64>,
    /// R_bcᵀ.
    camera_from_body_rot: Matrix3<f64>,
}

impl StereoRig {
    /// The camera `body_from_camera` on the body at `world_from_body`.
    pub fn new(world_from_body: &Isometry3<f64>, body_from_camera: &Isometry3<f64>) -> Self {
        Self {
            world_from_body: *world_from_body,
            body_from_camera: *body_from_camera,
            camera: CameraPose::new(&(world_from_body * body_from_camera)),
            body_from_world_rot: world_from_body.rotation.inverse().to_rotation_matrix().into_inner(),
            camera_from_body_rot: body_from_camera.rotation.inverse().to_rotation_matrix().into_inner(),
        }
    }

    /// ∂s/∂(δp, δφ) of the stereo measurement of landmark `L` (perturbation p + δp, R·Exp(δφ)):
    /// J_s·R_bcᵀ·[−R_wbᵀ, [p_b]×], p_b = R_wbᵀ·(L − p) (as [`stereo_pose_jacobian`]).
    pub fn pose_jacobian(&self, L: &Vector3<f64>) -> Matrix3x6<f64> {
        let p_b = self.body_from_world_rot * (L - self.world_from_body.translation.vector);
        let p_c = self.camera_from_body_rot * (p_b - self.body_from_camera.translation.vector);
        let JR = stereo_jacobian(&p_c) * self.camera_from_body_rot;
        let mut H = Matrix3x6::zeros();
        H.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-(JR * self.body_from_world_rot)));
        H.fixed_view_mut::<3, 3>(0, 3).copy_from(&(JR * p_b.cross_matrix()));
        H
    }
}

/// h(p, R, L) = Rᵀ·(L − p): the landmark in the body frame.
pub fn predict_measurement(world_from_body: &Isometry3<f64>, landmark_m: &Vector3<f64>) -> Vector3<f64> {
    world_from_body.rotation.inverse() * (landmark_m - world_from_body.translation.vector)
}

/// (H_L, H_x) at the pose and landmark.
pub fn jacobians(world_from_body: &Isometry3<f64>, landmark_m: &Vector3<f64>) -> (Matrix3<f64>, Matrix3x6<f64>) {
    let Rt = world_from_body.rotation.inverse().to_rotation_matrix().into_inner();
    let z = predict_measurement(world_from_body, landmark_m);
    let mut Hx = Matrix3x6::zeros();
    Hx.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-Rt));
    Hx.fixed_view_mut::<3, 3>(0, 3).copy_from(&z.cross_matrix());
    (Rt, Hx)
}

/// The innovation of one observation against one landmark.
#[derive(Debug, Clone)]
pub struct Innovation {
    /// ν = z − ẑ, m.
    pub nu: Vector3<f64>,
    /// S = H_L·Σ·H_Lᵀ + Rz, m².
    pub S: Matrix3<f64>,
    /// H_L = Rᵀ at the pose the innovation was computed for.
    pub HL: Matrix3<f64>,
    /// Cholesky factor of S.
    chol: Chol3,
    /// ε = νᵀ·S⁻¹·ν ([3D] eq 15).
    pub mahalanobis: f64,
}

impl Innovation {
    /// ln N(ν; 0, S).
    pub fn log_likelihood(&self) -> f64 {
        -0.5 * (self.mahalanobis + self.chol.log_det() + 3.0 * (2.0 * std::f64::consts::PI).ln())
    }

    /// ln |S|.
    pub fn log_det(&self) -> f64 {
        self.chol.log_det()
    }

    /// S⁻¹.
    pub fn S_inv(&self) -> Matrix3<f64> {
        self.chol.inverse()
    }

    /// The Cholesky factor L of S (S = L·Lᵀ): `whiten` gives L⁻¹·B, so Bᵀ·S⁻¹·B = (L⁻¹B)ᵀ(L⁻¹B).
    pub fn chol(&self) -> &Chol3 {
        &self.chol
    }
}

/// Innovation of measurement `z_m` (body frame, covariance `Rz`) against landmark `lm` seen from
/// `world_from_body` ([3D] eq 14-16).
pub fn innovation(
    world_from_body: &Isometry3<f64>,
    lm: &LandmarkEkf,
    z_m: &Vector3<f64>,
    Rz: &Matrix3<f64>,
) -> Result<Innovation, FilterError> {
    let HL = world_from_body.rotation.inverse().to_rotation_matrix().into_inner();
    let S = HL * lm.cov_m2 * HL.transpose() + Rz;
    let S = (S + S.transpose()) * 0.5;
    let chol = Chol3::new(&S).ok_or(FilterError::NotPositiveDefinite("innovation covariance S"))?;
    let nu = z_m - HL * (lm.mean_m - world_from_body.translation.vector);
    let mahalanobis = chol.mahalanobis(&nu);
    if !mahalanobis.is_finite() {
        return Err(FilterError::NonFinite("innovation"));
    }
    Ok(Innovation { nu, S, HL, chol, mahalanobis })
}

/// Normalised stereo coordinates s(p) = (x/z, y/z, 1/z) of a camera-frame point: for a
/// rectified pair these are (uL − cx, v − cy, uL − uR) divided by f, f and f·b, so pixel noise
/// makes them (nearly) Gaussian at any depth, where the triangulated point's depth is not.
pub fn stereo_coords(p_cam: &Vector3<f64>) -> Vector3<f64> {
    let iz = 1.0 / p_cam.z;
    Vector3::new(p_cam.x * iz, p_cam.y * iz, iz)
}

/// ∂s/∂p of [`stereo_coords`].
pub fn stereo_jacobian(p_cam: &Vector3<f64>) -> Matrix3<f64> {
    let iz = 1.0 / p_cam.z;
    let iz2 = iz * iz;
    Matrix3::new(iz, 0.0, -p_cam.x * iz2, 0.0, iz, -p_cam.y * iz2, 0.0, 0.0, -iz2)
}

/// Innovation of a stereo observation `s_obs` (normalised stereo coordinates, covariance
/// `Cs`) against landmark `lm` seen from a camera at `world_from_camera`: h(L) = s(R_wcᵀ·(L −
/// t_wc)), H_L = J_s·R_wcᵀ.
pub fn innovation_stereo(
    world_from_camera: &Isometry3<f64>,
    lm: &LandmarkEkf,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
) -> Result<Innovation, FilterError> {
    let Rt = world_from_camera.rotation.inverse().to_rotation_matrix().into_inner();
    let p = Rt * (lm.mean_m - world_from_camera.translation.vector);
    if p.z.is_nan() || p.z <= MIN_STEREO_DEPTH_M {
        return Err(FilterError::BehindCamera);
    }
    let HL = stereo_jacobian(&p) * Rt;
    let S = HL * lm.cov_m2 * HL.transpose() + Cs;
    let S = (S + S.transpose()) * 0.5;
    let chol = Chol3::new(&S).ok_or(FilterError::NotPositiveDefinite("innovation covariance S"))?;
    let nu = s_obs - stereo_coords(&p);
    let mahalanobis = chol.mahalanobis(&nu);
    if !mahalanobis.is_finite() {
        return Err(FilterError::NonFinite("innovation"));
    }
    Ok(Innovation { nu, S, HL, chol, mahalanobis })
}

/// Innovation of a stereo observation (`s_obs`, `Cs`) against an inverse-depth landmark seen
/// from a camera at `world_from_camera`; `HL` is with respect to (a, b, w).
pub fn innovation_inverse_depth(
    world_from_camera: &Isometry3<f64>,
    inv: &InverseDepth,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
) -> Result<Innovation, FilterError> {
    innovation_inverse_depth_from(&CameraPose::new(world_from_camera), inv, s_obs, Cs)
}

/// [`innovation_inverse_depth`] from a camera whose rotation matrix is already at hand.
pub fn innovation_inverse_depth_from(
    camera: &CameraPose,
    inv: &InverseDepth,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
) -> Result<Innovation, FilterError> {
    innovation_inverse_depth_in(&AnchorView::new(camera, &inv.world_from_anchor), inv, s_obs, Cs)
}

/// [`innovation_inverse_depth`] through the camera's view of the landmark's anchor (`view`, made
/// for `inv.world_from_anchor`).
pub fn innovation_inverse_depth_in(
    view: &AnchorView,
    inv: &InverseDepth,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
) -> Result<Innovation, FilterError> {
    debug_assert!(view.anchor == inv.world_from_anchor);
    let (s, HL) = view.proj.predict(&inv.s).ok_or(FilterError::BehindCamera)?;
    let S = HL * inv.cov * HL.transpose() + Cs;
    let S = (S + S.transpose()) * 0.5;
    let chol = Chol3::new(&S).ok_or(FilterError::NotPositiveDefinite("innovation covariance S"))?;
    let nu = s_obs - s;
    let mahalanobis = chol.mahalanobis(&nu);
    if !mahalanobis.is_finite() {
        return Err(FilterError::NonFinite("innovation"));
    }
    Ok(Innovation { nu, S, HL, chol, mahalanobis })
}

/// Iterated EKF update of an inverse-depth landmark with a stereo observation (`s_obs`, `Cs`)
/// from a camera at `world_from_camera` (Gauss-Newton relinearisation, up to `iterations` or
/// until a step is below 10⁻³ of the prior's σ; a step that raises the MAP cost or leaves the
/// camera's front halved), then the Cartesian view. Returns the observation's normalised innovation squared against the landmark before the
/// update (its NIS, νᵀS⁻¹ν at the prior: what [`innovation_inverse_depth`] gives).
pub fn update_inverse_depth(
    lm: &mut LandmarkEkf,
    world_from_camera: &Isometry3<f64>,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
    iterations: usize,
) -> Result<f64, FilterError> {
    update_inverse_depth_from(lm, &CameraPose::new(world_from_camera), s_obs, Cs, iterations)
}

/// [`update_inverse_depth`] from a camera whose rotation matrix is already at hand.
pub fn update_inverse_depth_from(
    lm: &mut LandmarkEkf,
    camera: &CameraPose,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
    iterations: usize,
) -> Result<f64, FilterError> {
    let inv = lm.inverse_depth.as_ref().ok_or(FilterError::NonFinite("inverse depth"))?;
    let view = AnchorView::new(camera, &inv.world_from_anchor);
    update_inverse_depth_in(lm, &view, s_obs, Cs, iterations)
}

/// [`update_inverse_depth`] through the camera's view of the landmark's anchor (`view`, made for
/// the landmark's `world_from_anchor`).
pub fn update_inverse_depth_in(
    lm: &mut LandmarkEkf,
    view: &AnchorView,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
    iterations: usize,
) -> Result<f64, FilterError> {
    let inv = lm.inverse_depth.as_ref().ok_or(FilterError::NonFinite("inverse depth"))?;
    debug_assert!(view.anchor == inv.world_from_anchor);
    let (x0, P) = (inv.s, inv.cov);
    let (Ra, proj) = (&view.Ra, &view.proj);
    let innovation_chol = |H: &Matrix3<f64>| {
        let S = H * P * H.transpose() + Cs;
        Chol3::new(&((S + S.transpose()) * 0.5)).ok_or(FilterError::NotPositiveDefinite("innovation covariance S"))
    };
    // The prior's prediction: the NIS, and the first linearisation.
    let (mut s, mut H) = proj.predict(&x0).ok_or(FilterError::BehindCamera)?;
    let mut chol = innovation_chol(&H)?;
    let nis = chol.mahalanobis(&(s_obs - s));
    if !nis.is_finite() {
        return Err(FilterError::NonFinite("innovation"));
    }
    let P_chol = Chol3::new(&P).ok_or(FilterError::NotPositiveDefinite("landmark covariance"))?;
    let Cs_chol = Chol3::new(Cs).ok_or(FilterError::NotPositiveDefinite("stereo covariance"))?;
    // The MAP cost at x, with the prediction there (for the next linearisation).
    let cost = |x: &Vector3<f64>| -> Option<(f64, Vector3<f64>, Matrix3<f64>)> {
        let (s, H) = proj.predict(x)?;
        Some((Cs_chol.mahalanobis(&(s_obs - s)) + P_chol.mahalanobis(&(x - x0)), s, H))
    };
    let mut x = x0;
    let mut c_x = Cs_chol.mahalanobis(&(s_obs - s));
    let mut chol_at_x = true;
    // The gain at the current linearisation, once computed there (the last iteration's is
    // the final update's).
    let mut K_at_x: Option<Matrix3<f64>> = None;
    for _ in 0..iterations.max(1) {
        if !chol_at_x {
            chol = innovation_chol(&H)?;
            chol_at_x = true;
        }
        let K = P * H.transpose() * chol.inverse();
        K_at_x = Some(K);
        let step = x0 + K * (s_obs - s - H * (x0 - x)) - x;
        // Converged: the step would move the estimate by less than a thousandth of the prior's
        // standard deviation (stepᵀP⁻¹step < 10⁻⁶). The first step of a stereo observation is
        // of the order of one σ, the second 10⁻³-10⁻⁴ σ, the third below 10⁻⁶ σ.
        if P_chol.mahalanobis(&step) < 1e-6 {
            break;
        }
        let mut alpha = 1.0;
        let mut moved = false;
        while alpha > 1e-3 {
            let trial = x + step * alpha;
            if let Some((c, s_t, H_t)) = cost(&trial)
                && c <= c_x
            {
                (x, s, H, c_x) = (trial, s_t, H_t, c);
                chol_at_x = false;
                K_at_x = None;
                moved = true;
                break;
            }
            alpha *= 0.5;
        }
        if !moved || (step * alpha).norm() < 1e-9 * (1.0 + x.norm()) {
            break;
        }
    }
    let K = match K_at_x {
        Some(K) => K,
        None => {
            if !chol_at_x {
                chol = innovation_chol(&H)?;
            }
            P * H.transpose() * chol.inverse()
        }
    };
    let IKH = Matrix3::identity() - K * H;
    let cov = IKH * P * IKH.transpose() + K * Cs * K.transpose();
    let cov = (cov + cov.transpose()) * 0.5;
    if !(x.iter().all(|v| v.is_finite()) && cov.iter().all(|v| v.is_finite())) {
        return Err(FilterError::NonFinite("landmark update"));
    }
    let new = InverseDepth { s: x, cov, world_from_anchor: inv.world_from_anchor };
    let (mean, cart) = new.cartesian_with(Ra);
    lm.mean_m = mean;
    lm.cov_m2 = cart;
    lm.inverse_depth = Some(new);
    Ok(nis)
}

/// A new landmark from a stereo observation (`s_obs`, `Cs`) made by a camera at
/// `world_from_camera`: anchored there, exactly the observation's Gaussian.
pub fn init_landmark_inverse_depth(
    world_from_camera: &Isometry3<f64>,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
    descriptor: Option<[u8; 32]>,
    frame: u32,
) -> LandmarkEkf {
    init_landmark_inverse_depth_from(&CameraPose::new(world_from_camera), s_obs, Cs, descriptor, frame)
}

/// [`init_landmark_inverse_depth`] from a camera whose rotation matrix is already at hand.
pub fn init_landmark_inverse_depth_from(
    camera: &CameraPose,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
    descriptor: Option<[u8; 32]>,
    frame: u32,
) -> LandmarkEkf {
    let inv = InverseDepth { world_from_anchor: camera.world_from_camera, s: *s_obs, cov: *Cs };
    let (mean_m, cov_m2) = inv.cartesian_with(&camera.camera_from_world_rot.transpose());
    LandmarkEkf { mean_m, cov_m2, descriptor, hits: 1, last_seen_frame: frame, inverse_depth: Some(inv) }
}

/// ∂s/∂(δp, δφ) of the stereo measurement of landmark `L` from the body pose `world_from_body`
/// (perturbation p + δp, R·Exp(δφ)) with the camera at `body_from_camera`:
/// J_s·R_bcᵀ·[−Rᵀ, [p_b]×], p_b = Rᵀ·(L − p).
pub fn stereo_pose_jacobian(
    world_from_body: &Isometry3<f64>,
    body_from_camera: &Isometry3<f64>,
    L: &Vector3<f64>,
) -> Matrix3x6<f64> {
    StereoRig::new(world_from_body, body_from_camera).pose_jacobian(L)
}

/// EKF update of `lm` with the innovation `inn` (EQUATIONS §4): K = Σ·H_Lᵀ·S⁻¹, μ += K·ν,
/// Σ = (I − K·H_L)·Σ·(I − K·H_L)ᵀ + K·Rz·Kᵀ (Joseph form). `inn` must have been computed for
/// this landmark at the current pose.
pub fn update(lm: &mut LandmarkEkf, inn: &Innovation, Rz: &Matrix3<f64>) -> Result<(), FilterError> {
    let HL = inn.HL;
    let K = lm.cov_m2 * HL.transpose() * inn.S_inv();
    let mean = lm.mean_m + K * inn.nu;
    let IKH = Matrix3::identity() - K * HL;
    let cov = IKH * lm.cov_m2 * IKH.transpose() + K * Rz * K.transpose();
    let cov = (cov + cov.transpose()) * 0.5;
    if !(mean.iter().all(|v| v.is_finite()) && cov.iter().all(|v| v.is_finite())) {
        return Err(FilterError::NonFinite("landmark update"));
    }
    lm.mean_m = mean;
    lm.cov_m2 = cov;
    Ok(())
}

/// Iterated EKF update of `lm` with a stereo observation (`s_obs`, `Cs`) from a camera at
/// `world_from_camera`: the measurement s(p) = (x/z, y/z, 1/z) is far from linear in a
/// Cartesian landmark whose depth is still uncertain, and a single linearisation can throw the
/// mean across the camera. Gauss-Newton iterations relinearise at the new mean (up to
/// `iterations`); μᵢ₊₁ = μ₀ + Kᵢ·(z − h(μᵢ) − Hᵢ·(μ₀ − μᵢ)), then the Joseph-form covariance at
/// the last linearisation. An iterate behind the camera is an error and leaves `lm` unchanged.
pub fn update_stereo_iterated(
    lm: &mut LandmarkEkf,
    world_from_camera: &Isometry3<f64>,
    s_obs: &Vector3<f64>,
    Cs: &Matrix3<f64>,
    iterations: usize,
) -> Result<(), FilterError> {
    let Rt = world_from_camera.rotation.inverse().to_rotation_matrix().into_inner();
    let t = world_from_camera.translation.vector;
    let (mu0, P) = (lm.mean_m, lm.cov_m2);
    let P_inv = Cholesky::new(P).ok_or(FilterError::NotPositiveDefinite("landmark covariance"))?.inverse();
    let Cs_inv = Cholesky::new(*Cs).ok_or(FilterError::NotPositiveDefinite("stereo covariance"))?.inverse();
    // The MAP cost the iterations descend; a step that raises it or crosses the camera is halved.
    let cost = |mu: &Vector3<f64>| -> Option<f64> {
        let p = Rt * (mu - t);
        (p.z > MIN_STEREO_DEPTH_M).then(|| {
            let r = s_obs - stereo_coords(&p);
            let d = mu - mu0;
            r.dot(&(Cs_inv * r)) + d.dot(&(P_inv * d))
        })
    };
    let mut mu = mu0;
    let mut c_mu = cost(&mu).ok_or(FilterError::BehindCamera)?;
    let mut last = None;
    for _ in 0..iterations.max(1) {
        let p = Rt * (mu - t);
        let H = stereo_jacobian(&p) * Rt;
        let S = H * P * H.transpose() + Cs;
        let chol = Cholesky::new((S + S.transpose()) * 0.5)
            .ok_or(FilterError::NotPositiveDefinite("innovation covariance S"))?;
        let K = P * H.transpose() * chol.inverse();
        last = Some((H, K));
        let next = mu0 + K * (s_obs - stereo_coords(&p) - H * (mu0 - mu));
        let step = next - mu;
        let mut alpha = 1.0;
        let mut moved = false;
        while alpha > 1e-3 {
            let trial = mu + step * alpha;
            if let Some(c) = cost(&trial)
                && c <= c_mu
            {
                mu = trial;
                c_mu = c;
                moved = true;
                break;
            }
            alpha *= 0.5;
        }
        if !moved || (step * alpha).norm() < 1e-6 * (1.0 + mu.norm()) {
            break;
        }
    }
    // The covariance at the final linearisation.
    let p = Rt * (mu - t);
    if p.z > MIN_STEREO_DEPTH_M {
        let H = stereo_jacobian(&p) * Rt;
        let S = H * P * H.transpose() + Cs;
        if let Some(chol) = Cholesky::new((S + S.transpose()) * 0.5) {
            last = Some((H, P * H.transpose() * chol.inverse()));
        }
    }
    if !(Rt * (mu - t)).z.gt(&MIN_STEREO_DEPTH_M) {
        return Err(FilterError::BehindCamera);
    }
    let (H, K) = last.expect("at least one iteration");
    let IKH = Matrix3::identity() - K * H;
    let cov = IKH * P * IKH.transpose() + K * Cs * K.transpose();
    let cov = (cov + cov.transpose()) * 0.5;
    if !(mu.iter().all(|v| v.is_finite()) && cov.iter().all(|v| v.is_finite())) {
        return Err(FilterError::NonFinite("landmark update"));
    }
    lm.mean_m = mu;
    lm.cov_m2 = cov;
    Ok(())
}

/// A new landmark from an observation (EQUATIONS §4): μ = p + R·z, Σ = R·Rz·Rᵀ.
pub fn init_landmark(
    world_from_body: &Isometry3<f64>,
    z_m: &Vector3<f64>,
    Rz: &Matrix3<f64>,
    descriptor: Option<[u8; 32]>,
    frame: u32,
) -> LandmarkEkf {
    let R = world_from_body.rotation.to_rotation_matrix().into_inner();
    LandmarkEkf {
        mean_m: world_from_body.translation.vector + R * z_m,
        cov_m2: R * Rz * R.transpose(),
        descriptor,
        hits: 1,
        last_seen_frame: frame,
        inverse_depth: None,
    }
}

/// Hamming distance of two 32-byte descriptors.
pub fn hamming(a: &[u8; 32], b: &[u8; 32]) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x ^ y).count_ones()).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use proptest::prelude::*;

    fn pose(x: f64, y: f64, z: f64, r: f64, p: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(r, p, yaw))
    }

    proptest! {
        #[test]
        fn jacobians_match_finite_differences(
            x in -5.0..5.0f64, y in -5.0..5.0f64, r in -0.5..0.5f64, p in -0.5..0.5f64, yaw in -3.0..3.0f64,
            lx in -10.0..10.0f64, ly in -10.0..10.0f64, lz in -10.0..10.0f64,
        ) {
            let T = pose(x, y, 1.0, r, p, yaw);
            let L = Vector3::new(lx, ly, lz);
            let (HL, Hx) = jacobians(&T, &L);
            let h = 1e-6;
            for i in 0..3 {
                let mut d = Vector3::zeros();
                d[i] = h;
                let fd = (predict_measurement(&T, &(L + d)) - predict_measurement(&T, &(L - d))) / (2.0 * h);
                prop_assert!((HL.column(i) - fd).norm() < 1e-6);
            }
            for i in 0..6 {
                let perturb = |s: f64| {
                    let mut dp = Vector3::zeros();
                    let mut dphi = Vector3::zeros();
                    if i < 3 { dp[i] = s } else { dphi[i - 3] = s }
                    Isometry3::from_parts(
                        Translation3::from(T.translation.vector + dp),
                        T.rotation * UnitQuaternion::from_scaled_axis(dphi),
                    )
                };
                let fd = (predict_measurement(&perturb(h), &L) - predict_measurement(&perturb(-h), &L)) / (2.0 * h);
                prop_assert!((Hx.column(i) - fd).norm() < 1e-5 * (1.0 + fd.norm()), "column {}: {} vs {}", i, Hx.column(i), fd);
            }
        }
    }

    proptest! {
        #[test]
        fn stereo_jacobians_match_finite_differences(
            x in -5.0..5.0f64, y in -5.0..5.0f64, r in -0.3..0.3f64, p in -0.3..0.3f64, yaw in -3.0..3.0f64,
            dist in 2.0..60.0f64, lat in -0.5..0.5f64, up in -0.3..0.3f64,
        ) {
            let T = pose(x, y, 1.0, r, p, yaw);
            let cam = geometry::body_from_camera(&Vector3::new(0.5, 0.1, -0.2), 0.3);
            // A landmark in front of the camera.
            let L = (T * cam).transform_point(&nalgebra::Point3::new(lat * dist, up * dist, dist)).coords;
            let h = |T: &Isometry3<f64>, L: &Vector3<f64>| {
                stereo_coords(&(T * cam).inverse_transform_point(&(*L).into()).coords)
            };
            let lm = LandmarkEkf { mean_m: L, cov_m2: Matrix3::identity(), descriptor: None, hits: 1, last_seen_frame: 0, inverse_depth: None };
            let inn = innovation_stereo(&(T * cam), &lm, &Vector3::zeros(), &Matrix3::identity()).unwrap();
            let Hx = stereo_pose_jacobian(&T, &cam, &L);
            let e = 1e-6;
            for i in 0..3 {
                let mut d = Vector3::zeros();
                d[i] = e;
                let fd = (h(&T, &(L + d)) - h(&T, &(L - d))) / (2.0 * e);
                prop_assert!((inn.HL.column(i) - fd).norm() < 1e-6 * (1.0 + fd.norm()), "H_L column {}", i);
            }
            for i in 0..6 {
                let perturb = |s: f64| {
                    let mut dp = Vector3::zeros();
                    let mut dphi = Vector3::zeros();
                    if i < 3 { dp[i] = s } else { dphi[i - 3] = s }
                    Isometry3::from_parts(
                        Translation3::from(T.translation.vector + dp),
                        T.rotation * UnitQuaternion::from_scaled_axis(dphi),
                    )
                };
                let fd = (h(&perturb(e), &L) - h(&perturb(-e), &L)) / (2.0 * e);
                prop_assert!((Hx.column(i) - fd).norm() < 1e-5 * (1.0 + fd.norm()), "H_x column {}: {} vs {}", i, Hx.column(i), fd);
            }
        }
    }

    #[test]
    fn an_iterated_stereo_update_does_not_throw_a_far_landmark_across_the_camera() {
        // A landmark initialised far (40 m, σ 12 m along the ray) seen nearer (25 m): a single
        // linearisation at 40 m moves it to 17.5 m; the damped iterations land near 25 m.
        let cam = Isometry3::identity();
        let prior = LandmarkEkf {
            mean_m: Vector3::new(0.0, 0.0, 40.0),
            cov_m2: Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 144.0)),
            descriptor: None,
            hits: 1,
            last_seen_frame: 0,
            inverse_depth: None,
        };
        let Cs = Matrix3::from_diagonal(&Vector3::new(1e-6, 1e-6, 4e-6));
        let truth = Vector3::new(0.0, 0.0, 25.0);
        let mut once = prior.clone();
        let inn = innovation_stereo(&cam, &once, &stereo_coords(&truth), &Cs).unwrap();
        update(&mut once, &inn, &Cs).unwrap();
        assert!((once.mean_m - truth).norm() > 3.0, "one linearisation is far off: {}", once.mean_m);
        let mut lm = prior.clone();
        update_stereo_iterated(&mut lm, &cam, &stereo_coords(&truth), &Cs, 8).unwrap();
        assert!((lm.mean_m - truth).norm() < 1.0, "{}", lm.mean_m);
    }

    proptest! {
        #[test]
        fn the_inverse_depth_jacobian_matches_finite_differences(
            ax in -0.5..0.5f64, ay in -0.3..0.3f64, yaw in -0.4..0.4f64,
            a in -0.6..0.6f64, b in -0.3..0.3f64, w in 0.0..0.4f64,
            tx in -2.0..2.0f64, tz in 0.0..3.0f64,
        ) {
            let anchor = Isometry3::from_parts(Translation3::new(ax, ay, 0.3), UnitQuaternion::from_euler_angles(0.02, yaw, -0.01));
            let cam = Isometry3::from_parts(Translation3::new(tx, 0.1, tz), UnitQuaternion::from_euler_angles(-0.03, yaw * 0.5, 0.02));
            let inv = InverseDepth { world_from_anchor: anchor, s: Vector3::new(a, b, w), cov: Matrix3::identity() };
            let Some((s0, H)) = inv.predict(&cam) else { return Ok(()) };
            let e = 1e-7;
            for i in 0..3 {
                let mut d = Vector3::zeros();
                d[i] = e;
                let p = InverseDepth { s: inv.s + d, ..inv.clone() }.predict(&cam).unwrap().0;
                let m = InverseDepth { s: inv.s - d, ..inv.clone() }.predict(&cam).unwrap().0;
                let fd = (p - m) / (2.0 * e);
                prop_assert!((H.column(i) - fd).norm() < 1e-5 * (1.0 + fd.norm()), "column {}: {} vs {}", i, H.column(i), fd);
            }
            // Where the point is finite, the prediction is the Cartesian point's stereo coordinates.
            if w > 1e-2 {
                let (X, _) = inv.cartesian();
                let direct = stereo_coords(&cam.inverse_transform_point(&X.into()).coords);
                prop_assert!((direct - s0).norm() < 1e-9 * (1.0 + s0.norm()));
            }
        }
    }

    #[test]
    fn inverse_depth_landmarks_converge_at_every_depth_without_bias() {
        // A camera driving 1 m per frame towards points 20-200 m away, pixel noise 0.5 px (KITTI):
        // the mean depth error over many points stays well under its spread (no 1/d bias).
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let (f, bl) = (718.0, 0.54);
        let n = Normal::new(0.0, 0.5).unwrap();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        for depth in [20.0, 60.0, 200.0] {
            let mut errs = vec![];
            for k in 0..300 {
                let truth = Vector3::new(((k % 7) as f64 - 3.0) * 0.1 * depth, 0.05 * depth, depth);
                let mut lm: Option<LandmarkEkf> = None;
                for step in 0..10 {
                    let cam =
                        Isometry3::from_parts(Translation3::new(0.0, 0.0, step as f64), UnitQuaternion::identity());
                    let p = cam.inverse_transform_point(&truth.into()).coords;
                    let (ul, ur, v) = (
                        f * p.x / p.z + n.sample(&mut rng),
                        f * (p.x - bl) / p.z + n.sample(&mut rng),
                        f * p.y / p.z + n.sample(&mut rng),
                    );
                    let d = ul - ur;
                    if d <= 0.05 {
                        continue;
                    }
                    let s_obs = Vector3::new(ul / f, v / f, d / (f * bl));
                    let Cs =
                        Matrix3::from_diagonal(&Vector3::new(0.25 / (f * f), 0.25 / (f * f), 0.5 / (f * bl).powi(2)));
                    match &mut lm {
                        None => lm = Some(init_landmark_inverse_depth(&cam, &s_obs, &Cs, None, 0)),
                        Some(l) => {
                            update_inverse_depth(l, &cam, &s_obs, &Cs, 3).unwrap();
                        }
                    }
                }
                let l = lm.unwrap();
                let w = l.inverse_depth.as_ref().unwrap().s.z;
                errs.push((w - 1.0 / depth) / (1.0 / depth));
            }
            let mean = errs.iter().sum::<f64>() / errs.len() as f64;
            let sd = (errs.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / errs.len() as f64).sqrt();
            assert!(
                mean.abs() < 3.0 * sd / (errs.len() as f64).sqrt() + 1e-3,
                "depth {depth}: relative inverse-depth bias {mean} (sd {sd})"
            );
        }
    }

    #[test]
    fn a_landmark_ekf_converges_on_a_static_landmark() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let truth = Vector3::new(4.0, -1.0, 2.0);
        let Rz = Matrix3::from_diagonal(&Vector3::new(0.04, 0.04, 0.25));
        let n = Normal::new(0.0, 1.0).unwrap();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        let noisy = |T: &Isometry3<f64>, rng: &mut rand_xoshiro::Xoshiro256PlusPlus| {
            let z = predict_measurement(T, &truth);
            z + Vector3::new(0.2 * n.sample(rng), 0.2 * n.sample(rng), 0.5 * n.sample(rng))
        };
        let T0 = pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let mut lm = init_landmark(&T0, &noisy(&T0, &mut rng), &Rz, None, 0);
        for k in 0..400 {
            let T = pose(0.02 * k as f64, 0.01 * k as f64, 0.0, 0.0, 0.0, 0.3 * (k as f64 * 0.05).sin());
            let z = noisy(&T, &mut rng);
            let inn = innovation(&T, &lm, &z, &Rz).unwrap();
            update(&mut lm, &inn, &Rz).unwrap();
            assert!((lm.cov_m2 - lm.cov_m2.transpose()).norm() < 1e-12, "Joseph form keeps Σ symmetric");
        }
        let err = lm.mean_m - truth;
        assert!(err.norm() < 0.1, "error {err}");
        assert!(lm.cov_m2.trace() < 0.003, "Σ shrank to {}", lm.cov_m2.trace());
        let nees = err.dot(&(lm.cov_m2.try_inverse().unwrap() * err));
        assert!(nees < 16.3, "consistent: NEES {nees}");
    }

    #[test]
    fn a_non_positive_definite_covariance_is_an_error_not_a_panic() {
        let T = pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let lm = LandmarkEkf {
            mean_m: Vector3::new(1.0, 0.0, 0.0),
            cov_m2: -Matrix3::identity(),
            descriptor: None,
            hits: 1,
            last_seen_frame: 0,
            inverse_depth: None,
        };
        let e = innovation(&T, &lm, &Vector3::new(1.0, 0.0, 0.0), &Matrix3::zeros()).unwrap_err();
        assert_eq!(e, FilterError::NotPositiveDefinite("innovation covariance S"));
        let nan = LandmarkEkf { mean_m: Vector3::new(f64::NAN, 0.0, 0.0), cov_m2: Matrix3::identity(), ..lm };
        assert!(innovation(&T, &nan, &Vector3::zeros(), &Matrix3::identity()).is_err());
    }

    #[test]
    fn log_likelihood_matches_the_gaussian_density() {
        let T = pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let lm = LandmarkEkf {
            mean_m: Vector3::new(2.0, 0.0, 0.0),
            cov_m2: Matrix3::identity() * 0.5,
            descriptor: None,
            hits: 1,
            last_seen_frame: 0,
            inverse_depth: None,
        };
        let inn = innovation(&T, &lm, &Vector3::new(3.0, 0.0, 0.0), &(Matrix3::identity() * 0.5)).unwrap();
        // S = I, ν = (1, 0, 0): ln N = −½(1 + 3 ln 2π).
        let expected = -0.5 * (1.0 + 3.0 * (2.0 * std::f64::consts::PI).ln());
        assert!((inn.log_likelihood() - expected).abs() < 1e-12);
        assert!((inn.mahalanobis - 1.0).abs() < 1e-12);
    }
}

//! What the filter takes and reports: observations, frame reports, timings, why a local map began.

#![allow(non_snake_case)]

use nalgebra::{Cholesky, Isometry3, Matrix3, Vector3};

use crate::ekf::{self, FilterError};

/// One observation of a frame, in the body frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Observation {
    /// Landmark position in the body frame, m.
    pub z_m: Vector3<f64>,
    /// Its covariance, m² (positive definite).
    pub Rz: Matrix3<f64>,
    /// Descriptor, if the source provides one.
    pub descriptor: Option<[u8; 32]>,
    /// The front end's feature track id, if the source provides one: the same id in two frames
    /// is the same landmark (association by attribute, [3D] §3.1).
    pub track_id: Option<u64>,
    /// The stereo measurement (normalised stereo coordinates in the camera frame and their
    /// covariance), when the observation comes from a stereo camera in front of it: the filter
    /// then compares landmarks with it in that space, where pixel noise is Gaussian at every
    /// depth (the triangulated point's depth is not, far away).
    pub stereo: Option<StereoMeasurement>,
}

/// A stereo observation in normalised stereo coordinates s = (x/z, y/z, 1/z) of the camera
/// frame ([`ekf::stereo_coords`]).
#[derive(Debug, Clone, PartialEq)]
pub struct StereoMeasurement {
    /// s.
    pub s: Vector3<f64>,
    /// Its covariance (first order from the camera-frame point's covariance).
    pub cov: Matrix3<f64>,
    /// The camera's mounting on the body.
    pub body_from_camera: Isometry3<f64>,
}

impl Observation {
    /// An observation from a camera-frame point and covariance and the `body_from_camera`
    /// extrinsic, with its stereo measurement when the point is in front of the camera; NaN/inf
    /// or a covariance that is not positive definite is an error.
    pub fn from_camera(
        point_cam_m: &Vector3<f64>,
        cov_cam_m2: &Matrix3<f64>,
        descriptor: Option<[u8; 32]>,
        body_from_camera: &Isometry3<f64>,
    ) -> Result<Self, FilterError> {
        if !(point_cam_m.iter().all(|v| v.is_finite()) && cov_cam_m2.iter().all(|v| v.is_finite())) {
            return Err(FilterError::NonFinite("observation"));
        }
        let R = body_from_camera.rotation.to_rotation_matrix().into_inner();
        let Rz = R * cov_cam_m2 * R.transpose();
        let Rz = (Rz + Rz.transpose()) * 0.5;
        if Cholesky::new(Rz).is_none() {
            return Err(FilterError::NotPositiveDefinite("observation covariance"));
        }
        let stereo = (point_cam_m.z > ekf::MIN_STEREO_DEPTH_M)
            .then(|| {
                let J = ekf::stereo_jacobian(point_cam_m);
                let cov = J * cov_cam_m2 * J.transpose();
                let cov = (cov + cov.transpose()) * 0.5;
                Cholesky::new(cov).map(|_| StereoMeasurement {
                    s: ekf::stereo_coords(point_cam_m),
                    cov,
                    body_from_camera: *body_from_camera,
                })
            })
            .flatten();
        Ok(Self {
            z_m: body_from_camera.transform_point(&(*point_cam_m).into()).coords,
            Rz,
            descriptor,
            track_id: None,
            stereo,
        })
    }
}

/// Why a new local map was started.
#[derive(Debug, Clone, PartialEq)]
pub enum SegmentReason {
    /// Fewer than m_l matched landmarks for several frames.
    FewMatches {
        /// Matched landmarks in the last frame.
        matched: usize,
        /// Weak frames in a row.
        frames: u32,
    },
    /// The position uncertainty grew beyond the threshold.
    PoseUncertainty {
        /// Largest position σ, m.
        sigma_m: f64,
    },
    /// Asked for from outside (e.g. fusion: camera and buoy estimates stopped overlapping).
    Requested,
}

impl std::fmt::Display for SegmentReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SegmentReason::FewMatches { matched, frames } => {
                write!(f, "only {matched} matched landmarks for {frames} frames")
            }
            SegmentReason::PoseUncertainty { sigma_m } => write!(f, "position σ {sigma_m:.2} m over the threshold"),
            SegmentReason::Requested => write!(f, "requested"),
        }
    }
}

/// What one frame did (for diagnostics).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameReport {
    /// Observations matched to confirmed landmarks (best particle).
    pub matched: usize,
    /// Observations that created landmarks (best particle).
    pub new: usize,
    /// Observations left out as possible duplicates (best particle).
    pub ambiguous: usize,
    /// Effective sample size before resampling.
    pub n_eff: f64,
    /// Whether the particles were resampled.
    pub resampled: bool,
    /// Confirmed landmarks in the best particle's map.
    pub landmarks: usize,
    /// The best particle's landmark id per observation (`None`: new or left out).
    pub associations: Vec<Option<u32>>,
    /// The first id this frame gave a new landmark (the next frame's first is after the last).
    pub first_new_id: u32,
    /// Per observation, the id of the landmark it created (in every particle that made it new;
    /// consecutive from `first_new_id` in observation order); `None` where no particle did.
    pub new_ids: Vec<Option<u32>>,
    /// Set when this frame started a new local map.
    pub new_segment: Option<SegmentReason>,
    /// Association candidates (landmarks looked up in each particle's map) per observation.
    pub candidates_per_observation: f64,
    /// Attribute (track id) matches left out because they failed the χ² gate (best particle).
    pub rejected: usize,
    /// Mean normalised innovation squared νᵀS⁻¹ν of the landmark updates of confirmed
    /// landmarks (best particle; ≈ 3 when consistent, a little less under the gate); NaN
    /// without updates.
    pub mean_nis: f64,
    /// Where the time of this update went.
    pub timing: FrameTiming,
}

/// Wall time of the phases of one [`FastSlam::update`], ms.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FrameTiming {
    /// Candidate landmarks per observation (grid, camera projection).
    pub candidates_ms: f64,
    /// Association, proposal and weights of every particle (parallel).
    pub weigh_ms: f64,
    /// Normalising and resampling.
    pub resample_ms: f64,
    /// Landmark EKF updates and new landmarks, once per surviving parent (parallel).
    pub update_ms: f64,
    /// The new particle set: copies of the parents, freeing the discarded ones, bookkeeping.
    pub copies_ms: f64,
    /// The whole update (with the estimate and the local-map checks).
    pub total_ms: f64,
}

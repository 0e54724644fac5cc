//! The stereo front end's settings and their checks.

use serde::{Deserialize, Serialize};
use validation::{Issues, Validate};

/// Settings of the stereo front end.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FrontEndConfig {
    /// χ²₃ gate on the normalised residual of a matched point (0.99 quantile: 11.34).
    pub inlier_chi2: f64,
    /// Fewest inliers of an accepted motion.
    pub min_inliers: usize,
    /// Fewest inliers as a fraction of the smaller frame's usable points (and of the nearer half
    /// of the previous frame's points).
    pub min_inlier_fraction: f64,
    /// Largest translation between two frames the prior-free search considers, m.
    pub max_translation_m: f64,
    /// Largest rotation between two frames the prior-free search considers, deg.
    pub max_rotation_deg: f64,
    /// Points whose position σ (√ of the covariance trace) is at most this seed the prior-free
    /// search, m (well-triangulated points make the rigidity test selective).
    pub search_max_sigma_m: f64,
    /// Base triples the prior-free search tries at most.
    pub search_trials: usize,
    /// Candidate triples per base triple at most.
    pub search_max_triples: usize,
    /// σ of the constant-velocity prior: change of the translation per frame, m.
    pub prior_translation_sigma_m: f64,
    /// σ of the constant-velocity prior: change of the rotation per frame, deg.
    pub prior_rotation_sigma_deg: f64,
    /// Huber threshold of the refinement, in σ of the normalised residual.
    pub huber_sigma: f64,
    /// RANSAC hypotheses at most.
    pub ransac_iterations: usize,
    /// Give observations without a track id the front end's own: the registration's inlier
    /// correspondences link a feature from frame to frame, so FastSLAM associates it by that
    /// attribute ([3D] §3.1) and needs maximum likelihood only for new features. Off: every
    /// observation without a source track id goes by maximum likelihood.
    pub assign_tracks: bool,
    /// With `assign_tracks`: frames a feature track may go unseen (the detector missed the
    /// feature, or the registration left it out) and still be continued when the feature is seen
    /// again, by its predicted position (0: a track ends when a frame misses it).
    pub bridge_gap_frames: u32,
    /// When no motion is found, FastSLAM predicts by constant velocity with this σ of the
    /// change of the linear velocity, m/s.
    pub fallback_velocity_sigma_mps: f64,
    /// ... and of the angular velocity, rad/s.
    pub fallback_angular_velocity_sigma_rps: f64,
    /// Seed of the sampling.
    pub seed: u64,
}

impl Default for FrontEndConfig {
    fn default() -> Self {
        Self {
            inlier_chi2: 11.34,
            min_inliers: 12,
            min_inlier_fraction: 0.25,
            max_translation_m: 2.5,
            max_rotation_deg: 15.0,
            search_max_sigma_m: 0.5,
            search_trials: 60,
            search_max_triples: 400,
            prior_translation_sigma_m: 0.15,
            prior_rotation_sigma_deg: 1.5,
            huber_sigma: 2.0,
            ransac_iterations: 200,
            assign_tracks: true,
            bridge_gap_frames: 2,
            fallback_velocity_sigma_mps: 2.0,
            fallback_angular_velocity_sigma_rps: 0.4,
            seed: 7,
        }
    }
}

impl Validate for FrontEndConfig {
    fn validate(&self, issues: &mut Issues) {
        let pos = |x: f64| x.is_finite() && x > 0.0;
        issues.check(pos(self.inlier_chi2), "inlier_chi2", "must be > 0");
        issues.check(self.min_inliers >= 3, "min_inliers", "must be >= 3");
        issues.check((0.0..=1.0).contains(&self.min_inlier_fraction), "min_inlier_fraction", "must be in [0, 1]");
        issues.check(pos(self.max_translation_m), "max_translation_m", "must be > 0");
        issues.check(
            pos(self.max_rotation_deg) && self.max_rotation_deg < 90.0,
            "max_rotation_deg",
            "must be in (0, 90)",
        );
        issues.check(pos(self.search_max_sigma_m), "search_max_sigma_m", "must be > 0");
        issues.check(self.search_trials >= 1, "search_trials", "must be >= 1");
        issues.check(self.search_max_triples >= 1, "search_max_triples", "must be >= 1");
        issues.check(pos(self.prior_translation_sigma_m), "prior_translation_sigma_m", "must be > 0");
        issues.check(pos(self.prior_rotation_sigma_deg), "prior_rotation_sigma_deg", "must be > 0");
        issues.check(pos(self.huber_sigma), "huber_sigma", "must be > 0");
        issues.check(self.ransac_iterations >= 1, "ransac_iterations", "must be >= 1");
        issues.check(self.bridge_gap_frames <= 30, "bridge_gap_frames", "must be at most 30");
        issues.check(pos(self.fallback_velocity_sigma_mps), "fallback_velocity_sigma_mps", "must be > 0");
        issues.check(
            pos(self.fallback_angular_velocity_sigma_rps),
            "fallback_angular_velocity_sigma_rps",
            "must be > 0",
        );
    }
}

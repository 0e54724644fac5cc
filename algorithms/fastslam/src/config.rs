//! Filter settings (the `[processes.<name>.settings]` of a `fastslam` process), with defaults
//! and a validation pass that names each bad key.

use serde::{Deserialize, Serialize};
use validation::{Issues, Validate};

/// Which proposal distribution samples the particle poses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Proposal {
    /// FastSLAM 1.0: poses from the motion model alone.
    Motion,
    /// FastSLAM 2.0: poses from the motion model conditioned on the frame's matched landmarks
    /// (the default: more accurate on the simulated mission and the stereo drive, and it keeps
    /// working when the sensor is more precise than the motion).
    #[default]
    Optimal,
}

/// Data association settings (EQUATIONS §3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AssociationConfig {
    /// χ²₃ gate of an accepted association (0.99 quantile: 11.34).
    pub gate_chi2: f64,
    /// Looser χ²₃ gate: an unmatched observation this close to a landmark creates no new one
    /// (guards against duplicates; 0.9999 quantile: 21.1).
    pub duplicate_gate_chi2: f64,
    /// Maximum likelihood: the best landmark's normalised innovation must be at least this much
    /// below the second best's (else the observation is left out as ambiguous).
    pub ml_margin_chi2: f64,
    /// Largest Hamming distance of a descriptor match.
    pub max_hamming: u32,
    /// Ratio test: best distance < ratio × second best.
    pub ratio: f64,
    /// Sightings before a provisional landmark counts (spurious detections are seen once).
    pub confirm_after: u32,
    /// A provisional landmark unseen for this many frames is dropped.
    pub provisional_max_age_frames: u32,
    /// Search radius around an observation for candidate landmarks, m.
    pub search_radius_m: f64,
}

impl Default for AssociationConfig {
    fn default() -> Self {
        Self {
            gate_chi2: 11.34,
            duplicate_gate_chi2: 21.1,
            ml_margin_chi2: 2.0,
            max_hamming: 64,
            ratio: 0.8,
            confirm_after: 2,
            provisional_max_age_frames: 5,
            search_radius_m: 3.0,
        }
    }
}

/// When to start a new local map (EQUATIONS §5, multi-map mechanism).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SegmentConfig {
    /// m_l: fewer matched landmarks than this in a frame counts as a weak frame.
    pub min_matched: usize,
    /// Weak frames in a row that start a new local map.
    pub weak_frames: u32,
    /// A position standard deviation (largest axis) above this starts a new local map, m.
    pub max_position_sigma_m: f64,
    /// Frames a local map lives at least before weak frames may end it. In a feature-scarce
    /// stretch a fresh map gets a few landmarks, loses them and would be replaced about once a
    /// second; maps that short cannot be placed in the world (fusion needs 3 or more buoy fixes
    /// inside a local map). The pose-uncertainty trigger and requests act at any age.
    pub min_frames: u32,
}

impl Default for SegmentConfig {
    fn default() -> Self {
        Self { min_matched: 3, weak_frames: 15, max_position_sigma_m: 3.0, min_frames: 75 }
    }
}

/// The filter's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FastSlamConfig {
    /// Number of particles N.
    pub particles: usize,
    /// Proposal distribution.
    pub proposal: Proposal,
    /// Resample when N_eff < this fraction of N.
    pub resample_fraction: f64,
    /// Additive process noise ω: position σ per √s, m/√s.
    pub process_position_sigma: f64,
    /// Additive process noise ω: rotation σ per √s, rad/√s.
    pub process_rotation_sigma: f64,
    /// Scales the input covariance carried by the odometry messages.
    pub input_noise_scale: f64,
    /// Scales the covariance of a relative motion from a front end (camera-only tracking); > 1
    /// widens it for errors the front end does not model (calibration, rolling shutter).
    pub relative_motion_noise_scale: f64,
    /// Drift of the reported pose covariance that no motion model accounts for, as a random walk
    /// over the distance travelled: position σ per √m, m/√m (0.005: 0.07 m after 200 m).
    pub drift_position_sigma_per_sqrt_m: f64,
    /// The same for the orientation, rad/√m.
    pub drift_rotation_sigma_per_sqrt_m: f64,
    /// Without odometry (constant-velocity model): σ of the change of the body's linear velocity
    /// between two frames, m/s; the displacement noise is this times the frame interval.
    pub cv_velocity_sigma_mps: f64,
    /// Without odometry: σ of the change of the angular velocity between two frames, rad/s.
    pub cv_angular_velocity_sigma_rps: f64,
    /// Data association.
    pub association: AssociationConfig,
    /// Local maps.
    pub segments: SegmentConfig,
    /// Threads for the particle updates (0 = every core; 1 = on the calling thread, no worker
    /// threads).
    pub threads: usize,
    /// Seed of the particle noise.
    pub seed: u64,
}

impl Default for FastSlamConfig {
    fn default() -> Self {
        Self {
            particles: 100,
            proposal: Proposal::Optimal,
            resample_fraction: 0.5,
            process_position_sigma: 0.02,
            process_rotation_sigma: 0.002,
            input_noise_scale: 1.0,
            relative_motion_noise_scale: 1.0,
            drift_position_sigma_per_sqrt_m: 0.005,
            drift_rotation_sigma_per_sqrt_m: 0.0,
            cv_velocity_sigma_mps: 1.0,
            cv_angular_velocity_sigma_rps: 0.1,
            association: AssociationConfig::default(),
            segments: SegmentConfig::default(),
            threads: 0,
            seed: 1,
        }
    }
}

impl Validate for FastSlamConfig {
    fn validate(&self, issues: &mut Issues) {
        let pos = |x: f64| x.is_finite() && x > 0.0;
        let nonneg = |x: f64| x.is_finite() && x >= 0.0;
        issues.check((1..=100_000).contains(&self.particles), "particles", "must be 1..=100000");
        issues.check(
            self.resample_fraction > 0.0 && self.resample_fraction <= 1.0,
            "resample_fraction",
            "must be in (0, 1]",
        );
        issues.check(nonneg(self.process_position_sigma), "process_position_sigma", "must be >= 0");
        issues.check(nonneg(self.process_rotation_sigma), "process_rotation_sigma", "must be >= 0");
        issues.check(nonneg(self.input_noise_scale), "input_noise_scale", "must be >= 0");
        issues.check(pos(self.relative_motion_noise_scale), "relative_motion_noise_scale", "must be > 0");
        issues.check(nonneg(self.drift_position_sigma_per_sqrt_m), "drift_position_sigma_per_sqrt_m", "must be >= 0");
        issues.check(nonneg(self.drift_rotation_sigma_per_sqrt_m), "drift_rotation_sigma_per_sqrt_m", "must be >= 0");
        issues.check(nonneg(self.cv_velocity_sigma_mps), "cv_velocity_sigma_mps", "must be >= 0");
        issues.check(nonneg(self.cv_angular_velocity_sigma_rps), "cv_angular_velocity_sigma_rps", "must be >= 0");
        let a = &self.association;
        issues.check(pos(a.gate_chi2), "association.gate_chi2", "must be > 0");
        issues.check(a.duplicate_gate_chi2 >= a.gate_chi2, "association.duplicate_gate_chi2", "must be >= gate_chi2");
        issues.check(a.ratio > 0.0 && a.ratio <= 1.0, "association.ratio", "must be in (0, 1]");
        issues.check(
            a.ml_margin_chi2.is_finite() && a.ml_margin_chi2 >= 0.0,
            "association.ml_margin_chi2",
            "must be >= 0",
        );
        issues.check(a.max_hamming <= 256, "association.max_hamming", "must be <= 256");
        issues.check(a.confirm_after >= 1, "association.confirm_after", "must be >= 1");
        issues.check(pos(a.search_radius_m), "association.search_radius_m", "must be > 0");
        issues.check(pos(self.segments.max_position_sigma_m), "segments.max_position_sigma_m", "must be > 0");
        issues.check(self.threads <= 256, "threads", "must be <= 256");
    }
}

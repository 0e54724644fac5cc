//! The filter's settings and the laser's geometry ([`GridSlamConfig`], [`ScanGeometry`],
//! [`MotionNoise`]), with their checks ([`Validate`]).

use crate::grid::LogOddsParams;
use crate::matcher::MatcherParams;
use omni::Pose2;
use validation::{Issues, Validate};

/// The laser's beam layout and mounting.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanGeometry {
    /// Angle of the first beam in the laser frame, rad (counter-clockwise from the laser's x).
    pub angle_min_rad: f64,
    /// Angle between consecutive beams, rad.
    pub angle_increment_rad: f64,
    /// Beams per scan.
    pub beams: usize,
    /// Ranges below this are invalid, m.
    pub range_min_m: f64,
    /// Ranges at or above this are "no return", m.
    pub range_max_m: f64,
    /// The laser's pose on the robot (`body_from_laser`).
    pub body_from_laser: Pose2,
}

/// Odometry noise of the holonomic motion model: the std devs of a body-frame increment
/// (dx, dy, dθ) grow with the motion (dx and dy alike: the base strafes).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionNoise {
    /// Translation std dev per metre of translation (gmapping's srr).
    pub srr: f64,
    /// Translation std dev (m) per radian of rotation (srt).
    pub srt: f64,
    /// Rotation std dev (rad) per metre of translation (str).
    pub str_: f64,
    /// Rotation std dev per radian of rotation (stt).
    pub stt: f64,
    /// Floor of the translation std dev, m.
    pub min_sd_m: f64,
    /// Floor of the rotation std dev, rad.
    pub min_sd_rad: f64,
}

impl Default for MotionNoise {
    fn default() -> Self {
        Self { srr: 0.1, srt: 0.1, str_: 0.1, stt: 0.1, min_sd_m: 0.01, min_sd_rad: 0.005 }
    }
}

impl MotionNoise {
    /// Std devs (x, y, θ) of the increment `d`.
    pub fn sd(&self, d: &Pose2) -> [f64; 3] {
        let rot = d.theta_rad.abs();
        let trans = d.x_m.hypot(d.y_m);
        [
            self.srr * d.x_m.abs() + self.srt * rot + self.min_sd_m,
            self.srr * d.y_m.abs() + self.srt * rot + self.min_sd_m,
            self.str_ * trans + self.stt * rot + self.min_sd_rad,
        ]
    }
}

/// Where the improved proposal's lattice (3 × 3 × 3 poses round the match, Grisetti et al.
/// 2007 §IV) takes its likelihoods from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProposalLikelihood {
    /// Evaluated at each pose of the lattice (the 27 computed together: a beam's cells read
    /// once per rotation).
    Evaluated,
    /// From the log-likelihood's Gauss-Newton model at the match (its gradient and curvature
    /// from the matcher's last linearisation: no evaluation; the beams keep the surfaces they
    /// matched at the match).
    Modelled,
}

/// Filter settings (defaults: gmapping's, with 30 particles at 0.05 m).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridSlamConfig {
    /// Particles.
    pub particles: usize,
    /// Grid cell side, m.
    pub resolution_m: f64,
    /// Beams are used (matched, and written as hits) up to this range; longer ones free space up
    /// to it (gmapping's maxUrange), m.
    pub usable_range_m: f64,
    /// A beam with no return (at or beyond the laser's maximum: raw logs write the maximum, e.g.
    /// 81.83 m for a SICK LMS) never adds a hit; it frees the cells along it up to this range, m
    /// (0: not at all; never beyond `usable_range_m`). 0 by default: such beams leave through
    /// windows, doors and glass, and freeing them up to the usable range painted large fans of
    /// "free" outside the building (on fr079 they tripled the map's area and the particles'
    /// memory).
    pub no_return_free_m: f64,
    /// A filter update after this much translation since the last one, m.
    pub linear_update_m: f64,
    /// ... or this much rotation, rad.
    pub angular_update_rad: f64,
    /// Resample when N_eff < this × N.
    pub resample_threshold: f64,
    /// Weights are tempered by 1/(obs_gain·N) before normalising (gmapping's ogain), because the
    /// beams of a scan are not independent. gmapping's 3.0 tempers so hard (1/90 with 30
    /// particles) that the particles are almost never resampled (6 times in 1,121 updates on
    /// fr079), their lineages never merge and each particle ends up with a private copy of most
    /// of the map (25× one map). 0.03 (1/0.9 with 30 particles, with the matcher's likelihood
    /// σ of 0.075 m) resamples at about 2 updates in 3, keeps the maps shared (fr079: peak 2.2×
    /// one map, with the tiles written alike shared after each update) and is as accurate
    /// (fr079 0.0456 m against 0.0446 m at 0.05, which peaks at 3.4×; indoor mission: mean ATE
    /// 0.037 m over 8 runs against 0.039 m).
    pub obs_gain: f64,
    /// Spacing of the points sampled around the match to fit the proposal, m.
    pub proposal_step_m: f64,
    /// ... and rad.
    pub proposal_step_rad: f64,
    /// Where the likelihoods of the proposal's lattice come from: evaluated at each of its 27
    /// poses (`"evaluated"`, the default), or from the log-likelihood's quadratic model at the
    /// match (`"modelled"`: fr079 under the supervisor in 0.78× the wall time, the same scores
    /// within the runs' spread; not the default yet: docs/grid_slam.md, "The proposal's
    /// likelihood from the matcher's model").
    pub proposal_likelihood: ProposalLikelihood,
    /// Floor of the proposal's std dev, m.
    pub proposal_min_sd_m: f64,
    /// ... and rad.
    pub proposal_min_sd_rad: f64,
    /// Scan matcher.
    pub matcher: MatcherParams,
    /// Motion model.
    pub motion: MotionNoise,
    /// Map updates.
    pub log_odds: LogOddsParams,
    /// Worker threads for the particles (0: all cores).
    pub threads: usize,
    /// Random seed.
    pub seed: u64,
}

impl Default for GridSlamConfig {
    fn default() -> Self {
        Self {
            particles: 30,
            resolution_m: 0.05,
            usable_range_m: 15.0,
            no_return_free_m: 0.0,
            linear_update_m: 0.5,
            angular_update_rad: 0.25,
            resample_threshold: 0.5,
            obs_gain: 0.03,
            proposal_step_m: 0.02,
            proposal_step_rad: 0.01,
            proposal_likelihood: ProposalLikelihood::Evaluated,
            proposal_min_sd_m: 0.005,
            proposal_min_sd_rad: 0.002,
            matcher: MatcherParams::default(),
            motion: MotionNoise::default(),
            log_odds: LogOddsParams::default(),
            threads: 0,
            seed: 1,
        }
    }
}

impl Validate for GridSlamConfig {
    fn validate(&self, issues: &mut Issues) {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        issues.check(self.particles != 0, "particles", "must be at least 1");
        for (key, v) in [
            ("resolution_m", self.resolution_m),
            ("usable_range_m", self.usable_range_m),
            ("linear_update_m", self.linear_update_m),
            ("angular_update_rad", self.angular_update_rad),
            ("obs_gain", self.obs_gain),
            ("proposal_step_m", self.proposal_step_m),
            ("proposal_step_rad", self.proposal_step_rad),
            ("proposal_min_sd_m", self.proposal_min_sd_m),
            ("proposal_min_sd_rad", self.proposal_min_sd_rad),
            ("matcher.score_sigma_m", self.matcher.score_sigma_m),
            ("matcher.likelihood_sigma_m", self.matcher.likelihood_sigma_m),
            ("matcher.linear_step_m", self.matcher.linear_step_m),
            ("matcher.angular_step_rad", self.matcher.angular_step_rad),
        ] {
            issues.check(pos(v), key, format!("must be a positive number, got {v}"));
        }
        issues.check(
            self.no_return_free_m.is_finite() && self.no_return_free_m >= 0.0,
            "no_return_free_m",
            "must be >= 0 (0: no-return beams free nothing)",
        );
        issues.check(
            self.resample_threshold >= 0.0 && self.resample_threshold <= 1.0,
            "resample_threshold",
            "must be within [0, 1]",
        );
        issues.check(self.matcher.beam_stride != 0, "matcher.beam_stride", "must be at least 1");
        issues.check(
            self.matcher.min_point_spacing_m.is_finite() && self.matcher.min_point_spacing_m >= 0.0,
            "matcher.min_point_spacing_m",
            "must be a finite distance ≥ 0",
        );
        issues.check(
            self.matcher.coarse_stride != 0,
            "matcher.coarse_stride",
            "must be at least 1 (1: every point at every step size)",
        );
        issues.check(
            self.matcher.coarse_refinements <= self.matcher.refinements,
            "matcher.coarse_refinements",
            "must be at most matcher.refinements",
        );
        issues.check((0..=3).contains(&self.matcher.kernel_cells), "matcher.kernel_cells", "must be 0..=3");
        let m = &self.motion;
        for (key, v) in [("motion.srr", m.srr), ("motion.srt", m.srt), ("motion.str_", m.str_), ("motion.stt", m.stt)] {
            issues.check(v.is_finite() && v >= 0.0, key, "must be a non-negative number");
        }
        issues.check(pos(m.min_sd_m) && pos(m.min_sd_rad), "motion.min_sd_m", "the floors must be positive");
        let l = &self.log_odds;
        issues.check(
            l.hit > 0.0 && l.miss < 0.0 && l.min < 0.0 && l.max > 0.0,
            "log_odds",
            "hit and max must be positive, miss and min negative",
        );
    }
}

impl Validate for ScanGeometry {
    fn validate(&self, issues: &mut Issues) {
        issues.check(self.beams >= 2, "laser.beams", "needs at least 2 beams");
        issues.check(
            self.angle_min_rad.is_finite() && self.angle_increment_rad.is_finite() && self.angle_increment_rad != 0.0,
            "laser.angle_increment_rad",
            "angles must be finite and the increment non-zero",
        );
        issues.check(
            self.range_min_m.is_finite() && self.range_min_m >= 0.0 && self.range_max_m > self.range_min_m,
            "laser.range_max_m",
            "needs 0 <= range_min_m < range_max_m",
        );
    }
}

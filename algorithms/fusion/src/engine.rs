//! The fusion engine ([3D] Alg 3, EQUATIONS §5.2 and §6): local maps (segments) of the SLAM
//! process, each with its local path, the buoy fixes of its time span, and its transform to the
//! world; the fused global pose per SLAM pose; the request for a new local map when camera and
//! buoy estimates stop overlapping; and at the end the globally consistent path and map.
//!
//! Per segment:
//! 1. The SLAM poses (local map frame) of the segment are its local path; a cubic B-spline
//!    through them ([`crate::bspline`]) is evaluated at each buoy fix time inside the segment
//!    (§6.1-6.2), giving correspondences (local position, world position) with covariances.
//! 2. With `align.min_pairs` correspondences that are not collinear, the transform
//!    `world_from_local` follows by weighted SVD ([`crate::align`], §6.3). It is re-estimated
//!    whenever the number of fixes inside the segment's span changes, so it is refined as the
//!    segment grows. Collinear or too small geometry is reported ([`SegmentStatus`]); with
//!    heading readings (a compass, [`Fusion::push_heading`]) inside the segment it is resolved
//!    ([`crate::align::align_with_heading`]: the local frame's yaw in the world is the compass yaw
//!    minus the SLAM body yaw in the local frame, averaged over the segment; the local frame is
//!    taken as level), else the segment waits.
//! 3. Each SLAM pose is mapped to the world (position with the transform's uncertainty, §6.5)
//!    and fused with the buoy position synchronised to its stamp (eq 31-32) when the two
//!    overlap under the χ²₃ gate (`gate_probability`). After `no_overlap_frames` poses in a row
//!    outside the gate the engine asks for a new local map (once per segment).
//!
//! At the end ([`Fusion::finish`]) every segment is aligned once more with all its fixes and its
//! whole path mapped and fused again: the globally consistent path (the live output could only
//! use the fixes up to each pose). The segments' landmark maps go into one global map
//! ([`crate::global_map`], eq 38).

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::FusionError;
use crate::align::{
    AlignConfig, Alignment, Correspondence, PRIOR_GATE_CHI2_6, align, align_with_heading, align_with_prior,
    compose_prior,
};
use crate::bspline::{LocalPathSpline, PathSample};
use crate::correlation::FixCorrelation;
use crate::fuse::{CorrelatedErrors, FuseOutcome, chi2_3_quantile, fuse, fuse_correlated};
use crate::global_map::{GlobalLandmark, MapLandmark, MergeConfig, build_global_map};
use validation::{ConfigIssue, Issues, Validate};

/// Settings of the engine.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionConfig {
    /// Transform estimation.
    pub align: AlignConfig,
    /// Probability of the χ²₃ overlap gate between the camera and buoy estimates.
    pub gate_probability: f64,
    /// Poses in a row outside the gate (with a transform) before a new local map is requested;
    /// 0 never requests one.
    pub no_overlap_frames: u32,
    /// Merging landmarks of different segments in the global map.
    pub merge: MergeConfig,
    /// Resolve collinear segments with heading readings when there are any.
    pub use_heading: bool,
    /// The final path aligns each pose with the fixes within this many seconds of it (in its
    /// segment; at least 7) instead of with all of the segment's: the local path drifts, and a
    /// transform fitted where the pose is removes that drift (0 = the segment's transform only).
    /// A window whose path is too straight for a rotation keeps the segment's rotation and
    /// re-estimates the translation alone.
    pub local_window_s: f64,
    /// A new local map starts where the SLAM body was (its frame is the body frame at that
    /// instant): when its first pose follows the previous local map's last within this many
    /// seconds, its transform starts as the previous one composed with that pose (extrapolated
    /// to the new map's first stamp), with both covariances, and the buoy fixes refine it as a
    /// prior ([`crate::align::align_with_prior`]) instead of the transform waiting for fixes
    /// and then resting on the first few alone. 0 = off.
    pub handover_max_gap_s: f64,
    /// σ of the roll and pitch of a local map's frame about level, deg, where the transform's
    /// rotation comes from the compass (a local map without a handover, with heading readings):
    /// the frame is the body frame where the map started, and a vehicle trimmed level starts
    /// within a few degrees of it. Its yaw's σ is the compass's own, not shrunk by averaging
    /// (a compass's deviation is correlated in time).
    pub level_sigma_deg: f64,
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            align: AlignConfig::default(),
            gate_probability: 0.99,
            no_overlap_frames: 15,
            merge: MergeConfig::default(),
            use_heading: true,
            local_window_s: 10.0,
            handover_max_gap_s: 1.0,
            level_sigma_deg: 5.0,
        }
    }
}

impl Validate for FusionConfig {
    fn validate(&self, issues: &mut Issues) {
        issues.nested("align", &self.align);
        issues.nested("merge", &self.merge);
        if !(self.gate_probability > 0.0 && self.gate_probability < 1.0) {
            issues.push("gate_probability", "must be in (0, 1)");
        }
        if !(self.local_window_s.is_finite() && self.local_window_s >= 0.0) {
            issues.push("local_window_s", "must be >= 0 (0 = off)");
        }
        if !(self.handover_max_gap_s.is_finite() && self.handover_max_gap_s >= 0.0) {
            issues.push("handover_max_gap_s", "must be >= 0 (0 = off)");
        }
        if !(self.level_sigma_deg.is_finite() && self.level_sigma_deg > 0.0 && self.level_sigma_deg <= 90.0) {
            issues.push("level_sigma_deg", "must be in (0, 90]");
        }
    }
}

/// A SLAM pose with the buoy position synchronised to its stamp (a `SyncedPair`).
#[derive(Debug, Clone, PartialEq)]
pub struct PairInput {
    /// Stamp, s.
    pub t_s: f64,
    /// Local map (segment) of the pose.
    pub segment: u32,
    /// The SLAM pose `local_from_body`.
    pub local_from_body: Isometry3<f64>,
    /// Its 6×6 covariance over (position, body-frame rotation error), m², rad².
    pub local_covariance: Matrix6<f64>,
    /// Buoy position at the stamp, world frame, m.
    pub buoy_m: Vector3<f64>,
    /// Its covariance, m².
    pub buoy_cov_m2: Matrix3<f64>,
}

/// A buoy fix (a `BuoyFix`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FixInput {
    /// Stamp, s.
    pub t_s: f64,
    /// Position, world frame, m.
    pub position_m: Vector3<f64>,
    /// Its covariance, m².
    pub covariance_m2: Matrix3<f64>,
}

/// A heading reading (compass): yaw of body x in the world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadingInput {
    /// Stamp, s.
    pub t_s: f64,
    /// Yaw, rad.
    pub yaw_rad: f64,
    /// σ, rad.
    pub sigma_rad: f64,
}

/// Where a fused pose came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    /// Camera (mapped to the world) and buoy fused.
    Fused,
    /// The camera alone: the buoy estimate was outside the gate.
    CameraOnly,
    /// The buoy alone: the segment has no transform yet.
    BuoyOnly,
}

/// A global pose.
#[derive(Debug, Clone, PartialEq)]
pub struct FusedOutput {
    /// Stamp, s.
    pub t_s: f64,
    /// Segment of the SLAM pose.
    pub segment: u32,
    /// `world_from_body`.
    pub world_from_body: Isometry3<f64>,
    /// 6×6 covariance over (position, body-frame rotation error).
    pub covariance: Matrix6<f64>,
    /// How it was made.
    pub source: Source,
    /// (X_c − X_b)ᵀ(P_b + P_c)⁻¹(X_c − X_b), when a transform exists.
    pub mahalanobis: Option<f64>,
    /// Set once per segment: camera and buoy stopped overlapping; start a new local map.
    pub request_new_segment: bool,
    /// Set when the segment's transform changed with this pose (status in [`Fusion::segment`]).
    pub realigned: bool,
}

/// The state of a segment's transform.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SegmentStatus {
    /// Not enough fixes inside the segment yet.
    WaitingForFixes {
        /// Fixes inside the segment's span.
        fixes: usize,
    },
    /// The correspondences are (nearly) collinear or too small: the rotation is unobservable.
    Degenerate {
        /// Why.
        reason: String,
    },
    /// Aligned.
    Aligned,
    /// The correspondences were degenerate; the rotation came from the heading readings.
    AlignedWithHeading {
        /// Heading readings used.
        readings: usize,
    },
    /// The previous local map's transform carried over to where this one starts, refined by the
    /// fixes inside this one ([`FusionConfig::handover_max_gap_s`]).
    AlignedWithPrior {
        /// Fixes used.
        fixes: usize,
    },
}

/// Where a local map started in the one before it ([`FusionConfig::handover_max_gap_s`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Handover {
    /// The previous local map.
    pub from: u32,
    /// The new map's origin in the previous map's frame (`previous_from_local`).
    pub previous_from_local: Isometry3<f64>,
    /// Its 6×6 covariance over (position, body-frame rotation error).
    pub covariance: Matrix6<f64>,
}

/// One local map.
#[derive(Debug, Clone)]
pub struct Segment {
    /// Segment id.
    pub id: u32,
    /// The local path (SLAM positions in the local map frame).
    pub samples: Vec<PathSample>,
    /// Every pose of the segment, for the final path.
    pub pairs: Vec<PairInput>,
    /// The transform `world_from_local`, once estimated.
    pub alignment: Option<Alignment>,
    /// Its state.
    pub status: SegmentStatus,
    /// The segment's latest landmark map (local frame).
    pub landmarks: Vec<MapLandmark>,
    /// World-frame covariance of the local path's errors that its own covariance does not
    /// explain (drift, an optimistic SLAM covariance), estimated from the alignment residuals
    /// (see [`excess_covariance`]) and added to every mapped camera estimate, m².
    pub excess_cov_m2: Matrix3<f64>,
    /// Where this local map started in the previous one, when it followed it closely enough.
    pub handover: Option<Handover>,
    /// The fixes disagreed with the handover's prior (χ²₆ above 0.999), so the transform rests
    /// on the fixes alone.
    pub prior_rejected: bool,
    /// The residuals g − T·l of its transform at its fixes, in time order (for the fixes'
    /// correlation during the run).
    residuals: Vec<Vector3<f64>>,
    fixes_used: usize,
    no_overlap: u32,
    requested: bool,
}

impl Segment {
    fn new(id: u32) -> Self {
        Self {
            id,
            samples: vec![],
            pairs: vec![],
            alignment: None,
            status: SegmentStatus::WaitingForFixes { fixes: 0 },
            landmarks: vec![],
            excess_cov_m2: Matrix3::zeros(),
            handover: None,
            prior_rejected: false,
            residuals: vec![],
            fixes_used: 0,
            no_overlap: 0,
            requested: false,
        }
    }
}

/// The engine.
pub struct Fusion {
    cfg: FusionConfig,
    gate_chi2: f64,
    segments: BTreeMap<u32, Segment>,
    /// Buoy fixes sorted by time.
    fixes: Vec<FixInput>,
    /// Heading readings sorted by time.
    headings: Vec<HeadingInput>,
    last_orientation: Option<UnitQuaternion<f64>>,
    /// The fixes' error autocorrelation from the local maps' residuals so far (docs/EQUATIONS.md
    /// §5.3), for the live poses; re-estimated whenever a local map's transform changes.
    live_correlation: FixCorrelation,
}

/// The end-of-run result.
#[derive(Debug, Clone)]
pub struct FinalResult {
    /// The globally consistent path: every pose with the final transforms.
    pub path: Vec<FusedOutput>,
    /// The SLAM path mapped to the world by the final transforms (camera only, the local ones
    /// where there are), where aligned.
    pub slam_world: Vec<(f64, Isometry3<f64>)>,
    /// The global landmark map.
    pub global_map: Vec<GlobalLandmark>,
    /// The buoy fixes' error autocorrelation the final path's covariances account for.
    pub fix_correlation: FixCorrelation,
}

fn finite3(v: &Vector3<f64>) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// Rotation-error covariance of a world orientation `R_a·R_l` (body frame) from the transform's
/// rotation covariance (world side, R = Exp(φ)·R̂).
fn body_rotation_cov(world_from_body: &UnitQuaternion<f64>, transform_rot_cov: &Matrix3<f64>) -> Matrix3<f64> {
    let r = world_from_body.to_rotation_matrix().into_inner();
    r.transpose() * transform_rot_cov * r
}

impl Fusion {
    /// A new engine; the configuration must validate.
    pub fn new(cfg: FusionConfig) -> Result<Self, Vec<ConfigIssue>> {
        cfg.issues().into_result()?;
        let gate_chi2 = chi2_3_quantile(cfg.gate_probability).ok_or_else(|| {
            vec![ConfigIssue { key: "gate_probability".into(), message: "no χ²₃ quantile for it".into() }]
        })?;
        Ok(Self {
            cfg,
            gate_chi2,
            segments: BTreeMap::new(),
            fixes: vec![],
            headings: vec![],
            last_orientation: None,
            live_correlation: FixCorrelation::default(),
        })
    }

    /// The settings.
    pub fn config(&self) -> &FusionConfig {
        &self.cfg
    }

    /// The segments seen so far.
    pub fn segments(&self) -> impl Iterator<Item = &Segment> {
        self.segments.values()
    }

    /// One segment.
    pub fn segment(&self, id: u32) -> Option<&Segment> {
        self.segments.get(&id)
    }

    /// The buoy fixes received.
    pub fn fixes(&self) -> &[FixInput] {
        &self.fixes
    }

    /// Adds a buoy fix (kept in time order).
    pub fn push_fix(&mut self, fix: FixInput) -> Result<(), FusionError> {
        if !(fix.t_s.is_finite() && finite3(&fix.position_m) && fix.covariance_m2.iter().all(|v| v.is_finite())) {
            return Err(FusionError::NonFinite("buoy fix"));
        }
        let i = self.fixes.partition_point(|f| f.t_s <= fix.t_s);
        if i > 0 && self.fixes[i - 1].t_s == fix.t_s {
            self.fixes[i - 1] = fix; // a re-published stamp: the later estimate
        } else {
            self.fixes.insert(i, fix);
        }
        Ok(())
    }

    /// Adds a heading reading (kept in time order).
    pub fn push_heading(&mut self, h: HeadingInput) -> Result<(), FusionError> {
        if !(h.t_s.is_finite() && h.yaw_rad.is_finite() && h.sigma_rad.is_finite() && h.sigma_rad > 0.0) {
            return Err(FusionError::NonFinite("heading reading"));
        }
        let i = self.headings.partition_point(|x| x.t_s <= h.t_s);
        self.headings.insert(i, h);
        Ok(())
    }

    /// Heading readings inside [from, to].
    fn headings_between(&self, from_s: f64, to_s: f64) -> &[HeadingInput] {
        let a = self.headings.partition_point(|h| h.t_s < from_s);
        let b = self.headings.partition_point(|h| h.t_s <= to_s);
        &self.headings[a..b.max(a)]
    }

    /// Replaces a segment's landmark map (local frame).
    pub fn set_landmarks(&mut self, segment: u32, landmarks: Vec<MapLandmark>) {
        self.segments.entry(segment).or_insert_with(|| Segment::new(segment)).landmarks = landmarks;
    }

    /// Fixes inside [from, to].
    fn fixes_between(&self, from_s: f64, to_s: f64) -> &[FixInput] {
        let a = self.fixes.partition_point(|f| f.t_s < from_s);
        let b = self.fixes.partition_point(|f| f.t_s <= to_s);
        &self.fixes[a..b.max(a)]
    }

    /// Re-estimates a segment's transform from all fixes inside its span (§6.1-6.3), from
    /// `prior` (the handover's) when there is one.
    fn realign(
        fcfg: &FusionConfig,
        seg: &mut Segment,
        fixes: &[FixInput],
        headings: &[HeadingInput],
        handover: Option<&Alignment>,
    ) {
        let cfg = &fcfg.align;
        seg.fixes_used = fixes.len();
        // The prior: the handover's, else the compass's yaw about a level frame (with a fix
        // at least: it says nothing of the translation).
        let prior = match handover {
            Some(h) => Some((*h, None)),
            None if fcfg.use_heading && !fixes.is_empty() => Self::local_frame_yaw_prior(seg, headings)
                .map(|(yaw, sigma, n)| (Self::heading_prior(yaw, sigma, fcfg.level_sigma_deg.to_radians()), Some(n))),
            None => None,
        };
        if let Some((prior, readings)) = prior
            && !seg.prior_rejected
        {
            let pairs = Self::correspondences(seg, fixes);
            match align_with_prior(&pairs, &prior) {
                Ok((a, chi2))
                    if (chi2 <= PRIOR_GATE_CHI2_6 || pairs.len() < cfg.min_pairs.max(3))
                        && (readings.is_none() || !pairs.is_empty()) =>
                {
                    seg.excess_cov_m2 = excess_covariance(&a, &pairs);
                    seg.residuals = residuals_of(&a, &pairs);
                    seg.alignment = Some(a);
                    seg.status = match readings {
                        None => SegmentStatus::AlignedWithPrior { fixes: pairs.len() },
                        Some(readings) => SegmentStatus::AlignedWithHeading { readings },
                    };
                    return;
                }
                Ok(_) if pairs.is_empty() => {}
                // The fixes disagree with the prior (or it is unusable): they decide alone.
                _ => {
                    seg.prior_rejected = true;
                    seg.alignment = None;
                }
            }
        }
        if fixes.len() < cfg.min_pairs.max(1) || seg.samples.len() < 2 {
            if seg.alignment.is_none() {
                seg.status = SegmentStatus::WaitingForFixes { fixes: fixes.len() };
            }
            return;
        }
        let spline = match LocalPathSpline::fit(&seg.samples) {
            Ok(s) => s,
            Err(e) => {
                seg.status = SegmentStatus::Degenerate { reason: format!("local path: {e}") };
                return;
            }
        };
        let pairs = Self::pairs_on(&spline, fixes);
        match align(&pairs, cfg) {
            Ok(a) => {
                seg.excess_cov_m2 = excess_covariance(&a, &pairs);
                seg.residuals = residuals_of(&a, &pairs);
                seg.alignment = Some(a);
                seg.status = SegmentStatus::Aligned;
            }
            Err(FusionError::TooFew { got, .. }) if seg.alignment.is_none() => {
                seg.status = SegmentStatus::WaitingForFixes { fixes: got };
            }
            Err(e) => {
                // Degenerate geometry: the heading readings give the rotation, if there are any.
                if let Some((yaw, sigma, n)) = Self::local_frame_yaw(seg, headings)
                    && let Ok(a) = align_with_heading(&pairs, yaw, sigma)
                {
                    seg.excess_cov_m2 = excess_covariance(&a, &pairs);
                    seg.residuals = residuals_of(&a, &pairs);
                    seg.alignment = Some(a);
                    seg.status = SegmentStatus::AlignedWithHeading { readings: n };
                } else if seg.alignment.is_none() {
                    // Keep an earlier transform if there is one (it was estimated from a subset).
                    seg.status = SegmentStatus::Degenerate { reason: e.to_string() };
                }
            }
        }
    }

    /// The prior of a transform whose rotation is the compass's: yaw `yaw_rad` (σ `yaw_sigma_rad`)
    /// about a level frame (roll and pitch σ `level_sigma_rad`), the translation unknown (σ 1 km).
    fn heading_prior(yaw_rad: f64, yaw_sigma_rad: f64, level_sigma_rad: f64) -> Alignment {
        let mut cov = Matrix6::zeros();
        for i in 0..3 {
            cov[(i, i)] = 1e6;
        }
        cov[(3, 3)] = level_sigma_rad * level_sigma_rad;
        cov[(4, 4)] = level_sigma_rad * level_sigma_rad;
        cov[(5, 5)] = yaw_sigma_rad * yaw_sigma_rad;
        Alignment::from_transform(
            Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_rad)),
            cov,
        )
    }

    /// The fixes paired with the segment's local path (its B-spline at their stamps); none while
    /// the path has fewer than two samples.
    fn correspondences(seg: &Segment, fixes: &[FixInput]) -> Vec<Correspondence> {
        match LocalPathSpline::fit(&seg.samples) {
            Ok(spline) if seg.samples.len() >= 2 => Self::pairs_on(&spline, fixes),
            _ => vec![],
        }
    }

    fn pairs_on(spline: &LocalPathSpline, fixes: &[FixInput]) -> Vec<Correspondence> {
        fixes
            .iter()
            .filter_map(|f| {
                let (local_m, local_cov_m2) = spline.evaluate(f.t_s).ok()?;
                Some(Correspondence {
                    local_m,
                    local_cov_m2: drift_free(&local_cov_m2),
                    global_m: f.position_m,
                    global_cov_m2: f.covariance_m2,
                })
            })
            .collect()
    }

    /// The prior a local map's transform started from (its handover's: the previous local map's
    /// current transform composed with where this one started in it), if it had one.
    pub fn handover_prior_of(&self, segment: u32) -> Option<Alignment> {
        self.handover_prior(self.segments.get(&segment)?)
    }

    /// The prior of a segment's transform from its handover: the previous local map's current
    /// transform composed with where this one started in it.
    fn handover_prior(&self, seg: &Segment) -> Option<Alignment> {
        let h = seg.handover.as_ref()?;
        let prev = self.segments.get(&h.from)?;
        let a = prev.alignment.as_ref()?;
        let mut cov = h.covariance;
        let extra = prev.excess_cov_m2;
        cov.fixed_view_mut::<3, 3>(0, 0).zip_apply(&extra, |c, e| *c += e);
        Some(compose_prior(a, &h.previous_from_local, &cov))
    }

    /// The handover of a local map whose first pose is `first`: where it started in the local
    /// map seen last before it, extrapolated from that map's last two poses to `first`'s stamp
    /// (the new map's frame is the body frame at that stamp). `None` when there is no such map,
    /// or the gap is wider than [`FusionConfig::handover_max_gap_s`].
    fn handover_for(&self, first: &PairInput) -> Option<Handover> {
        let max_gap = self.cfg.handover_max_gap_s;
        if max_gap <= 0.0 {
            return None;
        }
        let prev = self
            .segments
            .values()
            .filter(|s| s.id != first.segment && s.pairs.last().is_some_and(|p| p.t_s < first.t_s))
            .max_by(|a, b| a.pairs[a.pairs.len() - 1].t_s.total_cmp(&b.pairs[b.pairs.len() - 1].t_s))?;
        let last = prev.pairs.last()?;
        if first.t_s - last.t_s > max_gap {
            return None;
        }
        // Constant velocity over the gap, from the two last poses; its error taken as a quarter
        // of the step (σ), at least 1 cm and 1 mrad.
        let mut pose = last.local_from_body;
        let (mut sigma_p, mut sigma_r) = (0.01, 1e-3);
        if let Some(before) = prev.pairs.len().checked_sub(2).map(|i| &prev.pairs[i])
            && last.t_s > before.t_s
        {
            let step = before.local_from_body.inverse() * last.local_from_body;
            let k = (first.t_s - last.t_s) / (last.t_s - before.t_s);
            let scaled = Isometry3::from_parts(
                Translation3::from(step.translation.vector * k),
                UnitQuaternion::from_scaled_axis(step.rotation.scaled_axis() * k),
            );
            pose *= scaled;
            sigma_p = (0.25 * scaled.translation.vector.norm()).max(sigma_p);
            sigma_r = (0.25 * scaled.rotation.angle()).max(sigma_r);
        }
        let mut covariance = last.local_covariance;
        for i in 0..3 {
            covariance[(i, i)] += sigma_p * sigma_p;
            covariance[(3 + i, 3 + i)] += sigma_r * sigma_r;
        }
        Some(Handover { from: prev.id, previous_from_local: pose, covariance })
    }

    /// The yaw of the segment's local frame in the world from heading readings: compass yaw
    /// minus the SLAM body yaw in the local frame at the same time (nearest pose), averaged on
    /// the circle; σ from the readings' σ and their scatter, over √n.
    fn local_frame_yaw(seg: &Segment, headings: &[HeadingInput]) -> Option<(f64, f64, usize)> {
        if headings.is_empty() || seg.pairs.is_empty() {
            return None;
        }
        let (mut c, mut s, mut var) = (0.0, 0.0, 0.0);
        for h in headings {
            let i = seg.pairs.partition_point(|p| p.t_s < h.t_s).min(seg.pairs.len() - 1);
            let j = if i > 0 && (seg.pairs[i - 1].t_s - h.t_s).abs() < (seg.pairs[i].t_s - h.t_s).abs() {
                i - 1
            } else {
                i
            };
            let x = seg.pairs[j].local_from_body.rotation * Vector3::x();
            let body_yaw = x.y.atan2(x.x);
            let d = h.yaw_rad - body_yaw;
            c += d.cos();
            s += d.sin();
            var += h.sigma_rad * h.sigma_rad;
        }
        let n = headings.len() as f64;
        let r = (c * c + s * s).sqrt() / n; // mean resultant length
        let scatter = (-2.0 * r.max(1e-12).ln()).max(0.0); // circular variance
        let sigma = ((var / n).max(scatter) / n).sqrt();
        Some((s.atan2(c), sigma.max(1e-4), headings.len()))
    }

    /// [`Fusion::local_frame_yaw`] with σ no smaller than one reading's: for a prior that stands
    /// for the whole local map, whose compass errors are not independent over it.
    fn local_frame_yaw_prior(seg: &Segment, headings: &[HeadingInput]) -> Option<(f64, f64, usize)> {
        let (yaw, sigma, n) = Self::local_frame_yaw(seg, headings)?;
        let one = (headings.iter().map(|h| h.sigma_rad * h.sigma_rad).sum::<f64>() / n as f64).sqrt();
        Some((yaw, sigma.max(one), n))
    }

    /// The global pose of one pair with the segment's current transform (no side effects).
    fn pose_of(&self, p: &PairInput, alignment: Option<&Alignment>, excess_cov_m2: &Matrix3<f64>) -> FusedOutput {
        self.pose_of_with(p, alignment, excess_cov_m2, None, &Matrix3::zeros(), None)
    }

    /// [`Fusion::pose_of`] with the local position's covariance replaced (a local alignment
    /// removes the drift before the window: only the drift within it is left), the buoy's
    /// widened by `buoy_extra_cov_m2`, and, with `correlated`, the buoy fixes' errors correlated
    /// in time: the transform's covariance as the weights take it is the least-squares one, the
    /// pose's reported covariance that of its real errors ([`Correlated`], [`fuse_correlated`]).
    fn pose_of_with(
        &self,
        p: &PairInput,
        alignment: Option<&Alignment>,
        excess_cov_m2: &Matrix3<f64>,
        local_cov_override: Option<Matrix3<f64>>,
        buoy_extra_cov_m2: &Matrix3<f64>,
        correlated: Option<Correlated>,
    ) -> FusedOutput {
        let local_pos = p.local_from_body.translation.vector;
        let local_cov3: Matrix3<f64> =
            local_cov_override.unwrap_or_else(|| p.local_covariance.fixed_view::<3, 3>(0, 0).into_owned());
        let mut cov = Matrix6::zeros();
        match alignment {
            Some(a) => {
                let (x_c, p_c) = a.map_point(&local_pos, &local_cov3);
                let p_c = p_c + excess_cov_m2;
                // The transform's covariance for the errors the pose really has.
                let mut honest = *a;
                honest.covariance *= correlated.map_or(1.0, |c| c.inflation);
                let camera_cov_m2 = honest.map_point(&local_pos, &local_cov3).1 + excess_cov_m2;
                let rotation = a.global_from_local.rotation * p.local_from_body.rotation;
                let rot_cov = p.local_covariance.fixed_view::<3, 3>(3, 3).into_owned()
                    + body_rotation_cov(&rotation, &honest.covariance.fixed_view::<3, 3>(3, 3).into_owned());
                cov.fixed_view_mut::<3, 3>(3, 3).copy_from(&rot_cov);
                let buoy_cov = p.buoy_cov_m2 + buoy_extra_cov_m2;
                let fused = match correlated {
                    Some(c) => {
                        let cross_cov_m2 = joint_cross_covariance(&camera_cov_m2, &buoy_cov, c.buoy_share);
                        let errors = CorrelatedErrors { camera_cov_m2, cross_cov_m2 };
                        fuse_correlated(&x_c, &p_c, &p.buoy_m, &buoy_cov, &errors, self.gate_chi2)
                    }
                    None => fuse(&x_c, &p_c, &p.buoy_m, &buoy_cov, self.gate_chi2),
                };
                let (position, pos_cov, source, m) = match fused {
                    Ok(FuseOutcome::Fused { position_m, covariance_m2, mahalanobis }) => {
                        (position_m, covariance_m2, Source::Fused, Some(mahalanobis))
                    }
                    Ok(FuseOutcome::NoOverlap { mahalanobis }) => {
                        (x_c, camera_cov_m2, Source::CameraOnly, Some(mahalanobis))
                    }
                    Err(_) => (x_c, camera_cov_m2, Source::CameraOnly, None),
                };
                cov.fixed_view_mut::<3, 3>(0, 0).copy_from(&pos_cov);
                FusedOutput {
                    t_s: p.t_s,
                    segment: p.segment,
                    world_from_body: Isometry3::from_parts(Translation3::from(position), rotation),
                    covariance: cov,
                    source,
                    mahalanobis: m,
                    request_new_segment: false,
                    realigned: false,
                }
            }
            None => {
                cov.fixed_view_mut::<3, 3>(0, 0).copy_from(&p.buoy_cov_m2);
                let unknown = std::f64::consts::PI * std::f64::consts::PI;
                cov.fixed_view_mut::<3, 3>(3, 3).copy_from(&(Matrix3::identity() * unknown));
                FusedOutput {
                    t_s: p.t_s,
                    segment: p.segment,
                    world_from_body: Isometry3::from_parts(
                        Translation3::from(p.buoy_m),
                        self.last_orientation.unwrap_or_else(UnitQuaternion::identity),
                    ),
                    covariance: cov,
                    source: Source::BuoyOnly,
                    mahalanobis: None,
                    request_new_segment: false,
                    realigned: false,
                }
            }
        }
    }

    /// One SLAM pose with its synchronised buoy position: the fused global pose.
    pub fn push_pair(&mut self, pair: PairInput) -> Result<FusedOutput, FusionError> {
        Self::check_pair(&pair)?;
        self.push_checked_pair(pair)
    }

    /// The fused pose of a predicted pair (the buoy position extrapolated, the refined pair of
    /// the same stamp still to come) from the state as it is: its segment's current alignment,
    /// nothing stored, nothing realigned. A segment not seen yet has no alignment (buoy only).
    pub fn predict_pair(&self, pair: &PairInput) -> Result<FusedOutput, FusionError> {
        Self::check_pair(pair)?;
        let zero = Matrix3::zeros();
        let seg = self.segments.get(&pair.segment);
        // A local map not seen yet starts with its handover's transform, as its first pair will.
        let carried = match seg {
            Some(s) if s.alignment.is_some() || !s.pairs.is_empty() => None,
            _ => self.handover_for(pair).and_then(|h| {
                let mut new = Segment::new(pair.segment);
                new.handover = Some(h);
                self.handover_prior(&new)
            }),
        };
        match (seg, carried) {
            (Some(s), None) => Ok(self.live_pose(pair, s)),
            (s, carried) => Ok(self.pose_of(pair, carried.as_ref(), s.map_or(&zero, |s| &s.excess_cov_m2))),
        }
    }

    /// The live pose of `pair` in its segment `seg`: mapped with the segment's transform, whose
    /// covariance (least squares over the segment's fixes, as if independent) is inflated for
    /// the fixes' correlation estimated so far ([`Fusion::live_correlation`]), and whose error
    /// the pose's own buoy position shares as the segment's latest fix does (docs/EQUATIONS.md
    /// §5.3).
    fn live_pose(&self, pair: &PairInput, seg: &Segment) -> FusedOutput {
        match &seg.alignment {
            Some(a) if seg.residuals.len() >= 2 => {
                let n = seg.residuals.len();
                let correlated = Correlated {
                    inflation: self.live_correlation.mean_inflation(n),
                    buoy_share: self.live_correlation.with_mean(n, (n - 1) as f64),
                };
                self.pose_of_with(pair, Some(a), &seg.excess_cov_m2, None, &Matrix3::zeros(), Some(correlated))
            }
            _ => self.pose_of(pair, seg.alignment.as_ref(), &seg.excess_cov_m2),
        }
    }

    fn check_pair(pair: &PairInput) -> Result<(), FusionError> {
        let ok = pair.t_s.is_finite()
            && finite3(&pair.local_from_body.translation.vector)
            && pair.local_from_body.rotation.coords.iter().all(|v| v.is_finite())
            && pair.local_covariance.iter().all(|v| v.is_finite())
            && finite3(&pair.buoy_m)
            && pair.buoy_cov_m2.iter().all(|v| v.is_finite());
        if !ok {
            return Err(FusionError::NonFinite("synced pair"));
        }
        Ok(())
    }

    fn push_checked_pair(&mut self, pair: PairInput) -> Result<FusedOutput, FusionError> {
        let id = pair.segment;
        let first = self.segments.get(&id).is_none_or(|s| s.pairs.is_empty());
        let handover = if first { self.handover_for(&pair) } else { None };
        let seg = self.segments.entry(id).or_insert_with(|| Segment::new(id));
        if first && handover.is_some() {
            seg.handover = handover;
            let seg = &self.segments[&id];
            if let Some(prior) = self.handover_prior(seg) {
                let seg = self.segments.get_mut(&id).expect("inserted above");
                seg.alignment = Some(prior);
                seg.status = SegmentStatus::AlignedWithPrior { fixes: 0 };
            }
        }
        let seg = self.segments.get_mut(&id).expect("inserted above");
        if seg.samples.last().is_none_or(|s| pair.t_s > s.t_s) {
            seg.samples.push(PathSample {
                t_s: pair.t_s,
                position_m: pair.local_from_body.translation.vector,
                covariance_m2: pair.local_covariance.fixed_view::<3, 3>(0, 0).into_owned(),
            });
        }
        seg.pairs.push(pair.clone());
        let (from, to) = (seg.samples[0].t_s, seg.samples[seg.samples.len() - 1].t_s);
        let n_fixes = self.fixes_between(from, to).len();
        let mut realigned = false;
        if n_fixes != self.segments[&id].fixes_used {
            let fixes = self.fixes_between(from, to).to_vec();
            let headings = if self.cfg.use_heading { self.headings_between(from, to).to_vec() } else { vec![] };
            let cfg = self.cfg.clone();
            let prior = self.handover_prior(&self.segments[&id]);
            let seg = self.segments.get_mut(&id).expect("inserted above");
            let before = seg.alignment.as_ref().map(|a| a.global_from_local);
            Self::realign(&cfg, seg, &fixes, &headings, prior.as_ref());
            realigned = seg.alignment.as_ref().map(|a| a.global_from_local) != before;
        }
        // The fixes' correlation from every local map's residuals so far: the live pose is
        // mapped with its local map's transform, fitted to that map's fixes as if independent
        // (docs/EQUATIONS.md §5.3, with the pose just after the map's latest fix).
        if realigned {
            self.live_correlation = FixCorrelation::from_residuals(
                self.segments.values().map(|s| s.residuals.as_slice()),
                MAX_CORRELATION_LAG,
            );
        }
        let mut out = self.live_pose(&pair, &self.segments[&id]);
        out.realigned = realigned;
        let seg = self.segments.get_mut(&id).expect("exists");
        match out.source {
            Source::CameraOnly if out.mahalanobis.is_some() => seg.no_overlap += 1,
            Source::Fused => seg.no_overlap = 0,
            _ => {}
        }
        if self.cfg.no_overlap_frames > 0 && seg.no_overlap >= self.cfg.no_overlap_frames && !seg.requested {
            seg.requested = true;
            out.request_new_segment = true;
        }
        if out.source != Source::BuoyOnly {
            self.last_orientation = Some(out.world_from_body.rotation);
        }
        Ok(out)
    }

    /// The local aligner of a segment (`None` without a transform or with the window off).
    fn local_aligner<'a>(&'a self, seg: &'a Segment) -> Option<LocalAligner<'a>> {
        if self.cfg.local_window_s <= 0.0 || seg.alignment.is_none() || seg.samples.len() < 2 {
            return None;
        }
        let spline = LocalPathSpline::fit(&seg.samples).ok()?;
        let (from, to) = (seg.samples[0].t_s, seg.samples[seg.samples.len() - 1].t_s);
        let pairs = self
            .fixes_between(from, to)
            .iter()
            .filter_map(|f| {
                let (local_m, local_cov_m2) = spline.evaluate(f.t_s).ok()?;
                Some((
                    f.t_s,
                    Correspondence {
                        local_m,
                        local_cov_m2: drift_free(&local_cov_m2),
                        global_m: f.position_m,
                        global_cov_m2: f.covariance_m2,
                    },
                ))
            })
            .collect();
        Some(LocalAligner { seg, pairs, window_s: self.cfg.local_window_s })
    }

    /// The end of the run: every segment aligned with all its fixes, every pose mapped and fused
    /// again (the globally consistent path), and the global landmark map.
    pub fn finish(&mut self) -> FinalResult {
        let cfg = self.cfg.clone();
        let ids: Vec<u32> = self.segments.keys().copied().collect();
        for id in &ids {
            let seg = &self.segments[id];
            if seg.samples.is_empty() {
                continue;
            }
            let (from, to) = (seg.samples[0].t_s, seg.samples[seg.samples.len() - 1].t_s);
            let fixes = self.fixes_between(from, to).to_vec();
            let headings = if self.cfg.use_heading { self.headings_between(from, to).to_vec() } else { vec![] };
            // The previous local map is final already (ids ascend with time): its transform
            // carries over.
            let prior = self.handover_prior(&self.segments[id]);
            let seg = self.segments.get_mut(id).expect("listed");
            seg.fixes_used = usize::MAX; // force
            seg.prior_rejected = false;
            Self::realign(&cfg, seg, &fixes, &headings, prior.as_ref());
        }
        self.last_orientation = None;
        let mut path = vec![];
        let mut slam_world = vec![];
        // How correlated the fixes' errors are, from the whole local maps' residuals: what a
        // window's transform and its buoy fix share (docs/EQUATIONS.md §5.3).
        let residuals: Vec<Vec<Vector3<f64>>> =
            ids.iter().filter_map(|id| self.local_aligner(&self.segments[id])).map(|l| l.residuals()).collect();
        let corr = FixCorrelation::from_residuals(residuals.iter().map(Vec::as_slice), MAX_CORRELATION_LAG);
        for id in &ids {
            let seg = &self.segments[id];
            let local = self.local_aligner(seg);
            for p in &seg.pairs {
                let (out, a) = match local.as_ref().and_then(|l| l.at(p, &self.cfg.align, &corr)) {
                    Some(LocalFit { alignment: a, buoy_extra_cov_m2, local_cov_m2, correlated }) => (
                        self.pose_of_with(
                            p,
                            Some(&a),
                            &Matrix3::zeros(),
                            Some(local_cov_m2),
                            &buoy_extra_cov_m2,
                            Some(correlated),
                        ),
                        Some(a),
                    ),
                    None => (self.pose_of(p, seg.alignment.as_ref(), &seg.excess_cov_m2), seg.alignment),
                };
                if let Some(a) = a {
                    slam_world.push((p.t_s, a.global_from_local * p.local_from_body));
                }
                path.push(out);
            }
            if let Some(last) = path.last().filter(|o| o.source != Source::BuoyOnly) {
                self.last_orientation = Some(last.world_from_body.rotation);
            }
        }
        path.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
        slam_world.sort_by(|a, b| a.0.total_cmp(&b.0));
        let aligned: Vec<(Alignment, Vec<MapLandmark>)> = self
            .segments
            .values()
            .filter_map(|s| s.alignment.map(|a| (a, s.landmarks.clone())))
            .filter(|(_, l)| !l.is_empty())
            .collect();
        let global_map = build_global_map(&aligned, &self.cfg.merge);
        FinalResult { path, slam_world, global_map, fix_correlation: corr }
    }
}

/// The cross-covariance P_cb = `share`·P_b between a camera estimate with covariance `p_c` and a
/// buoy position with covariance `p_b`, capped direction by direction so that a joint covariance
/// can have it: P_c − P_cb·P_b⁻¹·P_cbᵀ ⪰ 0. In coordinates where P_b is the identity
/// (P_b = L·Lᵀ), P_c has eigenvalues λᵢ along uᵢ and the cross-covariance is share·I; along each
/// uᵢ the share is at most √λᵢ (zero when P_b is singular).
fn joint_cross_covariance(p_c: &Matrix3<f64>, p_b: &Matrix3<f64>, share: f64) -> Matrix3<f64> {
    let Some(l) = nalgebra::Cholesky::new(*p_b).map(|c| c.l()) else { return Matrix3::zeros() };
    let Some(l_inv) = l.try_inverse() else { return Matrix3::zeros() };
    let m = l_inv * p_c * l_inv.transpose();
    let mut eig = ((m + m.transpose()) * 0.5).symmetric_eigen();
    // Just inside the bound, so that the difference's covariance stays positive definite.
    eig.eigenvalues.iter_mut().for_each(|lambda| *lambda = share.clamp(0.0, 1.0).min(0.999 * lambda.max(0.0).sqrt()));
    l * eig.recompose() * l.transpose()
}

/// The residuals g − T·l of `a` at `pairs`.
fn residuals_of(a: &Alignment, pairs: &[Correspondence]) -> Vec<Vector3<f64>> {
    pairs.iter().map(|c| c.global_m - a.global_from_local.transform_point(&c.local_m.into()).coords).collect()
}

/// The covariance a local path position brings into an alignment. The SLAM covariance grows
/// with the drift since the local map's origin, most of which the rigid transform absorbs;
/// weighted by it, a transform would rest on the poses near the origin. The pairs are weighted by
/// the fixes alone (this returns a floor); what the local path's errors add to the residuals is
/// measured afterwards ([`excess_covariance`]) and carried into the mapped poses.
fn drift_free(_local_cov_m2: &Matrix3<f64>) -> Matrix3<f64> {
    Matrix3::identity() * 1e-6
}

/// Local alignments of one aligned segment for the final path ([`FusionConfig::local_window_s`]).
struct LocalAligner<'a> {
    seg: &'a Segment,
    /// (fix time, correspondence) of every fix inside the segment's span.
    pairs: Vec<(f64, Correspondence)>,
    window_s: f64,
}

/// Longest lag, in fixes, of the fixes' error autocorrelation ([`FixCorrelation`]).
const MAX_CORRELATION_LAG: usize = 60;

/// What the buoy fixes' correlation in time does to a pose mapped with a window's transform
/// (docs/EQUATIONS.md §5.3).
#[derive(Debug, Clone, Copy)]
struct Correlated {
    /// How much larger the transform's covariance is than the least-squares fit's, which takes
    /// the fixes as independent ([`FixCorrelation::mean_inflation`]).
    inflation: f64,
    /// The correlation of the pose's buoy position with the window's mean fix, as a share of its
    /// covariance ([`FixCorrelation::with_mean`]).
    buoy_share: f64,
}

/// A window's transform for one pose ([`LocalAligner::at`]).
struct LocalFit {
    /// The transform fitted to the window's fixes (the least-squares covariance).
    alignment: Alignment,
    /// What the residuals show beyond the fixes' covariance, added to the buoy's, m².
    buoy_extra_cov_m2: Matrix3<f64>,
    /// The local position's covariance within the window, m².
    local_cov_m2: Matrix3<f64>,
    /// The fixes' correlation's effect on the pose.
    correlated: Correlated,
}

impl LocalAligner<'_> {
    /// The residuals g − T·l of the segment's transform at every fix inside it, in time order.
    fn residuals(&self) -> Vec<Vector3<f64>> {
        let Some(a) = self.seg.alignment.as_ref() else { return vec![] };
        self.pairs
            .iter()
            .map(|(_, c)| c.global_m - a.global_from_local.transform_point(&c.local_m.into()).coords)
            .collect()
    }

    /// The transform, the fixes' extra covariance and the local-position covariance for pose
    /// `p`: fitted to the fixes within the window around it; a window too straight for a
    /// rotation keeps the segment's rotation and fits the translation; `None` (the segment's
    /// transform then) with fewer than 7 fixes in the window. The fixes' errors correlate in time
    /// (`corr`): the transform's covariance is that of a mean of fewer independent fixes, and the
    /// pose's own buoy position shares part of its error.
    fn at(&self, p: &PairInput, cfg: &AlignConfig, corr: &FixCorrelation) -> Option<LocalFit> {
        let seg_a = self.seg.alignment.as_ref()?;
        let w = self.window_s;
        let a = self.pairs.partition_point(|(t, _)| *t < p.t_s - w);
        let b = self.pairs.partition_point(|(t, _)| *t <= p.t_s + w);
        let window: Vec<Correspondence> = self.pairs[a..b].iter().map(|(_, c)| *c).collect();
        if window.len() < 7 {
            return None;
        }
        let local = match align(&window, cfg) {
            Ok(l) => l,
            Err(_) => translation_only(seg_a, &window)?,
        };
        // Within the window the local path's own error is not modelled but measured: the
        // reported SLAM covariance is its drift since the local map's origin (a dead-reckoning
        // bound, far more than what a window of a few seconds adds), so the camera estimate
        // carries the transform's uncertainty, scaled by the residuals below.
        let rel = Matrix3::identity() * 1e-6;
        // What the residuals show beyond the fixes' covariance is taken as the fixes' own error
        // (a buoy EKF's errors are correlated in time and larger than it reports: on the
        // simulated mission the locally aligned camera path is closer to the truth than the buoy
        // path), so it widens the fixes, and the transform's covariance grows with the
        // residuals' χ² per degree of freedom.
        let excess = excess_covariance(&local, &window);
        let (mut chi2, mut dof) = (0.0f64, 0.0f64);
        let r = local.global_from_local.rotation.to_rotation_matrix().into_inner();
        for c in &window {
            let e = c.global_m - local.global_from_local.transform_point(&c.local_m.into()).coords;
            if let Some(si) = (r * c.local_cov_m2 * r.transpose() + c.global_cov_m2 + excess).try_inverse() {
                chi2 += e.dot(&(si * e));
                dof += 3.0;
            }
        }
        let mut local = local;
        let scale = (chi2 / (dof - 6.0).max(1.0)).max(1.0);
        local.covariance *= scale;
        // Where the pose lies among the window's fixes (fractional index), for its buoy
        // position's share of the window's mean error.
        let times = &self.pairs[a..b];
        let k = times.partition_point(|(t, _)| *t <= p.t_s);
        let at = match (k.checked_sub(1).map(|i| times[i].0), times.get(k).map(|x| x.0)) {
            (Some(t0), Some(t1)) if t1 > t0 => (k - 1) as f64 + (p.t_s - t0) / (t1 - t0),
            (Some(_), _) => (k - 1) as f64,
            _ => 0.0,
        };
        let correlated =
            Correlated { inflation: corr.mean_inflation(window.len()), buoy_share: corr.with_mean(window.len(), at) };
        Some(LocalFit { alignment: local, buoy_extra_cov_m2: excess, local_cov_m2: rel, correlated })
    }
}

/// The transform with `seg`'s rotation and the translation that best fits `pairs`
/// (inverse-covariance weighted), with its covariance: for a window whose local path is too
/// straight to fix a rotation.
fn translation_only(seg: &Alignment, pairs: &[Correspondence]) -> Option<Alignment> {
    let r = seg.global_from_local.rotation.to_rotation_matrix().into_inner();
    let (mut info, mut b) = (Matrix3::zeros(), Vector3::zeros());
    for c in pairs {
        let s = r * c.local_cov_m2 * r.transpose() + c.global_cov_m2;
        let w = s.try_inverse()?;
        info += w;
        b += w * (c.global_m - r * c.local_m);
    }
    let cov_t = info.try_inverse()?;
    let t = cov_t * b;
    let mut cov = Matrix6::zeros();
    cov.fixed_view_mut::<3, 3>(0, 0).copy_from(&cov_t);
    cov.fixed_view_mut::<3, 3>(3, 3).copy_from(&seg.covariance.fixed_view::<3, 3>(3, 3));
    let global_from_local = Isometry3::from_parts(Translation3::from(t), seg.global_from_local.rotation);
    let rms = (pairs
        .iter()
        .map(|c| (c.global_m - global_from_local.transform_point(&c.local_m.into()).coords).norm_squared())
        .sum::<f64>()
        / pairs.len() as f64)
        .sqrt();
    Some(Alignment { global_from_local, covariance: cov, pairs: pairs.len(), rms_residual_m: rms, spread_ratio: 0.0 })
}

/// The covariance of the alignment residuals r = X_global − T·X_local beyond what the pairs'
/// covariances predict: E = mean(r·rᵀ) − mean(R·Σ_local·Rᵀ + Σ_global), with negative
/// eigenvalues clamped to zero (an a-posteriori variance estimate, as in adaptive Kalman
/// filtering). It grows when the local path drifts or its covariance is optimistic, so that the
/// fusion then leans on the buoy. Needs more pairs than the transform has degrees of freedom
/// (7+); zero otherwise.
pub fn excess_covariance(a: &Alignment, pairs: &[Correspondence]) -> Matrix3<f64> {
    if pairs.len() < 7 {
        return Matrix3::zeros();
    }
    let r = a.global_from_local.rotation.to_rotation_matrix().into_inner();
    let (mut rr, mut predicted) = (Matrix3::zeros(), Matrix3::zeros());
    for p in pairs {
        let e = p.global_m - a.global_from_local.transform_point(&p.local_m.into()).coords;
        rr += e * e.transpose();
        predicted += r * p.local_cov_m2 * r.transpose() + p.global_cov_m2;
    }
    // The fit removed 6 degrees of freedom from the residuals: scale for the expected shrinkage.
    let n = pairs.len() as f64;
    let excess = rr / (n - 2.0) - predicted / n;
    let eig = (excess + excess.transpose()).scale(0.5).symmetric_eigen();
    let clamped = eig.eigenvalues.map(|v| v.max(0.0));
    eig.eigenvectors * Matrix3::from_diagonal(&clamped) * eig.eigenvectors.transpose()
}

#[cfg(test)]
mod tests;

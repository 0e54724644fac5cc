//! Timestamp synchronisation of buoy fixes to camera stamps ([3D] eq 26-30), a pure library: no
//! IPC, no clocks (every time is passed in), no panics on bad input.
//!
//! The buoy estimate at a camera stamp t_k is the quadratic Lagrange interpolation of three buoy
//! fixes, X(t_k) = ξ1·X1 + ξ2·X2 + ξ3·X3, with ξ3 as corrected in EQUATIONS §9 (ξ1 + ξ2 + ξ3 = 1), and
//! the covariance P(t_k) = ξ1²·P1 + ξ2²·P2 + ξ3²·P3 (eq 30, which treats the three fixes as
//! independent). With only two fixes: linear interpolation (flagged). A fix that brings the
//! cross-covariance of its error with the previous fix's ([`CrossPrev`], from the estimator that
//! made both) gets the covariance of the weighted sum of correlated errors instead,
//! P(t_k) = Σᵢ Σⱼ ξᵢξⱼ·Cᵢⱼ (docs/EQUATIONS.md §5.1a). [`lagrange_weights`] and
//! [`interpolate`] are the formulas; [`Synchronizer`] is the buffer and the waiting policy. It is
//! pure logic: every time (stamps, "now") is passed in, on the one clock all sensors share.
//!
//! # Buffer rules ([`Synchronizer::insert`])
//! - Fixes are kept sorted by stamp, at most `capacity` (the oldest are dropped). An
//!   out-of-order fix is inserted at its place.
//! - Duplicate stamp (within `duplicate_tolerance_s`): the later arrival replaces the earlier
//!   one (an upstream estimator re-publishing a stamp has the better estimate); counted.
//! - Upstream restart: a fix stamped more than `restart_backjump_s` before the newest buffered
//!   fix, or whose `seq` is below the last seen `seq` by more than [`REORDER_WINDOW`] (a sequence reset;
//!   plain reordering moves it by less), clears the buffer, which then starts with this fix;
//!   counted. Fixes from before and after a restart are never interpolated together.
//!
//! # Query rules ([`Synchronizer::try_sync`])
//! - A fix within `duplicate_tolerance_s` of t_k: that fix, exactly.
//! - Fixes on both sides of t_k, the two adjacent ones at most `max_gap_s` apart: interpolated.
//!   The triple of two fixes before and one after is used; where it does not exist or spans a
//!   gap (consecutive fixes more than `max_gap_s` apart), one before and two after, waiting (as
//!   below) for the second fix after t_k if it has not arrived; without a usable triple, the two
//!   adjacent fixes interpolate linearly (flag `linear`). So the result depends only on the fixes,
//!   not on which of them had arrived when t_k was asked for (a replay gives the same pairs) and,
//!   in steady state, on no fix beyond the first after t_k (no added latency).
//! - The adjacent fixes are more than `max_gap_s` apart: no interpolation across the gap; the
//!   nearer fix is extrapolated (flags `gap` and `extrapolated`).
//! - No fix after t_k yet: [`SyncDecision::Wait`] until t_k + `max_latency_s` (on the caller's
//!   clock `now_s`); after that the newest fix is extrapolated (flag `extrapolated`).
//! - No fix before t_k (t_k older than the buffer): the oldest fix is extrapolated backwards.
//! - Extrapolation over Δt = t_k − t_fix uses the fix's own velocity, p = p_fix + v_fix·Δt, and
//!   inflates its covariance by the unmodelled velocity change: P = P_fix + (σ_v·Δt)²·I with
//!   σ_v = `extrapolation_velocity_sigma_mps`. Beyond `max_extrapolation_s` the query is
//!   [`SyncDecision::Unavailable`].

use std::collections::VecDeque;

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use serde::{Deserialize, Serialize};
use validation::{ConfigIssue, Issues, Validate};

/// An error of the synchronizer ([`Synchronizer`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SyncError {
    /// A stamp, position or covariance was NaN or infinite.
    #[error("non-finite input: {0}")]
    NonFinite(&'static str),
    /// A covariance was not symmetric positive semi-definite.
    #[error("covariance is not symmetric positive semi-definite")]
    BadCovariance,
    /// The stamps given to an interpolation are not distinct.
    #[error("interpolation stamps must be distinct")]
    RepeatedStamps,
}

/// How far a fix's `seq` may fall behind the last one seen by reordering alone; further back is
/// a sequence reset (an upstream restart).
pub const REORDER_WINDOW: u64 = 64;

/// The Lagrange weights (ξ1, ξ2, ξ3) of the quadratic through stamps `ts` evaluated at `t`
/// ([3D] eq 26-29 with the erratum of EQUATIONS §9 for ξ3). They sum to 1 and reproduce any quadratic
/// exactly. The stamps must be distinct.
pub fn lagrange_weights(t: f64, ts: [f64; 3]) -> Result<[f64; 3], SyncError> {
    if !(t.is_finite() && ts.iter().all(|x| x.is_finite())) {
        return Err(SyncError::NonFinite("stamp"));
    }
    let [t1, t2, t3] = ts;
    if t1 == t2 || t1 == t3 || t2 == t3 {
        return Err(SyncError::RepeatedStamps);
    }
    Ok([
        (t - t2) * (t - t3) / ((t1 - t2) * (t1 - t3)),
        (t - t1) * (t - t3) / ((t2 - t1) * (t2 - t3)),
        (t - t1) * (t - t2) / ((t3 - t1) * (t3 - t2)),
    ])
}

/// Linear interpolation weights (ξ1, ξ2) of two distinct stamps at `t`.
pub fn linear_weights(t: f64, ts: [f64; 2]) -> Result<[f64; 2], SyncError> {
    if !(t.is_finite() && ts.iter().all(|x| x.is_finite())) {
        return Err(SyncError::NonFinite("stamp"));
    }
    if ts[0] == ts[1] {
        return Err(SyncError::RepeatedStamps);
    }
    let a = (t - ts[0]) / (ts[1] - ts[0]);
    Ok([1.0 - a, a])
}

/// The cross-covariance of a fix's error with the previous fix's, from the estimator that made
/// both.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CrossPrev {
    /// Stamp of the previous fix, s.
    pub prev_t_s: f64,
    /// cov(e_prev, e_this), m² (rows: the previous fix's axes).
    pub covariance_m2: Matrix3<f64>,
}

/// A buoy fix: the buoy estimator's output at a stamp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fix {
    /// Stamp (measurement time), s.
    pub t_s: f64,
    /// Sequence number from the publisher.
    pub seq: u64,
    /// Position, m.
    pub position_m: Vector3<f64>,
    /// Its covariance, m².
    pub covariance_m2: Matrix3<f64>,
    /// Velocity, m/s (used to extrapolate).
    pub velocity_mps: Vector3<f64>,
    /// The cross-covariance with the previous fix, when its estimator gives it.
    pub cross_prev: Option<CrossPrev>,
}

impl Fix {
    fn validate(&self) -> Result<(), SyncError> {
        if !self.t_s.is_finite() {
            return Err(SyncError::NonFinite("fix stamp"));
        }
        if !self
            .position_m
            .iter()
            .chain(self.velocity_mps.iter())
            .chain(self.covariance_m2.iter())
            .chain(self.cross_prev.iter().flat_map(|c| c.covariance_m2.iter().chain(std::iter::once(&c.prev_t_s))))
            .all(|v| v.is_finite())
        {
            return Err(SyncError::NonFinite("fix position, velocity or covariance"));
        }
        let c = &self.covariance_m2;
        let scale = c.amax().max(1e-12);
        if (c - c.transpose()).amax() > 1e-9 * scale || SymmetricEigen::new(*c).eigenvalues.min() < -1e-9 * scale {
            return Err(SyncError::BadCovariance);
        }
        Ok(())
    }
}

/// An interpolated position.
#[derive(Debug, Clone, PartialEq)]
pub struct Interpolation {
    /// Σ ξᵢ·pᵢ, m.
    pub position_m: Vector3<f64>,
    /// Σ ξᵢ²·Pᵢ (eq 30), or with the fixes' cross-covariances Σᵢ Σⱼ ξᵢξⱼ·Cᵢⱼ, m².
    pub covariance_m2: Matrix3<f64>,
    /// The weights ξᵢ, in the order of the fixes.
    pub weights: Vec<f64>,
    /// The fixes' cross-covariances were used (every consecutive pair brought its own and the
    /// result is positive semi-definite); else eq 30.
    pub correlated: bool,
}

/// Stamps of a fix and its predecessor named by [`CrossPrev::prev_t_s`] agree within this, s.
const SAME_STAMP_S: f64 = 1e-6;

/// cov(e_i, e_j) of two consecutive fixes, when the later one names the earlier as its previous.
fn consecutive_cross(earlier: &Fix, later: &Fix) -> Option<Matrix3<f64>> {
    later.cross_prev.filter(|c| (c.prev_t_s - earlier.t_s).abs() <= SAME_STAMP_S).map(|c| c.covariance_m2)
}

/// Interpolates 2 (linear) or 3 (quadratic) fixes to `t`: position Σξᵢpᵢ, covariance Σξᵢ²Pᵢ
/// (eq 30); where every fix after the first brings its cross-covariance with the one before it,
/// the covariance of the correlated sum, Σᵢ Σⱼ ξᵢξⱼ·Cᵢⱼ with Cᵢᵢ = Pᵢ and, for the first and the
/// third of three, C₁₃ = C₁₂·P₂⁺·C₂₃ (the errors taken as Markov in the position: what the
/// third fix knows of the first it knows through the second; docs/EQUATIONS.md §5.1a). Another
/// number of fixes, or repeated stamps, is [`SyncError::RepeatedStamps`].
pub fn interpolate(t: f64, fixes: &[Fix]) -> Result<Interpolation, SyncError> {
    let weights: Vec<f64> = match fixes {
        [a, b] => linear_weights(t, [a.t_s, b.t_s])?.to_vec(),
        [a, b, c] => lagrange_weights(t, [a.t_s, b.t_s, c.t_s])?.to_vec(),
        _ => return Err(SyncError::RepeatedStamps),
    };
    let position_m = fixes.iter().zip(&weights).fold(Vector3::zeros(), |acc, (f, w)| acc + f.position_m * *w);
    let independent = fixes.iter().zip(&weights).fold(Matrix3::zeros(), |acc, (f, w)| acc + f.covariance_m2 * (w * w));
    let cross: Option<Vec<(usize, usize, Matrix3<f64>)>> = match fixes {
        [a, b] => consecutive_cross(a, b).map(|c| vec![(0, 1, c)]),
        [a, b, c] => consecutive_cross(a, b).zip(consecutive_cross(b, c)).and_then(|(c12, c23)| {
            let p2_pinv = b.covariance_m2.pseudo_inverse(1e-12 * b.covariance_m2.amax().max(1e-300)).ok()?;
            Some(vec![(0, 1, c12), (1, 2, c23), (0, 2, c12 * p2_pinv * c23)])
        }),
        _ => None,
    };
    let correlated = cross.map(|cs| {
        cs.iter().fold(independent, |acc, (i, j, c)| acc + (c + c.transpose()) * (weights[*i] * weights[*j]))
    });
    // The cross-covariances come from one estimator's model: a joint covariance they do not fit
    // (a fix re-published, a model approximation) could give a matrix that is no covariance.
    let psd = |m: &Matrix3<f64>| {
        let scale = m.amax().max(1e-300);
        m.iter().all(|v| v.is_finite()) && SymmetricEigen::new(*m).eigenvalues.min() >= -1e-9 * scale
    };
    match correlated.filter(psd) {
        Some(covariance_m2) => Ok(Interpolation { position_m, covariance_m2, weights, correlated: true }),
        None => Ok(Interpolation { position_m, covariance_m2: independent, weights, correlated: false }),
    }
}

/// Settings of the [`Synchronizer`] (see the module docs for the rules).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SyncConfig {
    /// Fixes kept, at most. Stages run at their own pace when a data set is replayed as fast as
    /// possible, so poses can lag the fixes by minutes of data time: the default (4096, over an
    /// hour at 1 Hz) keeps them pairable.
    pub capacity: usize,
    /// Largest time between two adjacent fixes that are interpolated across, s.
    pub max_gap_s: f64,
    /// How long after a query stamp to wait for a fix after it, s.
    pub max_latency_s: f64,
    /// Largest extrapolation, s.
    pub max_extrapolation_s: f64,
    /// σ of the unmodelled velocity change while extrapolating, m/s.
    pub extrapolation_velocity_sigma_mps: f64,
    /// Stamps closer than this are the same stamp, s.
    pub duplicate_tolerance_s: f64,
    /// A fix this far before the newest one means the upstream restarted, s.
    pub restart_backjump_s: f64,
}

impl Default for SyncConfig {
    fn default() -> Self {
        Self {
            capacity: 4096,
            max_gap_s: 5.0,
            max_latency_s: 1.0,
            max_extrapolation_s: 5.0,
            extrapolation_velocity_sigma_mps: 0.5,
            duplicate_tolerance_s: 1e-6,
            restart_backjump_s: 10.0,
        }
    }
}

impl Validate for SyncConfig {
    fn validate(&self, issues: &mut Issues) {
        let pos = |x: f64| x.is_finite() && x > 0.0;
        let nonneg = |x: f64| x.is_finite() && x >= 0.0;
        issues.check(self.capacity >= 3, "capacity", "must be >= 3");
        issues.check(pos(self.max_gap_s), "max_gap_s", "must be > 0");
        issues.check(nonneg(self.max_latency_s), "max_latency_s", "must be >= 0");
        issues.check(nonneg(self.max_extrapolation_s), "max_extrapolation_s", "must be >= 0");
        issues.check(nonneg(self.extrapolation_velocity_sigma_mps), "extrapolation_velocity_sigma_mps", "must be >= 0");
        issues.check(nonneg(self.duplicate_tolerance_s), "duplicate_tolerance_s", "must be >= 0");
        issues.check(
            pos(self.restart_backjump_s) && self.restart_backjump_s > self.duplicate_tolerance_s,
            "restart_backjump_s",
            "must be > duplicate_tolerance_s",
        );
    }
}

/// How a synchronised position came about.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SyncFlags {
    /// Interpolated between fixes on both sides (quadratic or linear).
    pub interpolated: bool,
    /// Only two fixes: linear interpolation.
    pub linear: bool,
    /// Extrapolated from one fix (no bracketing fix in time, a gap, or outside the buffer).
    pub extrapolated: bool,
    /// The fixes around the stamp are more than `max_gap_s` apart.
    pub gap: bool,
}

impl SyncFlags {
    /// As a bit set: 1 extrapolated, 2 linear (as `shared_types::SYNC_EXTRAPOLATED`,
    /// `SYNC_LINEAR`), 4 gap, 8 interpolated.
    pub fn bits(&self) -> u32 {
        u32::from(self.extrapolated)
            | u32::from(self.linear) << 1
            | u32::from(self.gap) << 2
            | u32::from(self.interpolated) << 3
    }
}

/// A buoy position synchronised to a query stamp.
#[derive(Debug, Clone, PartialEq)]
pub struct SyncResult {
    /// The query stamp, s.
    pub t_s: f64,
    /// Position, m.
    pub position_m: Vector3<f64>,
    /// Covariance, m².
    pub covariance_m2: Matrix3<f64>,
    /// How it was obtained.
    pub flags: SyncFlags,
    /// Fixes used (1, 2 or 3).
    pub fixes_used: usize,
    /// Stamp of the newest fix used, s.
    pub newest_fix_s: f64,
    /// The covariance accounts for the fixes' correlation ([`Interpolation::correlated`]).
    pub correlated: bool,
}

/// Why no synchronised position can be given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Unavailable {
    /// No fix in the buffer (and the wait is over).
    NoFixes,
    /// The nearest usable fix is further than `max_extrapolation_s` from the stamp.
    TooFarFromFixes {
        /// Distance to the nearest usable fix, s.
        distance_s: f64,
    },
}

/// The answer to a query.
#[derive(Debug, Clone, PartialEq)]
pub enum SyncDecision {
    /// Interpolated (or an exact fix).
    Ready(SyncResult),
    /// No fix after the stamp yet: ask again at or after `until_s` (caller's clock), or sooner
    /// when a fix arrives.
    Wait {
        /// When the wait is over, s.
        until_s: f64,
    },
    /// Extrapolated (flagged; covariance inflated).
    Extrapolated(SyncResult),
    /// Nothing usable.
    Unavailable(Unavailable),
}

/// What [`Synchronizer::insert`] did with a fix.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InsertOutcome {
    /// Inserted at its place in time.
    Inserted,
    /// It replaced a fix with the same stamp.
    ReplacedDuplicate,
    /// It signalled an upstream restart: the buffer was cleared and starts with it.
    Restarted,
    /// Older than everything in a full buffer: dropped.
    DroppedTooOld,
}

/// Counters of the buffer's decisions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SyncCounters {
    /// Fixes inserted (including duplicates and restarts).
    pub inserted: u64,
    /// Fixes that arrived out of stamp order.
    pub out_of_order: u64,
    /// Duplicate stamps replaced.
    pub duplicates: u64,
    /// Upstream restarts detected.
    pub restarts: u64,
    /// Fixes dropped (capacity).
    pub dropped: u64,
}

/// The buffer of buoy fixes and the synchronisation policy (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Synchronizer {
    cfg: SyncConfig,
    fixes: VecDeque<Fix>,
    last_seq: Option<u64>,
    counters: SyncCounters,
}

impl Synchronizer {
    /// An empty synchronizer; the configuration must validate.
    pub fn new(cfg: SyncConfig) -> Result<Self, Vec<ConfigIssue>> {
        cfg.issues().into_result()?;
        Ok(Self { cfg, fixes: VecDeque::new(), last_seq: None, counters: SyncCounters::default() })
    }

    /// The buffered fixes, oldest first.
    pub fn fixes(&self) -> impl Iterator<Item = &Fix> {
        self.fixes.iter()
    }

    /// The counters.
    pub fn counters(&self) -> SyncCounters {
        self.counters
    }

    /// Adds a fix (see the module docs for duplicates, order and restarts).
    pub fn insert(&mut self, fix: Fix) -> Result<InsertOutcome, SyncError> {
        fix.validate()?;
        self.counters.inserted += 1;
        let seq_reset = self.last_seq.is_some_and(|s| fix.seq.saturating_add(REORDER_WINDOW) < s);
        self.last_seq = Some(fix.seq);
        let newest = self.fixes.back().map(|f| f.t_s);
        if seq_reset || newest.is_some_and(|n| fix.t_s < n - self.cfg.restart_backjump_s) {
            self.fixes.clear();
            self.fixes.push_back(fix);
            self.counters.restarts += 1;
            return Ok(InsertOutcome::Restarted);
        }
        let tol = self.cfg.duplicate_tolerance_s;
        if let Some(dup) = self.fixes.iter_mut().find(|f| (f.t_s - fix.t_s).abs() <= tol) {
            *dup = fix;
            self.counters.duplicates += 1;
            return Ok(InsertOutcome::ReplacedDuplicate);
        }
        let at = self.fixes.partition_point(|f| f.t_s < fix.t_s);
        if at < self.fixes.len() {
            self.counters.out_of_order += 1;
            if at == 0 && self.fixes.len() >= self.cfg.capacity {
                self.counters.dropped += 1;
                return Ok(InsertOutcome::DroppedTooOld);
            }
        }
        self.fixes.insert(at, fix);
        while self.fixes.len() > self.cfg.capacity {
            self.fixes.pop_front();
            self.counters.dropped += 1;
        }
        Ok(InsertOutcome::Inserted)
    }

    /// The buoy position at `t_s`, given the caller's current time `now_s` (for the wait).
    pub fn try_sync(&self, t_s: f64, now_s: f64) -> Result<SyncDecision, SyncError> {
        if !(t_s.is_finite() && now_s.is_finite()) {
            return Err(SyncError::NonFinite("query stamp or now"));
        }
        let c = &self.cfg;
        let waiting = now_s < t_s + c.max_latency_s;
        let (Some(oldest), Some(newest)) = (self.fixes.front(), self.fixes.back()) else {
            return Ok(if waiting {
                SyncDecision::Wait { until_s: t_s + c.max_latency_s }
            } else {
                SyncDecision::Unavailable(Unavailable::NoFixes)
            });
        };
        if let Some(f) = self.fixes.iter().find(|f| (f.t_s - t_s).abs() <= c.duplicate_tolerance_s) {
            return Ok(SyncDecision::Ready(SyncResult {
                t_s,
                position_m: f.position_m,
                covariance_m2: f.covariance_m2,
                flags: SyncFlags::default(),
                fixes_used: 1,
                newest_fix_s: f.t_s,
                correlated: false,
            }));
        }
        if t_s > newest.t_s {
            if waiting {
                return Ok(SyncDecision::Wait { until_s: t_s + c.max_latency_s });
            }
            return Ok(self.extrapolate(newest, t_s, false));
        }
        if t_s < oldest.t_s {
            return Ok(self.extrapolate(oldest, t_s, false));
        }
        // Bracketed: a = last fix before, b = a + 1 the first after.
        let b = self.fixes.partition_point(|f| f.t_s < t_s);
        let a = b - 1;
        let f = &self.fixes;
        if f[b].t_s - f[a].t_s > c.max_gap_s {
            let nearer = if t_s - f[a].t_s <= f[b].t_s - t_s { &f[a] } else { &f[b] };
            return Ok(self.extrapolate(nearer, t_s, true));
        }
        let gap_free =
            |i: usize, j: usize, k: usize| f[j].t_s - f[i].t_s <= c.max_gap_s && f[k].t_s - f[j].t_s <= c.max_gap_s;
        let used: Vec<Fix> = if a >= 1 && gap_free(a - 1, a, b) {
            vec![f[a - 1], f[a], f[b]]
        } else if b + 1 < f.len() {
            if gap_free(a, b, b + 1) { vec![f[a], f[b], f[b + 1]] } else { vec![f[a], f[b]] }
        } else if waiting {
            // One before + two after is the only triple: wait for its second fix after t_k.
            return Ok(SyncDecision::Wait { until_s: t_s + c.max_latency_s });
        } else {
            vec![f[a], f[b]]
        };
        let Interpolation { position_m, covariance_m2, correlated, .. } = interpolate(t_s, &used)?;
        Ok(SyncDecision::Ready(SyncResult {
            t_s,
            position_m,
            covariance_m2,
            flags: SyncFlags { interpolated: true, linear: used.len() == 2, extrapolated: false, gap: false },
            fixes_used: used.len(),
            newest_fix_s: used.iter().map(|u| u.t_s).fold(f64::NEG_INFINITY, f64::max),
            correlated,
        }))
    }

    fn extrapolate(&self, fix: &Fix, t_s: f64, gap: bool) -> SyncDecision {
        let dt = t_s - fix.t_s;
        if dt.abs() > self.cfg.max_extrapolation_s {
            return SyncDecision::Unavailable(Unavailable::TooFarFromFixes { distance_s: dt.abs() });
        }
        let inflation = (self.cfg.extrapolation_velocity_sigma_mps * dt).powi(2);
        SyncDecision::Extrapolated(SyncResult {
            t_s,
            position_m: fix.position_m + fix.velocity_mps * dt,
            covariance_m2: fix.covariance_m2 + Matrix3::identity() * inflation,
            flags: SyncFlags { interpolated: false, linear: false, extrapolated: true, gap },
            fixes_used: 1,
            newest_fix_s: fix.t_s,
            correlated: false,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn fix(t_s: f64, seq: u64, x: f64) -> Fix {
        Fix {
            t_s,
            seq,
            position_m: Vector3::new(x, 2.0 * x, -1.0),
            covariance_m2: Matrix3::identity() * 0.01,
            velocity_mps: Vector3::new(1.0, 2.0, 0.0),
            cross_prev: None,
        }
    }

    fn sync_with(fixes: &[Fix]) -> Synchronizer {
        let mut s = Synchronizer::new(SyncConfig::default()).unwrap();
        for f in fixes {
            s.insert(*f).unwrap();
        }
        s
    }

    proptest! {
        #[test]
        fn lagrange_weights_sum_to_one_and_reproduce_any_quadratic(
            t0 in -100.0..100.0f64,
            d1 in 0.01..10.0f64,
            d2 in 0.01..10.0f64,
            u in -0.5..1.5f64,
            a in -50.0..50.0f64,
            b in -10.0..10.0f64,
            c in -3.0..3.0f64,
        ) {
            let ts = [t0, t0 + d1, t0 + d1 + d2];
            let t = t0 + u * (d1 + d2);
            let w = lagrange_weights(t, ts).unwrap();
            prop_assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-9);
            let q = |t: f64| a + b * (t - t0) + c * (t - t0) * (t - t0);
            let interpolated: f64 = w.iter().zip(ts).map(|(wi, ti)| wi * q(ti)).sum();
            let scale = 1.0 + a.abs() + b.abs() * (d1 + d2) + c.abs() * (d1 + d2).powi(2);
            prop_assert!((interpolated - q(t)).abs() < 1e-9 * scale, "{} vs {}", interpolated, q(t));
            // Order does not matter.
            let w2 = lagrange_weights(t, [ts[2], ts[0], ts[1]]).unwrap();
            prop_assert!((w2[0] - w[2]).abs() < 1e-9 && (w2[1] - w[0]).abs() < 1e-9);
        }

        #[test]
        fn linear_weights_reproduce_any_line(
            t0 in -100.0..100.0f64,
            d in 0.01..10.0f64,
            u in -0.5..1.5f64,
            a in -50.0..50.0f64,
            b in -10.0..10.0f64,
        ) {
            let t = t0 + u * d;
            let w = linear_weights(t, [t0, t0 + d]).unwrap();
            prop_assert!((w[0] + w[1] - 1.0).abs() < 1e-12);
            let line = |t: f64| a + b * t;
            let scale = 1.0 + a.abs() + b.abs() * (t0.abs() + d);
            prop_assert!((w[0] * line(t0) + w[1] * line(t0 + d) - line(t)).abs() < 1e-9 * scale);
        }
    }

    #[test]
    fn the_weights_of_a_hand_computed_case() {
        // Stamps 0, 1, 3 at t = 2: ξ1 = (2−1)(2−3)/((0−1)(0−3)) = −1/3,
        // ξ2 = (2−0)(2−3)/((1−0)(1−3)) = 1, ξ3 = (2−0)(2−1)/((3−0)(3−1)) = 1/3.
        let w = lagrange_weights(2.0, [0.0, 1.0, 3.0]).unwrap();
        let expected = [-1.0 / 3.0, 1.0, 1.0 / 3.0];
        for (a, b) in w.iter().zip(expected) {
            assert!((a - b).abs() < 1e-15, "{w:?}");
        }
        assert_eq!(lagrange_weights(2.0, [0.0, 1.0, 1.0]), Err(SyncError::RepeatedStamps));
        assert!(lagrange_weights(f64::NAN, [0.0, 1.0, 2.0]).is_err());
    }

    #[test]
    fn covariance_follows_eq_30() {
        // Same stamps: P = (1/9)·P1 + 1·P2 + (1/9)·P3.
        let mk = |t: f64, p: Matrix3<f64>| Fix {
            t_s: t,
            seq: 0,
            position_m: Vector3::new(t, 0.0, 0.0),
            covariance_m2: p,
            velocity_mps: Vector3::zeros(),
            cross_prev: None,
        };
        let p1 = Matrix3::from_diagonal(&Vector3::new(9.0, 0.0, 0.0));
        let p2 = Matrix3::new(1.0, 0.5, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 2.0);
        let p3 = Matrix3::from_diagonal(&Vector3::new(0.0, 18.0, 9.0));
        let Interpolation { position_m: p, covariance_m2: cov, weights: w, correlated } =
            interpolate(2.0, &[mk(0.0, p1), mk(1.0, p2), mk(3.0, p3)]).unwrap();
        assert!(!correlated, "no cross-covariances given: eq 30");
        let expected = Matrix3::new(2.0, 0.5, 0.0, 0.5, 3.0, 0.0, 0.0, 0.0, 3.0);
        assert!((cov - expected).amax() < 1e-12, "{cov}");
        assert!((p.x - 2.0).abs() < 1e-12, "a line through (t, t) gives t: {p}");
        assert_eq!(w.len(), 3);
    }

    /// Fixes whose errors follow an AR(1) process (ρ per fix, per axis; z independent) with
    /// their cross-covariances: the interpolated covariance is the sample covariance of the
    /// interpolated error (20,000 draws), and larger than eq 30's, which is what the errors
    /// are not.
    #[test]
    fn correlated_fixes_give_the_covariance_of_the_correlated_sum() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let (sigma, rho) = (Vector3::new(0.3, 0.2, 0.1), Vector3::new(0.9, 0.8, 0.0));
        let p = Matrix3::from_diagonal(&sigma.component_mul(&sigma));
        let c = Matrix3::from_diagonal(&sigma.component_mul(&sigma).component_mul(&rho));
        let mk = |t: f64, prev: Option<f64>| Fix {
            t_s: t,
            seq: 0,
            position_m: Vector3::zeros(),
            covariance_m2: p,
            velocity_mps: Vector3::zeros(),
            cross_prev: prev.map(|prev_t_s| CrossPrev { prev_t_s, covariance_m2: c }),
        };
        let fixes = [mk(0.0, None), mk(1.0, Some(0.0)), mk(2.0, Some(1.0))];
        let t = 1.5;
        let got = interpolate(t, &fixes).unwrap();
        assert!(got.correlated);
        let eq30 = interpolate(t, &fixes.map(|f| Fix { cross_prev: None, ..f })).unwrap();
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let n01 = Normal::new(0.0, 1.0).unwrap();
        let draws = 20_000;
        let mut sample = Matrix3::zeros();
        for _ in 0..draws {
            let mut e = Vector3::from_fn(|a, _| sigma[a] * n01.sample(&mut rng));
            let mut sum = e * got.weights[0];
            for w in &got.weights[1..] {
                e = Vector3::from_fn(|a, _| {
                    rho[a] * e[a] + (1.0 - rho[a] * rho[a]).sqrt() * sigma[a] * n01.sample(&mut rng)
                });
                sum += e * *w;
            }
            sample += sum * sum.transpose() / draws as f64;
        }
        for a in 0..3 {
            let v = got.covariance_m2[(a, a)];
            // The sample variance of n draws is within 4·√(2/n) ≈ 4 % of the variance.
            assert!((sample[(a, a)] / v - 1.0).abs() < 0.04, "axis {a}: {sample} against {}", got.covariance_m2);
        }
        assert!(got.covariance_m2[(0, 0)] > 1.3 * eq30.covariance_m2[(0, 0)], "correlated x: larger than eq 30's");
        assert!((got.covariance_m2[(2, 2)] - eq30.covariance_m2[(2, 2)]).abs() < 1e-15, "independent z: eq 30's");
        // A fix that names another predecessor (one in between was lost) is not linked: eq 30.
        let broken = [mk(0.0, None), mk(1.0, Some(0.5)), mk(2.0, Some(1.0))];
        let b = interpolate(t, &broken).unwrap();
        assert!(!b.correlated && (b.covariance_m2 - eq30.covariance_m2).amax() < 1e-15);
        // Cross-covariances no joint covariance has (larger than the variances): eq 30.
        let bad = |t: f64, prev: Option<f64>| Fix {
            cross_prev: prev.map(|prev_t_s| CrossPrev { prev_t_s, covariance_m2: -p * 3.0 }),
            ..mk(t, None)
        };
        let b = interpolate(t, &[bad(0.0, None), bad(1.0, Some(0.0)), bad(2.0, Some(1.0))]).unwrap();
        assert!(!b.correlated && (b.covariance_m2 - eq30.covariance_m2).amax() < 1e-15, "{}", b.covariance_m2);
    }

    #[test]
    fn out_of_order_fixes_are_sorted_and_interpolation_uses_two_fixes_before_and_one_after() {
        let mut s = sync_with(&[fix(0.0, 0, 0.0), fix(2.0, 2, 2.0), fix(1.0, 1, 1.0), fix(5.0, 3, 5.0)]);
        assert_eq!(s.fixes().map(|f| f.t_s).collect::<Vec<_>>(), [0.0, 1.0, 2.0, 5.0]);
        assert_eq!(s.counters().out_of_order, 1);
        // t = 1.5: candidates (0, 1, 2) spanning 2 s and (1, 2, 5) spanning 4 s.
        let SyncDecision::Ready(r) = s.try_sync(1.5, 1.5).unwrap() else { panic!() };
        assert_eq!((r.fixes_used, r.flags), (3, SyncFlags { interpolated: true, ..SyncFlags::default() }));
        assert!((r.position_m.x - 1.5).abs() < 1e-12);
        assert_eq!(r.newest_fix_s, 2.0);
        // At 4.9 (2, 5, ...) would span less than (1, 2, 5), but two before + one after is used
        // whatever else has arrived, so the result does not depend on arrival timing.
        s.insert(fix(5.2, 4, 5.2)).unwrap();
        let SyncDecision::Ready(r) = s.try_sync(4.9, 4.9).unwrap() else { panic!() };
        assert_eq!((r.fixes_used, r.newest_fix_s), (3, 5.0));
        // Between the first two fixes only one triple exists (0, 1, 2).
        let SyncDecision::Ready(r) = s.try_sync(0.5, 9.0).unwrap() else { panic!() };
        assert_eq!(r.fixes_used, 3);
        // With two fixes only: wait for a second fix after t, then linear.
        s = sync_with(&[fix(0.0, 0, 0.0), fix(1.0, 1, 1.0)]);
        assert!(matches!(s.try_sync(0.25, 0.25).unwrap(), SyncDecision::Wait { .. }));
        let SyncDecision::Ready(r) = s.try_sync(0.25, 9.0).unwrap() else { panic!() };
        assert!(r.flags.linear && r.flags.interpolated && r.fixes_used == 2);
        assert_eq!(r.flags.bits(), 2 | 8);
        // Covariance of the linear case: (0.75² + 0.25²)·0.01.
        assert!((r.covariance_m2[(0, 0)] - 0.00625).abs() < 1e-12);
    }

    #[test]
    fn a_duplicate_stamp_keeps_the_latest_fix() {
        let mut s = sync_with(&[fix(0.0, 0, 0.0), fix(1.0, 1, 1.0)]);
        assert_eq!(s.insert(fix(1.0, 2, 7.0)).unwrap(), InsertOutcome::ReplacedDuplicate);
        assert_eq!(s.fixes().count(), 2);
        assert_eq!(s.counters().duplicates, 1);
        let SyncDecision::Ready(r) = s.try_sync(1.0, 1.0).unwrap() else { panic!() };
        assert_eq!((r.position_m.x, r.fixes_used), (7.0, 1));
    }

    #[test]
    fn no_interpolation_across_a_gap() {
        let s = sync_with(&[fix(0.0, 0, 0.0), fix(1.0, 1, 1.0), fix(10.0, 2, 10.0), fix(11.0, 3, 11.0)]);
        // 2 s after the fix at 1 s, across a 9 s gap: extrapolated from that fix, flagged.
        let SyncDecision::Extrapolated(r) = s.try_sync(3.0, 3.0).unwrap() else { panic!() };
        assert!(r.flags.gap && r.flags.extrapolated && !r.flags.interpolated);
        assert_eq!(r.newest_fix_s, 1.0);
        assert!((r.position_m.x - 3.0).abs() < 1e-12, "p + v·Δt");
        // Nearer the later fix: extrapolated backwards from it.
        let SyncDecision::Extrapolated(r) = s.try_sync(9.0, 9.0).unwrap() else { panic!() };
        assert_eq!(r.newest_fix_s, 10.0);
        // At 10.5 the triple (1, 10, 11) would span the gap and there is no fix after 11: it waits
        // for one, then (none came) linear.
        assert!(matches!(s.try_sync(10.5, 10.5).unwrap(), SyncDecision::Wait { .. }));
        let SyncDecision::Ready(r) = s.try_sync(10.5, 12.0).unwrap() else { panic!() };
        assert!(r.flags.linear && r.fixes_used == 2, "{r:?}");
        // Too far into the gap.
        let s = sync_with(&[fix(0.0, 0, 0.0), fix(20.0, 1, 1.0)]);
        assert_eq!(
            s.try_sync(10.0, 10.0).unwrap(),
            SyncDecision::Unavailable(Unavailable::TooFarFromFixes { distance_s: 10.0 })
        );
    }

    #[test]
    fn an_upstream_restart_clears_the_buffer() {
        let mut s = sync_with(&[fix(100.0, 50, 0.0), fix(101.0, 51, 1.0), fix(102.0, 52, 2.0)]);
        // A stamp far before the buffer.
        assert_eq!(s.insert(fix(50.0, 53, 9.0)).unwrap(), InsertOutcome::Restarted);
        assert_eq!(s.fixes().map(|f| f.t_s).collect::<Vec<_>>(), [50.0]);
        // A sequence reset with stamps going on.
        let mut s = sync_with(&[fix(100.0, 500, 0.0), fix(101.0, 501, 1.0)]);
        assert_eq!(s.insert(fix(102.0, 0, 2.0)).unwrap(), InsertOutcome::Restarted);
        assert_eq!(s.counters().restarts, 1);
        assert_eq!(s.fixes().count(), 1);
        // Plain reordering is not a restart.
        let mut s = sync_with(&[fix(100.0, 10, 0.0), fix(102.0, 12, 2.0)]);
        assert_eq!(s.insert(fix(101.0, 11, 1.0)).unwrap(), InsertOutcome::Inserted);
    }

    #[test]
    fn without_a_later_fix_the_caller_waits_then_gets_an_inflated_extrapolation() {
        let s = sync_with(&[fix(0.0, 0, 0.0), fix(1.0, 1, 1.0)]);
        assert_eq!(s.try_sync(1.5, 1.6).unwrap(), SyncDecision::Wait { until_s: 2.5 });
        let SyncDecision::Extrapolated(r) = s.try_sync(1.5, 2.5).unwrap() else { panic!() };
        assert_eq!(r.flags, SyncFlags { extrapolated: true, ..SyncFlags::default() });
        assert_eq!(r.flags.bits(), 1);
        assert!((r.position_m - Vector3::new(1.5, 3.0, -1.0)).norm() < 1e-12);
        // P = 0.01·I + (0.5 m/s · 0.5 s)²·I.
        assert!((r.covariance_m2 - Matrix3::identity() * (0.01 + 0.0625)).amax() < 1e-12);
        // Empty buffer: wait, then unavailable.
        let e = Synchronizer::new(SyncConfig::default()).unwrap();
        assert_eq!(e.try_sync(1.0, 1.0).unwrap(), SyncDecision::Wait { until_s: 2.0 });
        assert_eq!(e.try_sync(1.0, 2.0).unwrap(), SyncDecision::Unavailable(Unavailable::NoFixes));
        // Older than the buffer: extrapolated backwards, no wait.
        let SyncDecision::Extrapolated(r) = s.try_sync(-1.0, -1.0).unwrap() else { panic!() };
        assert_eq!(r.newest_fix_s, 0.0);
    }

    #[test]
    fn capacity_bounds_the_buffer_and_bad_fixes_are_refused() {
        let cfg = SyncConfig { capacity: 3, ..SyncConfig::default() };
        let mut s = Synchronizer::new(cfg).unwrap();
        for k in 0..5u32 {
            s.insert(fix(f64::from(k), u64::from(k), 0.0)).unwrap();
        }
        assert_eq!(s.fixes().map(|f| f.t_s).collect::<Vec<_>>(), [2.0, 3.0, 4.0]);
        assert_eq!(s.insert(fix(1.5, 5, 0.0)).unwrap(), InsertOutcome::DroppedTooOld);
        assert_eq!(s.counters().dropped, 3);
        assert_eq!(s.insert(fix(f64::NAN, 6, 0.0)), Err(SyncError::NonFinite("fix stamp")));
        let mut bad = fix(6.0, 6, 0.0);
        bad.covariance_m2[(0, 1)] = 1.0;
        assert_eq!(s.insert(bad), Err(SyncError::BadCovariance));
        bad.covariance_m2 = -Matrix3::identity();
        assert_eq!(s.insert(bad), Err(SyncError::BadCovariance));
        assert!(s.try_sync(f64::INFINITY, 0.0).is_err());
        assert!(Synchronizer::new(SyncConfig { capacity: 2, max_gap_s: 0.0, ..SyncConfig::default() }).is_err());
    }
}

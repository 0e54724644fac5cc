//! The buoy estimator (EQUATIONS §5): an extended Kalman filter for the global position from ranges
//! to buoys at known positions, odometry, pressure depth and GPS fixes.
//!
//! # State
//! x = (p, v, ψ, \[b_ω\], \[s\], \[β…\]), in this order (bracketed parts are optional):
//! - p: position, (x, y) in planar mode, (x, y, z) in spatial mode, m;
//! - v: velocity in the world frame, same dimension, m/s;
//! - ψ: heading (yaw) of the body x axis, rad, wrapped to (−π, π];
//! - b_ω: turn-rate bias of the odometry, rad/s (`motion.estimate_turn_bias`);
//! - s: range scale factor, dimensionless (`range.estimate_scale`);
//! - β: range biases, m: none, one global (the default), or one per buoy in buoy-table order
//!   (`range.bias`). With the scale this is an affine range calibration r = (1 + s)·d + β; on
//!   Plaza2 the ranges read ~7 % long (2-4 m at 30-60 m), which the scale state takes up.
//!
//! # Models
//! - Range (EQUATIONS §5 with scale and bias): r_j = (1 + s)·‖p − b_j‖ + β_j + n_j, so
//!   H = ((1 + s)(p − b_j)ᵀ/‖p − b_j‖, ∂/∂s = ‖p − b_j‖, ∂/∂β_j = 1). In planar mode the distance
//!   is sqrt(‖p_xy − b_j,xy‖² + Δz²) with the known height difference Δz = b_j,z − `planar_height_m`.
//! - Constant velocity ([`BuoyEkf::predict_to`] without a recent odometry input): p += v·Δt,
//!   white-noise acceleration `motion.accel_sigma_mps2`; ψ random walk `motion.cv_turn_rate_sigma_rps`·Δt.
//! - Odometry ([`BuoyEkf::predict_with_input`], speed v and turn δθ over Δt, EQUATIONS §1 restricted
//!   to yaw): ψ' = ψ + δθ − b_ω·Δt, p_xy' = p_xy + v·Δt·(cos ψ_m, sin ψ_m) with the midpoint heading
//!   ψ_m = ψ + (δθ − b_ω·Δt)/2 (second order; EQUATIONS §1's start heading differs by O(v·Δt·δθ/2)),
//!   v_xy' = v·(cos ψ', sin ψ'). Noise: the input's variances through the Jacobian, plus wheel slip
//!   (σ = `motion.slip_fraction`·|v|·Δt per horizontal axis) and a heading random walk. In spatial
//!   mode z and v_z follow the constant-velocity model (depth readings constrain them).
//!   Between inputs (a range stamped between two odometry rows) the last input's speed and turn
//!   rate are held for up to `motion.input_hold_s`; the next input covers the rest of its interval
//!   pro rata.
//! - Depth: d = −z (spatial mode only). Position fix: p directly (the planar mode uses x, y).
//!
//! All updates are Joseph-form. Accepted ranges beyond `range.huber_k` normalised innovations
//! are down-weighted (Huber, R scaled by |ν|/(k√S)). The range scale and bias states do not
//! learn from a range whose innovation is more than `range.calibration_k` σ of what they cannot
//! explain (position uncertainty and range noise): its gain rows for them are zeroed (a
//! Schmidt update; counted as `calibration_held`), so a gross error accepted while the bias
//! prior is still wide moves the position a little instead of the bias a lot; but the second of
//! two such ranges to a buoy within 5 s whose innovations agree (a calibration error repeats, a
//! gross error does not) does teach them. Nor do they learn
//! what the recent ranges cannot determine (`range.observable_sigma_fraction`,
//! [`Model::unobservable_calibration`]: the ranges of the last `range.observability_window_s`,
//! along the odometry's path, with the position's offset and the other calibration states
//! free; counted as `calibration_unobservable`): from one place among 3 buoys a scale, a bias
//! and the position cannot be told apart, and per-buoy biases need the vehicle to move.
//!
//! # Gating and recovery
//! A range whose normalised innovation ν²/S exceeds the χ²₁ quantile of `range.gate_probability`
//! is rejected and counted (total and per buoy). One accepted at more than `range.doubtful_sigma`
//! is taken while a copy of the filter without it runs alongside; the ranges after it decide
//! (their likelihoods under each, 19:1), and a range the copy wins on is undone and counted as
//! rejected (`outlier_branch_switches`); depth uses the same χ²₁ gate and a position fix
//! the χ²_D one. A filter that has gone wrong rejects everything, so rejections in a row trigger
//! recovery: after `recovery.consecutive_rejections` ranges in a row rejected (no range accepted
//! in between) the position covariance grows by the run's mean squared innovation on every axis
//! and the heading variance by `recovery.heading_sigma_rad`², after which the ranges pass the gate
//! and pull the estimate back. One buoy rejected `recovery.buoy_consecutive_rejections` times in a
//! row while others pass has its bias state (per-buoy biases) reset to its prior. After
//! `recovery.fix_rejections` position fixes in a row rejected the position is reset to the fix.
//!
//! With the odometry window (below) a lost filter is re-started instead: when a run of
//! rejections trips, or at least `recovery.check_rejected_share` of the last
//! `recovery.check_ranges` ranges were rejected, the window's robust fix (ranges corrected by the
//! current calibration, or raw if that finds none) is compared with the filter; if they disagree
//! (χ²₂ gate of the position difference) the filter re-starts at the fix with the heading it
//! solved (`reinitialisations`); a check without a fix is counted (`lost_checks_without_fix`)
//! and the covariance inflation above applies as before.
//!
//! A start from the window's fix is provisional (`recovery.confirm_checks`): the first fix comes
//! from the fewest ranges and the shortest path that allow one, and a range bias it does not
//! model can fit there as a wrong heading, metres off with a confident covariance. Every
//! `recovery.confirm_every_ranges` ranges after a start the grown window is solved again, from
//! the raw ranges and from the ranges corrected by the filter's calibration; when neither fix
//! agrees with the filter (χ²₂ gate) it re-starts at the first with the calibration at its
//! prior (`start_corrections`); `confirm_checks` agreeing checks in a row end the checking.
//!
//! # Initialisation
//! `init.method = "trilateration"`: ranges are buffered for `init.window_s`; once they reach
//! `init.min_buoys` distinct buoys (default 4: one spare, so a wrong range shows in the residual)
//! in a usable geometry ([`crate::trilaterate()`]) the filter starts at the solution, with the
//! solution's covariance plus the range bias and scale priors propagated through it (a consider
//! covariance, with the matching cross-covariances). Until then ranges return
//! [`RangeOutcome::Waiting`] with the reason. A position fix initialises too.
//! `init.method = "prior"`: the filter starts at `init.prior_position_m`.
//!
//! **Odometry window** (planar mode with odometry, `init.odometry_window`, default on): every
//! range is also kept with the odometry's dead-reckoned pose at its time, for the last
//! `init.odometry_window_s`. While waiting, the filter starts from [`crate::window_fix()`]: a robust
//! fix over that window with the positions propagated by odometry, outliers found by sampling,
//! and the heading solved with the position once the path shows it. A stationary trilateration
//! with a spare buoy (`init.min_buoys` > 3) is tried first (it starts at once and a wrong range
//! shows in its residual), of the ranges taken within a range σ of the odometry's position now
//! (a vehicle under way is not smeared along its path); with exactly 3 buoys only the window can
//! tell a wrong range. While
//! the heading is still a mixture of hypotheses, a window fix that agrees with the mixture's
//! position and is as sure of the heading as `init.heading_max_sigma_rad` settles it.
//!
//! Heading: without a prior heading the filter has none. Once odometry arrives it splits into
//! `init.heading_hypotheses` filters with evenly spaced headings (a Gaussian sum), each updated
//! as usual and weighted by its ranges' likelihoods (the normalised innovation capped at the gate,
//! so one outlier cannot eliminate the true hypothesis); they merge (moment matching) into one
//! filter once the mixture's heading σ falls below `init.heading_max_sigma_rad`. Meanwhile the
//! estimate is the moment-matched mixture; while the vehicle stands still the hypotheses agree
//! on the position, so it is already usable.
//!
//! # Errors
//! Non-finite inputs, non-positive σ, unknown buoys, time going backwards and numerical failures
//! (a covariance that is not positive definite) are [`BuoyError`]s; the filter is left as it was.

#![allow(non_snake_case)]

use std::collections::VecDeque;

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

use crate::chi2::chi2_quantile;
use crate::config::{BiasMode, BuoyConfig, InitMethod, Mode};
use crate::error::{BuoyError, TrilaterationError};
use crate::trilaterate::{Geometry, Limits, RangeObs, trilaterate, wrap_angle};
use crate::window_fix::{WindowFix, WindowLimits, WindowRange, window_fix};

mod model;
mod types;

use model::*;
pub use types::*;

/// A range kept for initialisation.
#[derive(Debug, Clone, Copy, PartialEq)]
struct InitRange {
    t_s: f64,
    buoy: usize,
    range_m: f64,
    sigma_m: f64,
    /// The odometry's dead-reckoned position at the range, when there is odometry.
    odom_xy: Option<[f64; 2]>,
}

/// The buoy estimator (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct BuoyEkf {
    model: Model,
    ids: Vec<u32>,
    t_s: f64,
    phase: Phase,
    heading_known: bool,
    held: Option<HeldInput>,
    init_ranges: VecDeque<InitRange>,
    /// Latest depth reading: (t, z, σ).
    last_depth: Option<(f64, f64, f64)>,
    counters: Counters,
    /// Σν² of the current run of rejected ranges.
    rejection_run_nu2: f64,
    fix_run: u32,
    /// Dead reckoning of the odometry inputs: (x m, y m, ψ rad, path m), from the first input.
    odo: Option<[f64; 4]>,
    /// The odometry window of ranges (`init.odometry_window`), oldest first, with their stamps.
    window: VecDeque<(f64, WindowRange)>,
    /// The last ranges' outcomes (true: rejected), for the lost-filter check.
    recent: VecDeque<bool>,
    /// Accepted ranges of the last `range.observability_window_s`, oldest first.
    seen: VecDeque<SeenRange>,
    /// Per buoy: the time and innovation of its last accepted range that the calibration was
    /// held on (cleared by one it learned from).
    held_nu: Vec<Option<(f64, f64)>>,
    /// The filter without a doubtful range it took, run alongside until the ranges after it
    /// tell which is right.
    shadow: Option<Shadow>,
    /// A start from a window fix not yet confirmed (`recovery.confirm_checks`).
    confirming: Option<Confirming>,
}

/// A provisional start: ranges since the last check, and checks in a row that agreed.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct Confirming {
    ranges: u32,
    agreed: u32,
}

/// The branch that left out a doubtful range.
#[derive(Debug, Clone, PartialEq)]
struct Shadow {
    g: Gaussian,
    /// log p(shadow) − log p(filter), from the ranges since.
    log_odds: f64,
    ranges: u32,
    /// The buoy of the range it left out.
    buoy: usize,
}

/// Two ranges to a buoy within this many seconds whose innovations agree (within
/// `range.calibration_k`·√2 σ) show a systematic error, not an outlier: the second one teaches the
/// calibration even when its innovation is large against the position's uncertainty alone.
const SYSTEMATIC_WITHIN_S: f64 = 5.0;

/// The branches of a doubtful range (`range.doubtful_sigma`) are decided at these log odds
/// (19:1) ...
const SHADOW_DECIDE: f64 = 2.944;
/// ... or after this many ranges (the filter's branch kept).
const SHADOW_RANGES: u32 = 12;

fn finite(x: f64, what: &'static str) -> Result<f64, BuoyError> {
    if x.is_finite() { Ok(x) } else { Err(BuoyError::NonFinite(what)) }
}

fn positive(x: f64, what: &'static str) -> Result<f64, BuoyError> {
    finite(x, what)?;
    if x > 0.0 { Ok(x) } else { Err(BuoyError::NonPositiveSigma { what, value: x }) }
}

fn non_negative(x: f64, what: &'static str) -> Result<f64, BuoyError> {
    finite(x, what)?;
    if x >= 0.0 { Ok(x) } else { Err(BuoyError::NonPositiveSigma { what, value: x }) }
}

/// Largest log-weight difference kept between heading hypotheses (weights below e^−50 of the
/// best are floored there, so a hypothesis can still come back after a burst of outliers).
const MIN_LOG_WEIGHT: f64 = -50.0;

impl BuoyEkf {
    /// A filter at time `t0_s` (validates the configuration; method `prior` starts initialised).
    pub fn new(config: BuoyConfig, t0_s: f64) -> Result<Self, BuoyError> {
        validation::Validate::issues(&config).into_result().map_err(BuoyError::InvalidConfig)?;
        finite(t0_s, "t0_s")?;
        let lay = Layout::new(&config);
        let q = |p: f64, k: usize| chi2_quantile(p, k).ok_or(BuoyError::NonFinite("gate probability"));
        let model = Model {
            gate1: q(config.range.gate_probability, 1)?,
            gate_fix: q(config.range.gate_probability, lay.d)?,
            buoys: config.buoys.iter().map(|b| Vector3::from(b.position_m)).collect(),
            lay,
            cfg: config,
        };
        let ids: Vec<u32> = model.cfg.buoys.iter().map(|b| b.id).collect();
        let n_buoys = ids.len();
        let counters = Counters {
            per_buoy: ids
                .iter()
                .map(|&id| BuoyCounters { id, accepted: 0, rejected: 0, consecutive_rejected: 0 })
                .collect(),
            ..Counters::default()
        };
        let mut f = Self {
            model,
            ids,
            t_s: t0_s,
            phase: Phase::Waiting,
            heading_known: false,
            held: None,
            init_ranges: VecDeque::new(),
            last_depth: None,
            counters,
            rejection_run_nu2: 0.0,
            held_nu: vec![None; n_buoys],
            shadow: None,
            confirming: None,
            fix_run: 0,
            odo: None,
            window: VecDeque::new(),
            recent: VecDeque::new(),
            seen: VecDeque::new(),
        };
        if f.model.cfg.init.method == InitMethod::Prior {
            let i = f.model.cfg.init.clone();
            let cov = Matrix3::identity() * i.prior_position_sigma_m.powi(2);
            let mut g = f.initial_gaussian(&Vector3::from(i.prior_position_m), &cov);
            if let Some(psi) = i.prior_heading_rad {
                let l = f.model.lay;
                g.x[l.psi] = wrap_angle(psi);
                g.P[(l.psi, l.psi)] = i.prior_heading_sigma_rad.powi(2);
                f.heading_known = true;
            }
            f.phase = Phase::Single(g);
        }
        Ok(f)
    }

    /// The configuration in use.
    pub fn config(&self) -> &BuoyConfig {
        &self.model.cfg
    }

    /// The filter's time, s.
    pub fn time_s(&self) -> f64 {
        self.t_s
    }

    /// Whether the filter has a state (after trilateration, a fix or a prior).
    pub fn is_initialised(&self) -> bool {
        !matches!(self.phase, Phase::Waiting)
    }

    /// Whether the heading is known (a prior, or the hypotheses have merged).
    pub fn heading_known(&self) -> bool {
        self.heading_known
    }

    /// The counters of accepted and rejected measurements.
    pub fn counters(&self) -> &Counters {
        &self.counters
    }

    /// The share of rejected ranges among the last ones since the latest (re)start or lost
    /// check (at most `recovery.check_ranges`), with their number; `None` before any. A share
    /// at the end well below `recovery.check_rejected_share` says the estimate has recovered.
    pub fn recent_rejected_share(&self) -> Option<(f64, usize)> {
        let n = self.recent.len();
        (n > 0).then(|| (self.recent.iter().filter(|&&r| r).count() as f64 / n as f64, n))
    }

    fn buoy_index(&self, id: u32) -> Result<usize, BuoyError> {
        self.ids.iter().position(|&b| b == id).ok_or(BuoyError::UnknownBuoy(id))
    }

    /// A state at `p` with covariance `cov` for the position, priors elsewhere.
    fn initial_gaussian(&self, p: &Vector3<f64>, cov: &Matrix3<f64>) -> Gaussian {
        let l = &self.model.lay;
        let mut x = DVector::zeros(l.n);
        for k in 0..l.d {
            x[k] = p[k];
        }
        let mut P = DMatrix::from_diagonal(&self.model.prior_variances());
        for a in 0..l.d {
            for b in 0..l.d {
                P[(a, b)] = cov[(a, b)];
            }
        }
        Gaussian { x, P }
    }

    /// Advances every hypothesis by `dt` with the held input (if fresh) or constant velocity.
    fn propagate(&mut self, dt: f64) {
        if dt <= 0.0 {
            return;
        }
        let hold = self.model.cfg.motion.input_hold_s;
        let held = self.held.filter(|h| self.t_s - h.t_end_s <= hold);
        let use_input = held.is_some() && (self.heading_known || matches!(self.phase, Phase::Mixture(_)));
        let model = &self.model;
        let step = |g: &mut Gaussian| match (use_input, held) {
            (true, Some(h)) => model.input_predict(g, dt, h.v_mps, h.rate_rps * dt, h.var_v, h.var_rate * dt),
            _ => model.cv_predict(g, dt),
        };
        match &mut self.phase {
            Phase::Waiting => {}
            Phase::Single(g) => {
                step(g);
                if let Some(sh) = &mut self.shadow {
                    step(&mut sh.g);
                }
            }
            Phase::Mixture(hyps) => hyps.iter_mut().for_each(|h| step(&mut h.g)),
        }
    }

    /// Predicts to `t_s` (≥ the filter's time): with the last odometry input held if it ended
    /// less than `motion.input_hold_s` ago, else with the constant-velocity model.
    pub fn predict_to(&mut self, t_s: f64) -> Result<(), BuoyError> {
        finite(t_s, "t_s")?;
        if t_s < self.t_s {
            return Err(BuoyError::TimeWentBackwards { t_s, now_s: self.t_s });
        }
        self.propagate(t_s - self.t_s);
        self.t_s = t_s;
        Ok(())
    }

    /// Applies an odometry input over (`t_s` − dt, `t_s`]. A gap before the interval is
    /// predicted first; the part of the interval the filter has already predicted through (to a
    /// range stamped inside it) is skipped, the rest gets the input pro rata.
    pub fn predict_with_input(&mut self, t_s: f64, input: &OdometryInput) -> Result<(), BuoyError> {
        finite(t_s, "t_s")?;
        positive(input.dt_s, "odometry dt_s")?;
        finite(input.v_mps, "odometry v_mps")?;
        finite(input.dtheta_rad, "odometry dtheta_rad")?;
        non_negative(input.var_v, "odometry var_v")?;
        non_negative(input.var_dtheta, "odometry var_dtheta")?;
        if t_s < self.t_s {
            return Err(BuoyError::TimeWentBackwards { t_s, now_s: self.t_s });
        }
        let start = t_s - input.dt_s;
        if start > self.t_s {
            self.predict_to(start)?;
        }
        let o = self.odo.get_or_insert([0.0; 4]);
        let mid = o[2] + input.dtheta_rad / 2.0;
        o[0] += input.v_mps * input.dt_s * mid.cos();
        o[1] += input.v_mps * input.dt_s * mid.sin();
        o[2] = wrap_angle(o[2] + input.dtheta_rad);
        o[3] += input.v_mps.abs() * input.dt_s;
        let held = HeldInput {
            v_mps: input.v_mps,
            rate_rps: input.dtheta_rad / input.dt_s,
            var_v: input.var_v,
            var_rate: input.var_dtheta / input.dt_s,
            t_end_s: t_s,
        };
        self.held = Some(held);
        self.split_if_heading_unknown();
        let span = t_s - self.t_s;
        if span > 0.0 {
            // Apply the input (rather than whatever was held before) over the remaining span.
            self.held = Some(HeldInput { t_end_s: self.t_s, ..held });
            self.propagate(span);
            self.held = Some(held);
        }
        self.t_s = t_s;
        Ok(())
    }

    /// Odometry is present and the heading unknown: one filter becomes a Gaussian sum.
    fn split_if_heading_unknown(&mut self) {
        if self.heading_known || self.held.is_none() {
            return;
        }
        let Phase::Single(g) = &self.phase else { return };
        let n = self.model.cfg.init.heading_hypotheses;
        let psi = self.model.lay.psi;
        let sigma = std::f64::consts::PI / n as f64;
        let hyps = (0..n)
            .map(|k| {
                let mut h = g.clone();
                h.x[psi] = wrap_angle(2.0 * std::f64::consts::PI * k as f64 / n as f64);
                h.P.row_mut(psi).fill(0.0);
                h.P.column_mut(psi).fill(0.0);
                h.P[(psi, psi)] = sigma * sigma;
                Hypothesis { log_w: -(n as f64).ln(), g: h }
            })
            .collect();
        self.phase = Phase::Mixture(hyps);
    }

    /// Re-weights a mixture by the log-likelihoods and merges it once its heading is known.
    fn reweight(&mut self, log_liks: &[f64]) {
        let Phase::Mixture(hyps) = &mut self.phase else { return };
        for (h, ll) in hyps.iter_mut().zip(log_liks) {
            h.log_w += ll;
        }
        let max = hyps.iter().map(|h| h.log_w).fold(f64::NEG_INFINITY, f64::max);
        for h in hyps.iter_mut() {
            h.log_w = (h.log_w - max).max(MIN_LOG_WEIGHT);
        }
        let norm = hyps.iter().map(|h| h.log_w.exp()).sum::<f64>().ln();
        for h in hyps.iter_mut() {
            h.log_w -= norm;
        }
        let merged = self.model.moment_match(hyps);
        let psi = self.model.lay.psi;
        if merged.P[(psi, psi)].sqrt() <= self.model.cfg.init.heading_max_sigma_rad {
            self.phase = Phase::Single(merged);
            self.heading_known = true;
        }
    }

    /// Runs `f` on every hypothesis (a single filter is one); returns the heaviest hypothesis's
    /// result. All-or-nothing: on an error no hypothesis changes.
    fn for_each_hypothesis(
        &mut self,
        f: impl Fn(&Model, &mut Gaussian) -> Result<UpdateInfo, BuoyError>,
    ) -> Result<UpdateInfo, BuoyError> {
        match &mut self.phase {
            Phase::Waiting => Err(BuoyError::NotInitialised),
            Phase::Single(g) => {
                let mut next = g.clone();
                let info = f(&self.model, &mut next)?;
                *g = next;
                Ok(info)
            }
            Phase::Mixture(hyps) => {
                let mut next = hyps.clone();
                let mut infos = Vec::with_capacity(next.len());
                for h in next.iter_mut() {
                    infos.push(f(&self.model, &mut h.g)?);
                }
                let best = (0..next.len()).max_by(|&a, &b| next[a].log_w.total_cmp(&next[b].log_w)).unwrap_or(0);
                *hyps = next;
                let log_liks: Vec<f64> = infos.iter().map(|i| i.log_lik).collect();
                self.reweight(&log_liks);
                Ok(infos[best])
            }
        }
    }

    /// A range to buoy `buoy_id` at the filter's time (call [`Self::predict_to`] first).
    pub fn update_range(&mut self, buoy_id: u32, range_m: f64, sigma_m: f64) -> Result<RangeOutcome, BuoyError> {
        non_negative(range_m, "range_m")?;
        positive(sigma_m, "range sigma_m")?;
        let j = self.buoy_index(buoy_id)?;
        // The range joins the odometry window for the fixes below; on an error it leaves again
        // (the filter is left as it was).
        let pushed = self.push_window(j, range_m, sigma_m);
        let result = self.update_range_at(j, range_m, sigma_m);
        if result.is_err() && pushed {
            self.window.pop_back();
        } else {
            self.prune_window();
        }
        result
    }

    /// [`Self::update_range`] after the validation and the window.
    fn update_range_at(&mut self, j: usize, range_m: f64, sigma_m: f64) -> Result<RangeOutcome, BuoyError> {
        if matches!(self.phase, Phase::Waiting) {
            let r = InitRange { t_s: self.t_s, buoy: j, range_m, sigma_m, odom_xy: self.odo.map(|o| [o[0], o[1]]) };
            if !self.window_enabled() {
                return Ok(self.try_trilaterate(r));
            }
            // With a spare buoy (`init.min_buoys` above the 2 horizontal unknowns plus one) the
            // stationary trilateration (of the ranges taken within a σ of here) sees a wrong range
            // in its residual and starts at once; without one only the window can tell.
            if self.model.cfg.init.min_buoys > 3 {
                let stationary = self.try_trilaterate(r);
                if stationary == RangeOutcome::Initialised {
                    return Ok(stationary);
                }
            }
            return Ok(self.try_window_init());
        }
        if matches!(self.phase, Phase::Mixture(_)) && self.window_enabled() {
            // The heading is still unknown: once the path shows it, the window's fix gives it.
            if let Phase::Mixture(h) = &self.phase {
                let merged = self.model.moment_match(h);
                if let Ok(fix) = self.window_fix_with(Some(&merged))
                    && self.position_distance2(&merged, &fix) <= self.model.gate_fix
                    && let Some(h) = fix.heading_rad
                    && fix.heading_sigma_rad <= self.model.cfg.init.heading_max_sigma_rad
                {
                    // Take the heading; the mixture's position agrees with the fix and keeps its
                    // correlations with the calibration states.
                    let mut g = merged;
                    let psi = self.model.lay.psi;
                    g.x[psi] = h;
                    g.P.row_mut(psi).fill(0.0);
                    g.P.column_mut(psi).fill(0.0);
                    g.P[(psi, psi)] = fix.heading_sigma_rad.max(1f64.to_radians()).powi(2);
                    self.phase = Phase::Single(g);
                    self.heading_known = true;
                    self.recent.clear();
                    return Ok(RangeOutcome::Initialised);
                }
            }
        }
        let single = matches!(self.phase, Phase::Single(_));
        if self.seen.is_empty() {
            self.seed_seen();
        }
        let next = self.seen_range(j, sigma_m)?;
        let z_sigma = self.last_depth.filter(|&(t, _, _)| self.t_s - t <= self.model.cfg.range.observability_window_s);
        let anchor = self.path_anchor();
        let unobservable = self.model.unobservable_calibration(&self.seen, &next, z_sigma.map(|(_, _, s)| s), anchor);
        let nu_pre = match &self.phase {
            Phase::Single(g) => range_m - self.model.range_model(&g.x, j).0,
            Phase::Mixture(h) => range_m - self.model.range_model(&self.model.moment_match(h).x, j).0,
            Phase::Waiting => 0.0,
        };
        let ck = self.model.cfg.range.calibration_k;
        let systematic = self.held_nu[j].is_some_and(|(t, nu)| {
            self.t_s - t <= SYSTEMATIC_WITHIN_S && (nu_pre - nu).abs() <= ck * std::f64::consts::SQRT_2 * sigma_m
        });
        let before = match &self.phase {
            Phase::Single(g) if self.shadow.is_none() && self.model.cfg.range.doubtful_sigma > 0.0 => Some(g.clone()),
            _ => None,
        };
        let info =
            self.for_each_hypothesis(|m, g| m.range_update(g, j, range_m, sigma_m, &unobservable, systematic))?;
        if let Some(mut sh) = self.shadow.take()
            && matches!(self.phase, Phase::Single(_))
        {
            if let Ok(si) = self.model.range_update(&mut sh.g, j, range_m, sigma_m, &unobservable, systematic) {
                sh.log_odds += si.log_lik - info.log_lik;
                sh.ranges += 1;
                if sh.log_odds >= SHADOW_DECIDE {
                    self.phase = Phase::Single(sh.g);
                    // The range it left out counts as rejected after all.
                    let c = &mut self.counters;
                    c.outlier_branch_switches += 1;
                    c.accepted = c.accepted.saturating_sub(1);
                    c.rejected += 1;
                    let b = &mut c.per_buoy[sh.buoy];
                    b.accepted = b.accepted.saturating_sub(1);
                    b.rejected += 1;
                } else if sh.log_odds > -SHADOW_DECIDE && sh.ranges < SHADOW_RANGES {
                    self.shadow = Some(sh);
                }
            }
        } else if let Some(g) = before
            && info.accepted
            && info.nis > self.model.cfg.range.doubtful_sigma.powi(2)
        {
            self.shadow = Some(Shadow { g, log_odds: 0.0, ranges: 0, buoy: j });
        }
        if info.accepted {
            self.held_nu[j] = info.held.then_some((self.t_s, nu_pre));
        }
        let checks = self.model.cfg.recovery.check_ranges;
        self.recent.push_back(!info.accepted);
        while self.recent.len() > checks {
            self.recent.pop_front();
        }
        let c = &mut self.counters;
        if info.accepted {
            c.accepted += 1;
            c.consecutive_rejected = 0;
            c.per_buoy[j].accepted += 1;
            c.per_buoy[j].consecutive_rejected = 0;
            c.calibration_held += u64::from(info.held);
            c.calibration_unobservable += u64::from(!info.held && !unobservable.is_empty());
            self.rejection_run_nu2 = 0.0;
            self.seen.push_back(next);
            let window = self.model.cfg.range.observability_window_s;
            while self.seen.front().is_some_and(|r| self.t_s - r.t_s > window) {
                self.seen.pop_front();
            }
            if !self.confirm_start() {
                self.check_lost(false);
            }
            return Ok(RangeOutcome::Accepted { innovation_m: info.nu0, nis: info.nis, weight: info.weight });
        }
        c.rejected += 1;
        c.consecutive_rejected += 1;
        c.per_buoy[j].rejected += 1;
        c.per_buoy[j].consecutive_rejected += 1;
        self.rejection_run_nu2 += info.nu0 * info.nu0;
        let mut recovery = false;
        if single {
            let rc = self.model.cfg.recovery.clone();
            if self.counters.consecutive_rejected >= rc.consecutive_rejections {
                let mean_nu2 = self.rejection_run_nu2 / f64::from(self.counters.consecutive_rejected);
                if !self.check_lost(true) {
                    self.inflate_after_rejections(mean_nu2, rc.heading_sigma_rad);
                }
                self.counters.consecutive_rejected = 0;
                self.rejection_run_nu2 = 0.0;
                recovery = true;
            } else if self.counters.per_buoy[j].consecutive_rejected >= rc.buoy_consecutive_rejections
                && self.model.lay.n_bias > 1
            {
                self.reset_bias(j);
            } else {
                self.check_lost(false);
            }
        } else {
            self.check_lost(false);
        }
        if !recovery {
            self.confirm_start();
        }
        Ok(RangeOutcome::Rejected { innovation_m: info.nu0, nis: info.nis, recovery })
    }

    /// Fills the observability window from the odometry window (just after the start): the
    /// geometry of the ranges the start was made from, placed along the odometry's path
    /// through the estimate now (turned by the estimated heading once it is known).
    fn seed_seen(&mut self) {
        let (Some(odo), Ok(e)) = (self.odo, self.estimate()) else { return };
        let window = self.model.cfg.range.observability_window_s;
        let turn = e.heading_rad.map_or(0.0, |h| h - odo[2]);
        let (sn, cs) = turn.sin_cos();
        for (t, w) in &self.window {
            if self.t_s - t > window {
                continue;
            }
            let Some(j) = self.ids.iter().position(|&id| id == w.buoy_id) else { continue };
            let (dx, dy) = (w.odom_pose[0] - odo[0], w.odom_pose[1] - odo[1]);
            let mut p = e.position_m;
            p.x += cs * dx - sn * dy;
            p.y += sn * dx + cs * dy;
            if self.model.lay.d == 3 {
                p.z = w.height_m;
            }
            self.seen.push_back(SeenRange {
                t_s: *t,
                buoy: j,
                position_m: p,
                odom_xy: Some([w.odom_pose[0], w.odom_pose[1]]),
                sigma_m: w.sigma_m,
            });
        }
    }

    /// Range `j` as seen from the current estimate (for the observability check).
    fn seen_range(&self, j: usize, sigma_m: f64) -> Result<SeenRange, BuoyError> {
        let x = match &self.phase {
            Phase::Waiting => return Err(BuoyError::NotInitialised),
            Phase::Single(g) => g.x.clone(),
            Phase::Mixture(h) => self.model.moment_match(h).x,
        };
        let odom_xy = self.odo.map(|o| [o[0], o[1]]);
        Ok(SeenRange { t_s: self.t_s, buoy: j, position_m: self.model.position(&x), odom_xy, sigma_m })
    }

    /// The odometry path's anchor for the observability check (with odometry and a heading).
    fn path_anchor(&self) -> Option<PathAnchor> {
        let o = self.odo?;
        let e = self.estimate().ok()?;
        let heading = e.heading_rad?;
        Some(PathAnchor { position_m: e.position_m, odom_xy: [o[0], o[1]], turn_rad: heading - o[2] })
    }

    /// The vehicle's known height now: planar mode's fixed height, or in spatial mode the
    /// latest depth reading if it is at most `init.window_s` old.
    fn known_height(&self) -> Option<(f64, f64)> {
        match self.model.lay.d {
            2 => Some((self.model.cfg.planar_height_m, 0.0)),
            _ => self.last_depth.filter(|d| self.t_s - d.0 <= self.model.cfg.init.window_s).map(|d| (d.1, d.2)),
        }
    }

    /// Whether the odometry window is in use: `init.odometry_window`, odometry seen, and the
    /// height known (planar mode, or a recent depth reading in spatial mode).
    fn window_enabled(&self) -> bool {
        self.model.cfg.init.odometry_window && self.odo.is_some() && self.known_height().is_some()
    }

    /// Adds a range to the odometry window (with the odometry's pose now); whether it did.
    fn push_window(&mut self, j: usize, range_m: f64, sigma_m: f64) -> bool {
        if !self.model.cfg.init.odometry_window {
            return false;
        }
        // Before the first odometry input the vehicle is where the odometry will start.
        let o = self.odo.unwrap_or([0.0; 4]);
        // Without a known height yet (3-D before the first depth reading) the height is filled
        // in by the first reading if it comes within `init.window_s` (see `update_depth`), else
        // the range stays out of the fix (NaN).
        let height_m = self.known_height().map_or(f64::NAN, |h| h.0);
        self.window.push_back((
            self.t_s,
            WindowRange {
                odom_pose: [o[0], o[1], o[2]],
                path_m: o[3],
                height_m,
                buoy_id: self.ids[j],
                buoy_m: self.model.buoys[j],
                range_m,
                sigma_m,
            },
        ));
        true
    }

    /// Drops the window's ranges older than `init.odometry_window_s` or beyond its size.
    fn prune_window(&mut self) {
        let i = &self.model.cfg.init;
        let (span, max) = (i.odometry_window_s, i.odometry_window_max_ranges);
        while self.window.front().is_some_and(|w| w.0 < self.t_s - span) || self.window.len() > max {
            self.window.pop_front();
        }
    }

    /// The robust fix of the window, with the ranges corrected by the calibration (scale and
    /// bias means) of `calibration`, or taken as they are.
    fn window_fix_with(&self, calibration: Option<&Gaussian>) -> Result<WindowFix, TrilaterationError> {
        let l = &self.model.lay;
        let i = &self.model.cfg.init;
        let obs: Vec<WindowRange> = self
            .window
            .iter()
            .filter(|(_, w)| w.height_m.is_finite())
            .map(|(_, w)| {
                let mut w = *w;
                if let Some(g) = calibration {
                    let j = self.ids.iter().position(|&id| id == w.buoy_id).unwrap_or(0);
                    let s = l.scale.map_or(0.0, |k| g.x[k]);
                    let beta = l.bias_of(j).map_or(0.0, |k| g.x[k]);
                    w.range_m = ((w.range_m - beta) / (1.0 + s)).max(0.0);
                }
                w
            })
            .collect();
        let limits = WindowLimits {
            min_buoys: i.min_buoys,
            min_inliers: i.odometry_window_min_inliers,
            min_inlier_fraction: i.odometry_window_min_inlier_fraction,
            drift_fraction: i.odometry_drift_fraction,
            ambiguity_margin: i.odometry_window_ambiguity_margin,
            ..WindowLimits::default()
        };
        window_fix(&obs, &limits)
    }

    /// Waiting with the odometry window: starts from its robust fix when it has one.
    fn try_window_init(&mut self) -> RangeOutcome {
        match self.window_fix_with(None) {
            Err(e) => RangeOutcome::Waiting(e),
            Ok(fix) => {
                self.start_from_fix(&fix, None);
                RangeOutcome::Initialised
            }
        }
    }

    /// (Re)starts the filter at a window fix: the position (and heading, when the fix has one)
    /// from the fix, the velocity at its prior; the calibration states from `keep` (a filter
    /// being re-started) or their priors.
    fn start_from_fix(&mut self, fix: &WindowFix, keep: Option<Gaussian>) {
        let l = self.model.lay;
        let mut cov = fix.covariance_m2 * fix.normalised_rms.max(1.0).powi(2);
        if l.d == 3 {
            // z comes from the depth reading.
            cov[(2, 2)] = self.known_height().map_or(1.0, |(_, sigma)| sigma * sigma).max(1e-6);
        }
        let mut g = match keep {
            Some(mut g) => {
                self.model.reset_position(&mut g, &fix.position_m, &cov);
                let prior = self.model.prior_variances();
                for k in l.d..2 * l.d {
                    g.x[k] = 0.0;
                    g.P.row_mut(k).fill(0.0);
                    g.P.column_mut(k).fill(0.0);
                    g.P[(k, k)] = prior[k];
                }
                g
            }
            None => self.initial_gaussian(&fix.position_m, &cov),
        };
        g.P.row_mut(l.psi).fill(0.0);
        g.P.column_mut(l.psi).fill(0.0);
        match fix.heading_rad {
            Some(h) => {
                g.x[l.psi] = h;
                // The heading's σ scaled like the position's; with their correlation.
                let scale = fix.normalised_rms.max(1.0).powi(2);
                let var = (fix.heading_sigma_rad.powi(2) * scale).max(1f64.to_radians().powi(2));
                g.P[(l.psi, l.psi)] = var;
                let c = position_heading_cov(&cov, var, &(fix.position_heading_cov_m_rad * scale));
                for a in 0..2 {
                    g.P[(a, l.psi)] = c[a];
                    g.P[(l.psi, a)] = c[a];
                }
                self.heading_known = true;
                self.phase = Phase::Single(g);
            }
            None => {
                g.P[(l.psi, l.psi)] = std::f64::consts::PI.powi(2);
                self.heading_known = false;
                self.phase = Phase::Single(g);
                self.split_if_heading_unknown();
            }
        }
        self.init_ranges.clear();
        self.recent.clear();
        self.held_nu.iter_mut().for_each(|h| *h = None);
        self.shadow = None;
        self.confirming = (self.model.cfg.recovery.confirm_checks > 0).then(Confirming::default);
    }

    /// The check of a provisional start (see `recovery.confirm_checks`), after each range:
    /// every `recovery.confirm_every_ranges` ranges the window is solved again, as at the start
    /// (raw ranges) and with the ranges corrected by the filter's calibration; when both
    /// disagree with the filter it re-starts at the first with the calibration at its prior.
    /// Returns whether it re-started.
    fn confirm_start(&mut self) -> bool {
        let rc = &self.model.cfg.recovery;
        let (every, needed) = (rc.confirm_every_ranges, rc.confirm_checks);
        let Some(mut c) = self.confirming else { return false };
        c.ranges += 1;
        self.confirming = Some(c);
        if c.ranges < every || !self.window_enabled() {
            return false;
        }
        c.ranges = 0;
        self.confirming = Some(c);
        let g = match &self.phase {
            Phase::Single(g) => g.clone(),
            Phase::Mixture(h) => self.model.moment_match(h),
            Phase::Waiting => return false,
        };
        let Ok(fix) = self.window_fix_with(None) else { return false };
        self.counters.start_checks += 1;
        // The raw fix is off by what the calibration learned since the start (a scale, a
        // bias): a filter that agrees with the fix of the ranges corrected by its own
        // calibration holds too.
        let agrees = |f: &WindowFix| self.position_distance2(&g, f) <= self.model.gate_fix;
        if agrees(&fix) || self.window_fix_with(Some(&g)).is_ok_and(|f| agrees(&f)) {
            c.agreed += 1;
            self.confirming = (c.agreed < needed).then_some(c);
            return false;
        }
        self.start_from_fix(&fix, None);
        self.counters.start_corrections += 1;
        true
    }

    /// Squared Mahalanobis distance between the planar positions of `g` and `fix`.
    fn position_distance2(&self, g: &Gaussian, fix: &WindowFix) -> f64 {
        let dp = nalgebra::Vector2::new(fix.position_m.x - g.x[0], fix.position_m.y - g.x[1]);
        let S = nalgebra::Matrix2::new(g.P[(0, 0)], g.P[(0, 1)], g.P[(1, 0)], g.P[(1, 1)])
            + fix.covariance_m2.fixed_view::<2, 2>(0, 0);
        S.try_inverse().map_or(f64::INFINITY, |inv| dp.dot(&(inv * dp)))
    }

    /// The lost-filter check (see `recovery.check_rejected_share`): with `forced` (a run of
    /// rejections) or too many rejections among the last ranges, asks the window for a robust
    /// fix and re-starts the filter there if the two disagree. Returns whether it re-started.
    fn check_lost(&mut self, forced: bool) -> bool {
        if !self.window_enabled() {
            return false;
        }
        let rc = &self.model.cfg.recovery;
        let rejected = self.recent.iter().filter(|&&r| r).count();
        let due = self.recent.len() >= rc.check_ranges
            && rejected as f64 >= rc.check_rejected_share * self.recent.len() as f64;
        if !(forced || due) {
            return false;
        }
        self.recent.clear();
        let g = match &self.phase {
            Phase::Single(g) => g.clone(),
            Phase::Mixture(h) => self.model.moment_match(h),
            Phase::Waiting => return false,
        };
        let (fix, keep) = match self.window_fix_with(Some(&g)) {
            Ok(f) => (f, true),
            Err(_) => match self.window_fix_with(None) {
                Ok(f) => (f, false),
                Err(_) => {
                    self.counters.lost_checks_without_fix += 1;
                    return false;
                }
            },
        };
        if self.position_distance2(&g, &fix) <= self.model.gate_fix {
            return false;
        }
        self.start_from_fix(&fix, keep.then_some(g));
        self.counters.reinitialisations += 1;
        true
    }

    fn inflate_after_rejections(&mut self, mean_nu2: f64, heading_sigma: f64) {
        self.shadow = None;
        let l = self.model.lay;
        let heading_known = self.heading_known;
        if let Phase::Single(g) = &mut self.phase {
            for k in 0..l.d {
                g.P[(k, k)] += mean_nu2;
            }
            if heading_known {
                g.P[(l.psi, l.psi)] += heading_sigma * heading_sigma;
            }
        }
        self.counters.recoveries += 1;
        self.counters.consecutive_rejected = 0;
        self.rejection_run_nu2 = 0.0;
    }

    fn reset_bias(&mut self, j: usize) {
        let Some(i) = self.model.lay.bias_of(j) else { return };
        self.shadow = None;
        let var = self.model.cfg.range.bias_prior_sigma_m.powi(2);
        if let Phase::Single(g) = &mut self.phase {
            g.P.row_mut(i).fill(0.0);
            g.P.column_mut(i).fill(0.0);
            g.P[(i, i)] = var;
        }
        self.counters.bias_resets += 1;
        self.counters.per_buoy[j].consecutive_rejected = 0;
    }

    /// Buffers a range for initialisation and tries a trilateration.
    fn try_trilaterate(&mut self, r: InitRange) -> RangeOutcome {
        let window = self.model.cfg.init.window_s;
        self.init_ranges.push_back(r);
        while self.init_ranges.front().is_some_and(|o| o.t_s < self.t_s - window) {
            self.init_ranges.pop_front();
        }
        // With odometry, only the ranges taken while the vehicle was within a range σ of where
        // it is now (the trilateration takes them as taken from one place; a range from before
        // the first odometry input counts as taken where the odometry started).
        if let Some(o) = self.odo {
            self.init_ranges.retain(|r| {
                let p = r.odom_xy.unwrap_or([0.0, 0.0]);
                (p[0] - o[0]).hypot(p[1] - o[1]) <= r.sigma_m.max(0.05)
            });
        }
        let obs: Vec<RangeObs> = self
            .init_ranges
            .iter()
            .map(|o| RangeObs {
                buoy_id: self.ids[o.buoy],
                buoy_m: self.model.buoys[o.buoy],
                range_m: o.range_m,
                sigma_m: o.sigma_m,
            })
            .collect();
        let c = &self.model.cfg;
        let geometry = match c.mode {
            Mode::Planar => Geometry::Planar { height_m: c.planar_height_m },
            Mode::Spatial => Geometry::Spatial {
                z_constraint: self.last_depth.filter(|d| self.t_s - d.0 <= window).map(|d| (d.1, d.2)),
            },
        };
        let limits = Limits {
            min_buoys: c.init.min_buoys,
            max_condition: c.init.max_condition,
            max_normalised_rms: c.init.max_normalised_rms,
            huber_k: c.range.huber_k,
        };
        match trilaterate(&obs, geometry, &limits) {
            Err(e) => RangeOutcome::Waiting(e),
            Ok(sol) => {
                let mut g = self.initial_gaussian(&sol.position_m, &sol.covariance_m2);
                self.add_consider_covariance(&mut g, &sol.sensitivity, &sol.position_m);
                self.phase = Phase::Single(g);
                // The ranges it started from join the observability window (taken at the
                // solution, as the trilateration took them).
                self.seen.clear();
                for o in &self.init_ranges {
                    let (t_s, buoy, sigma_m) = (o.t_s, o.buoy, o.sigma_m);
                    let odom_xy = o.odom_xy;
                    self.seen.push_back(SeenRange { t_s, buoy, position_m: sol.position_m, odom_xy, sigma_m });
                }
                self.init_ranges.clear();
                self.split_if_heading_unknown();
                RangeOutcome::Initialised
            }
        }
    }

    /// The trilateration assumed zero bias and unit scale; their prior uncertainty propagates
    /// through the solution's sensitivity K: e_p = −K·G·e_β, so P_pp += K·G·P_β·Gᵀ·Kᵀ and
    /// P_pβ = −K·G·P_β (G = ∂r/∂(s, β)).
    fn add_consider_covariance(&self, g: &mut Gaussian, K: &DMatrix<f64>, p: &Vector3<f64>) {
        let l = &self.model.lay;
        let mut G = DMatrix::zeros(self.init_ranges.len(), l.n);
        for (i, o) in self.init_ranges.iter().enumerate() {
            if let Some(k) = l.scale {
                G[(i, k)] = (p - self.model.buoys[o.buoy]).norm();
            }
            if let Some(k) = l.bias_of(o.buoy) {
                G[(i, k)] = 1.0;
            }
        }
        let P0 = DMatrix::from_diagonal(&self.model.prior_variances());
        let M = K * G; // D × n, non-zero only in the scale and bias columns
        let add = &M * &P0 * M.transpose();
        let cross = -(&M * &P0);
        for a in 0..l.d {
            for b in 0..l.d {
                g.P[(a, b)] += add[(a, b)];
            }
            for col in l.scale.into_iter().chain(l.bias.into_iter().flat_map(|b| b..b + l.n_bias)) {
                g.P[(a, col)] = cross[(a, col)];
                g.P[(col, a)] = cross[(a, col)];
            }
        }
    }

    /// A pressure depth (positive down: z = −depth) at the filter's time; spatial mode only.
    pub fn update_depth(&mut self, depth_m: f64, sigma_m: f64) -> Result<FixOutcome, BuoyError> {
        if self.model.lay.d == 2 {
            return Err(BuoyError::NotInPlanarMode("a depth reading"));
        }
        finite(depth_m, "depth_m")?;
        positive(sigma_m, "depth sigma_m")?;
        if self.last_depth.is_none() {
            let since = self.t_s - self.model.cfg.init.window_s;
            for (_, w) in self.window.iter_mut().filter(|(t, w)| *t >= since && w.height_m.is_nan()) {
                w.height_m = -depth_m;
            }
        }
        self.last_depth = Some((self.t_s, -depth_m, sigma_m));
        if matches!(self.phase, Phase::Waiting) {
            return Ok(FixOutcome::Stored);
        }
        let info = self.for_each_hypothesis(|m, g| m.depth_update(g, -depth_m, sigma_m))?;
        if let Some(sh) = &mut self.shadow
            && self.model.depth_update(&mut sh.g, -depth_m, sigma_m).is_err()
        {
            self.shadow = None;
        }
        if info.accepted {
            Ok(FixOutcome::Accepted { nis: info.nis })
        } else {
            self.counters.depth_rejected += 1;
            Ok(FixOutcome::Rejected { nis: info.nis })
        }
    }

    /// A position fix (GPS at the surface) with its covariance at the filter's time; in planar
    /// mode only x, y and their 2 × 2 block are used.
    pub fn update_position_fix(
        &mut self,
        position_m: &Vector3<f64>,
        covariance_m2: &Matrix3<f64>,
    ) -> Result<FixOutcome, BuoyError> {
        if !position_m.iter().chain(covariance_m2.iter()).all(|v| v.is_finite()) {
            return Err(BuoyError::NonFinite("position fix"));
        }
        let d = self.model.lay.d;
        let block = covariance_m2.view((0, 0), (d, d)).into_owned();
        if (&block - block.transpose()).amax() > 1e-9 * block.amax().max(1.0) || block.cholesky().is_none() {
            return Err(BuoyError::NotPositiveDefinite("position fix covariance"));
        }
        if matches!(self.phase, Phase::Waiting) {
            self.phase = Phase::Single(self.initial_gaussian(position_m, covariance_m2));
            self.init_ranges.clear();
            self.split_if_heading_unknown();
            return Ok(FixOutcome::Initialised);
        }
        // A position fix settles the position: no branch is kept past it.
        self.shadow = None;
        let info = self.for_each_hypothesis(|m, g| m.fix_update(g, position_m, covariance_m2))?;
        if info.accepted {
            self.fix_run = 0;
            return Ok(FixOutcome::Accepted { nis: info.nis });
        }
        self.counters.fixes_rejected += 1;
        self.fix_run += 1;
        if self.fix_run >= self.model.cfg.recovery.fix_rejections {
            self.fix_run = 0;
            let model = &self.model;
            match &mut self.phase {
                Phase::Single(g) => model.reset_position(g, position_m, covariance_m2),
                Phase::Mixture(hyps) => {
                    hyps.iter_mut().for_each(|h| model.reset_position(&mut h.g, position_m, covariance_m2))
                }
                Phase::Waiting => {}
            }
            return Ok(FixOutcome::Reset);
        }
        Ok(FixOutcome::Rejected { nis: info.nis })
    }

    /// The estimate at the filter's time (the moment-matched mixture while the heading is
    /// unknown).
    pub fn estimate(&self) -> Result<Estimate, BuoyError> {
        let (g, hypotheses) = match &self.phase {
            Phase::Waiting => return Err(BuoyError::NotInitialised),
            Phase::Single(g) => (g.clone(), 1),
            Phase::Mixture(h) => (self.model.moment_match(h), h.len()),
        };
        let l = &self.model.lay;
        let d = l.d;
        let mut covariance_m2 = Matrix3::zeros();
        let mut velocity_covariance = Matrix3::zeros();
        let mut velocity_mps = Vector3::zeros();
        for a in 0..d {
            velocity_mps[a] = g.x[d + a];
            for b in 0..d {
                covariance_m2[(a, b)] = g.P[(a, b)];
                velocity_covariance[(a, b)] = g.P[(d + a, d + b)];
            }
        }
        let with_sigma = |i: usize| (g.x[i], g.P[(i, i)].max(0.0).sqrt());
        let biases = match self.model.cfg.range.bias {
            BiasMode::None => Vec::new(),
            _ => (0..self.ids.len())
                .filter_map(|j| {
                    l.bias_of(j).map(|i| BiasEstimate {
                        buoy_id: self.ids[j],
                        bias_m: g.x[i],
                        sigma_m: g.P[(i, i)].max(0.0).sqrt(),
                    })
                })
                .collect(),
        };
        Ok(Estimate {
            t_s: self.t_s,
            position_m: self.model.position(&g.x),
            covariance_m2,
            velocity_mps,
            velocity_covariance,
            heading_rad: self.heading_known.then_some(g.x[l.psi]),
            heading_sigma_rad: g.P[(l.psi, l.psi)].max(0.0).sqrt(),
            range_scale: l.scale.map(with_sigma),
            turn_bias_rps: l.turn_bias.map(with_sigma),
            biases,
            hypotheses,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{BuoyEntry, InitMethod};
    use nalgebra::Vector2;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    use rand_xoshiro::Xoshiro256PlusPlus;

    const BUOYS_XY: [[f64; 2]; 5] = [[0.0, 0.0], [60.0, 0.0], [60.0, 60.0], [0.0, 60.0], [30.0, 75.0]];

    fn planar_config(bias: BiasMode) -> BuoyConfig {
        BuoyConfig {
            mode: Mode::Planar,
            buoys: BUOYS_XY
                .iter()
                .enumerate()
                .map(|(i, b)| BuoyEntry { id: 10 + i as u32, position_m: [b[0], b[1], 0.0] })
                .collect(),
            range: crate::config::RangeConfig { bias, ..Default::default() },
            ..BuoyConfig::default()
        }
    }

    /// A simulated drive: true speed `v` and turn rate `omega` from `start` (x, y, ψ), odometry
    /// at 10 Hz (noisy, with a turn-rate bias), one range every 0.25 s round robin, stamped
    /// between odometry rows.
    struct Sim {
        seconds: f64,
        v: f64,
        omega: f64,
        start: (f64, f64, f64),
        odometry: bool,
        range_sigma: f64,
        scale: f64,
        biases: Vec<f64>,
        turn_bias: f64,
        seed: u64,
    }

    impl Default for Sim {
        fn default() -> Self {
            Self {
                seconds: 300.0,
                v: 2.0,
                omega: 0.1,
                start: (30.0, 10.0, 0.0),
                odometry: true,
                range_sigma: 0.3,
                scale: 0.02,
                biases: vec![0.5; 5],
                turn_bias: 0.01,
                seed: 7,
            }
        }
    }

    /// (t, truth, estimate) after every range.
    type Track = Vec<(f64, Vector2<f64>, Option<Vector2<f64>>)>;

    /// Runs the filter; returns it and its track.
    fn simulate(cfg: BuoyConfig, s: &Sim) -> (BuoyEkf, Track) {
        simulate_with(cfg, s, |_, _| {})
    }

    /// [`simulate`], calling `hook` with the time and the filter after every range.
    fn simulate_with(cfg: BuoyConfig, s: &Sim, mut hook: impl FnMut(f64, &mut BuoyEkf)) -> (BuoyEkf, Track) {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(s.seed);
        let n01 = Normal::new(0.0, 1.0).unwrap();
        let (speed_sigma, turn_sigma, dt) = (0.05, 0.002, 0.1);
        let mut ekf = BuoyEkf::new(cfg, 0.0).unwrap();
        let (mut x, mut y, mut psi) = s.start;
        let mut out = Vec::new();
        let steps = (s.seconds / dt) as usize;
        let mut next_buoy = 0;
        for k in 0..steps {
            let t = k as f64 * dt;
            // A range at t + 0.05 every 0.25 s (on the steps where one falls in (t, t + 0.1]).
            let t_range = t + 0.05;
            if ((t_range / 0.25).round() * 0.25 - t_range).abs() < 0.05 + 1e-9 && k > 0 {
                let j = next_buoy % 5;
                next_buoy += 1;
                // Truth at t_range: half a step on.
                let hm = psi + s.omega * 0.025;
                let (xr, yr) = (x + s.v * 0.05 * hm.cos(), y + s.v * 0.05 * hm.sin());
                let d = (xr - BUOYS_XY[j][0]).hypot(yr - BUOYS_XY[j][1]);
                let r = (1.0 + s.scale) * d + s.biases[j] + s.range_sigma * n01.sample(&mut rng);
                ekf.predict_to(t_range).unwrap();
                ekf.update_range(10 + j as u32, r, s.range_sigma).unwrap();
                hook(t_range, &mut ekf);
                let est = ekf.estimate().ok().map(|e| e.position_m.xy());
                out.push((t_range, Vector2::new(xr, yr), est));
            }
            // Truth over (t, t + dt], then the odometry row stamped t + dt.
            let hm = psi + s.omega * dt / 2.0;
            x += s.v * dt * hm.cos();
            y += s.v * dt * hm.sin();
            psi += s.omega * dt;
            if s.odometry {
                let input = OdometryInput {
                    dt_s: dt,
                    v_mps: s.v + speed_sigma * n01.sample(&mut rng),
                    dtheta_rad: (s.omega + s.turn_bias) * dt + turn_sigma * n01.sample(&mut rng),
                    var_v: speed_sigma * speed_sigma,
                    var_dtheta: turn_sigma * turn_sigma,
                };
                ekf.predict_with_input(t + dt, &input).unwrap();
            } else {
                ekf.predict_to(t + dt).unwrap();
            }
        }
        (ekf, out)
    }

    fn rmse_after(track: &Track, t0: f64) -> f64 {
        let e: Vec<f64> =
            track.iter().filter(|r| r.0 >= t0).map(|r| (r.2.expect("initialised") - r.1).norm_squared()).collect();
        (e.iter().sum::<f64>() / e.len() as f64).sqrt()
    }

    #[test]
    fn converges_on_a_circular_path_with_noise_scale_and_bias() {
        let s = Sim::default();
        let cfg = planar_config(BiasMode::Global);
        let (ekf, track) = simulate(cfg, &s);
        let rmse = rmse_after(&track, 100.0);
        assert!(rmse < 0.3, "RMSE after 100 s: {rmse}");
        let e = ekf.estimate().unwrap();
        assert!(ekf.heading_known() && e.hypotheses == 1);
        let true_heading = wrap_angle(s.start.2 + s.omega * s.seconds);
        assert!(wrap_angle(e.heading_rad.unwrap() - true_heading).abs() < 0.05, "heading {:?}", e.heading_rad);
        let (scale, scale_sigma) = e.range_scale.unwrap();
        assert!((scale - s.scale).abs() < 3.0 * scale_sigma + 1e-3, "scale {scale} ± {scale_sigma}");
        let b = e.biases[0];
        assert!((b.bias_m - 0.5).abs() < 0.15 && (b.bias_m - 0.5).abs() < 3.0 * b.sigma_m, "bias {b:?}");
        assert!(b.sigma_m < 0.1, "bias σ shrank to {}", b.sigma_m);
        let (turn_bias, tb_sigma) = e.turn_bias_rps.unwrap();
        assert!((turn_bias - s.turn_bias).abs() < 3.0 * tb_sigma + 1e-3, "turn bias {turn_bias} ± {tb_sigma}");
        assert_eq!(ekf.counters().recoveries, 0);
        // Consistency: the final error is within the covariance (NEES < χ²₂(0.999)).
        let (t, truth, est) = *track.last().unwrap();
        let err = est.unwrap() - truth;
        let p2 = e.covariance_m2.fixed_view::<2, 2>(0, 0).into_owned();
        let nees = err.dot(&(p2.try_inverse().unwrap() * err));
        assert!(nees < 13.8, "NEES {nees} at {t} s");
    }

    #[test]
    fn the_bias_estimate_converges_toward_the_true_bias() {
        let biases = vec![0.3, -0.2, 0.6, 0.0, 0.9];
        let s = Sim { seconds: 600.0, scale: 0.0, biases: biases.clone(), start: (40.0, 20.0, 1.0), ..Sim::default() };
        let mut cfg = planar_config(BiasMode::PerBuoy);
        cfg.range.estimate_scale = false;
        let (ekf, track) = simulate(cfg, &s);
        let e = ekf.estimate().unwrap();
        for (b, truth) in e.biases.iter().zip(&biases) {
            assert!((b.bias_m - truth).abs() < 0.2, "buoy {}: {} ± {} vs {truth}", b.buoy_id, b.bias_m, b.sigma_m);
            assert!((b.bias_m - truth).abs() < 3.5 * b.sigma_m, "buoy {}: {} ± {}", b.buoy_id, b.bias_m, b.sigma_m);
            assert!(b.sigma_m < 0.5 * 1.0, "σ {} did not shrink from the prior", b.sigma_m);
        }
        assert!(rmse_after(&track, 300.0) < 0.35);
    }

    #[test]
    fn converges_on_a_straight_path_without_odometry() {
        let s = Sim { odometry: false, omega: 0.0, v: 0.5, start: (10.0, 20.0, 0.3), seconds: 120.0, ..Sim::default() };
        let mut cfg = planar_config(BiasMode::Global);
        cfg.motion.accel_sigma_mps2 = 0.05; // a vehicle that keeps its velocity
        let (ekf, track) = simulate(cfg, &s);
        let rmse = rmse_after(&track, 40.0);
        assert!(rmse < 0.5, "RMSE {rmse}");
        let e = ekf.estimate().unwrap();
        let v = e.velocity_mps;
        assert!(
            (v.xy() - Vector2::new(0.3f64.cos(), 0.3f64.sin()) * 0.5).norm() < 0.15,
            "velocity {v} {}",
            e.velocity_covariance
        );
        assert!(!ekf.heading_known(), "no odometry: the heading stays unknown");
    }

    #[test]
    fn injected_outliers_are_gated_counted_and_leave_the_estimate_unchanged() {
        let s = Sim { seconds: 100.0, ..Sim::default() };
        let (mut ekf, _) = simulate(planar_config(BiasMode::Global), &s);
        let before = ekf.estimate().unwrap();
        let (rejected, rejected_12) = (ekf.counters().rejected, ekf.counters().buoy(12).unwrap().rejected);
        let d = (before.position_m.xy() - Vector2::new(60.0, 60.0)).norm();
        for k in 0..3 {
            let outcome = ekf.update_range(12, d + 15.0 + k as f64, 0.3).unwrap();
            assert!(matches!(outcome, RangeOutcome::Rejected { recovery: false, .. }), "{outcome:?}");
        }
        assert_eq!(ekf.counters().rejected, rejected + 3);
        assert_eq!(ekf.counters().buoy(12).unwrap().rejected, rejected_12 + 3);
        assert_eq!(ekf.counters().consecutive_rejected, 3);
        assert_eq!(ekf.estimate().unwrap(), before, "rejected ranges do not touch the state");
        // A good range resets the run.
        let good = ekf.update_range(10, before.position_m.xy().norm() * 1.02 + 0.5, 0.3).unwrap();
        assert!(matches!(good, RangeOutcome::Accepted { .. }), "{good:?}");
        assert_eq!(ekf.counters().consecutive_rejected, 0);
    }

    #[test]
    fn a_doubtful_range_the_next_ranges_contradict_is_undone() {
        // Known calibration, a position known to 0.5 m: a range 3σ off its prediction is taken
        // (down-weighted) and moves the position ~1 m toward buoy 10. Ranges from where the
        // vehicle really is then decide between the filter and its copy without that range.
        let mut cfg = planar_config(BiasMode::None);
        cfg.range.estimate_scale = false;
        let start = Vector3::new(20.0, 30.0, 0.0);
        let range_from = |ekf: &BuoyEkf, j: usize, p: &Vector3<f64>| {
            let mut x = DVector::zeros(ekf.model.lay.n);
            x[0] = p.x;
            x[1] = p.y;
            ekf.model.range_model(&x, j).0
        };
        let run = |cfg: &BuoyConfig, truth: Vector3<f64>| {
            let mut ekf = BuoyEkf::new(cfg.clone(), 0.0).unwrap();
            ekf.update_position_fix(&start, &(Matrix3::identity() * 0.25)).unwrap();
            let sd = (0.25f64 + 0.09).sqrt();
            let doubtful = range_from(&ekf, 0, &start) - 3.0 * sd;
            let outcome = ekf.update_range(10, doubtful, 0.3).unwrap();
            assert!(matches!(outcome, RangeOutcome::Accepted { weight, .. } if weight < 0.5), "{outcome:?}");
            let moved = (ekf.estimate().unwrap().position_m - start).norm();
            assert!(moved > 0.8, "the doubtful range moved the position {moved} m");
            for k in 0..6 {
                let j = [0, 2, 1, 3, 0, 4][k];
                let r = range_from(&ekf, j, &truth);
                ekf.update_range(10 + j as u32, r, 0.3).unwrap();
            }
            let error = (ekf.estimate().unwrap().position_m - truth).norm();
            let c = ekf.counters();
            // Undone, the doubtful range counts as rejected.
            let undone = c.outlier_branch_switches;
            assert_eq!((c.accepted, c.rejected), (7 - undone, undone));
            assert_eq!(c.buoy(10).unwrap().rejected, undone);
            (undone, error, ekf.shadow.as_ref().map(|c| c.log_odds))
        };
        // The vehicle is where the fix put it: the range was a gross error.
        let (switches, error, _) = run(&cfg, start);
        assert_eq!(switches, 1);
        assert!(error < 0.05, "after the switch: {error} m off");
        let mut off = cfg.clone();
        off.range.doubtful_sigma = 0.0;
        let (switches, error_without, _) = run(&off, start);
        assert_eq!(switches, 0);
        assert!(error_without > 4.0 * error.max(0.02), "without the copy: {error_without} m off");
        // The vehicle is where the doubtful range put it: no switch, the odds are for the filter.
        let toward = start - start.normalize() * 1.0;
        let (switches, error, copy) = run(&cfg, toward);
        assert_eq!(switches, 0);
        assert!(copy.is_none_or(|log_odds| log_odds < -1.0), "log odds of the copy {copy:?}");
        assert!(error < 0.3, "{error} m off");
    }

    #[test]
    fn a_filter_started_far_off_recovers_through_the_rejection_counter() {
        let s = Sim { seconds: 120.0, scale: 0.0, biases: vec![0.0; 5], ..Sim::default() };
        let mut cfg = planar_config(BiasMode::None);
        cfg.range.estimate_scale = false;
        cfg.init.method = InitMethod::Prior;
        // 25 m off with a confident 0.5 m σ; heading right.
        cfg.init.prior_position_m = [s.start.0 + 20.0, s.start.1 + 15.0, 0.0];
        cfg.init.prior_position_sigma_m = 0.5;
        cfg.init.prior_heading_rad = Some(s.start.2);
        // With the odometry window the lost filter is re-started at the window's robust fix.
        let (ekf, track) = simulate(cfg.clone(), &s);
        assert!(ekf.counters().reinitialisations >= 1, "{:?}", ekf.counters());
        assert!(ekf.counters().rejected >= 8);
        assert!(rmse_after(&track, 60.0) < 0.5, "RMSE {}", rmse_after(&track, 60.0));
        // Without it, the covariance inflation after a run of rejections brings it back.
        cfg.init.odometry_window = false;
        let (ekf, track) = simulate(cfg, &s);
        assert!(ekf.counters().recoveries >= 1);
        assert_eq!(ekf.counters().reinitialisations, 0);
        assert!(ekf.counters().rejected >= 8);
        assert!(rmse_after(&track, 60.0) < 0.5, "RMSE {}", rmse_after(&track, 60.0));
    }

    #[test]
    fn a_start_the_grown_window_disagrees_with_is_corrected() {
        // The filter (re)starts at 20 s from a fix 3 m off with a confident 0.3 m σ, the heading
        // right: as a first fix from a short window can be. The checks of the start solve the
        // grown window again and re-start it where the vehicle is. (Ranges with a 0.3 m bias,
        // no scale error.)
        let s = Sim { seconds: 60.0, scale: 0.0, biases: vec![0.3; 5], ..Sim::default() };
        let run = |cfg: &BuoyConfig| {
            let mut started = false;
            simulate_with(cfg.clone(), &s, |t, ekf| {
                if t >= 20.0 && !started {
                    started = true;
                    let e = ekf.estimate().unwrap();
                    let wrong = WindowFix {
                        position_m: e.position_m + Vector3::new(2.0, -2.2, 0.0),
                        covariance_m2: Matrix3::from_diagonal(&Vector3::new(0.09, 0.09, 0.0)),
                        heading_rad: e.heading_rad,
                        heading_sigma_rad: 0.02,
                        position_heading_cov_m_rad: Vector2::zeros(),
                        inliers: vec![],
                        buoys: 3,
                        normalised_rms: 1.0,
                    };
                    ekf.start_from_fix(&wrong, None);
                }
            })
        };
        let cfg = planar_config(BiasMode::Global);
        let (ekf, track) = run(&cfg);
        let c = ekf.counters();
        assert_eq!(c.start_corrections, 1, "{c:?}");
        assert!(c.start_checks > u64::from(cfg.recovery.confirm_checks), "{c:?}");
        // Corrected within the first check (5 ranges, 1.25 s) of the wrong start.
        let error_at = |t0: f64| track.iter().find(|r| r.0 >= t0).map(|r| (r.2.unwrap() - r.1).norm()).unwrap();
        assert!(error_at(21.5) < 0.7, "{} m off at 21.5 s", error_at(21.5));
        let mut off = cfg.clone();
        off.recovery.confirm_checks = 0;
        let (ekf, track_off) = run(&off);
        assert_eq!((ekf.counters().start_corrections, ekf.counters().start_checks), (0, 0));
        let error_off = |t0: f64| track_off.iter().find(|r| r.0 >= t0).map(|r| (r.2.unwrap() - r.1).norm()).unwrap();
        assert!(error_off(21.5) > 1.5, "without the checks: {} m off at 21.5 s", error_off(21.5));
        let (with, without) = (rmse_after(&track, 20.0), rmse_after(&track_off, 20.0));
        eprintln!("RMSE after 20 s: {with:.3} m with the checks, {without:.3} m without");
        assert!(with < 0.7 * without, "RMSE after 20 s: {with} with the checks, {without} without");
    }

    #[test]
    fn nan_and_invalid_inputs_are_errors_and_leave_the_filter_unchanged() {
        let s = Sim { seconds: 30.0, ..Sim::default() };
        let (mut ekf, _) = simulate(planar_config(BiasMode::Global), &s);
        let before = ekf.clone();
        let u = OdometryInput { dt_s: 0.1, v_mps: 1.0, dtheta_rad: 0.0, var_v: 0.01, var_dtheta: 1e-4 };
        let t = ekf.time_s();
        assert_eq!(ekf.update_range(10, f64::NAN, 0.3), Err(BuoyError::NonFinite("range_m")));
        assert!(matches!(ekf.update_range(10, 5.0, -0.3), Err(BuoyError::NonPositiveSigma { .. })));
        assert!(matches!(ekf.update_range(10, 5.0, 0.0), Err(BuoyError::NonPositiveSigma { .. })));
        assert!(matches!(ekf.update_range(10, -5.0, 0.3), Err(BuoyError::NonPositiveSigma { .. })));
        assert_eq!(ekf.update_range(99, 5.0, 0.3), Err(BuoyError::UnknownBuoy(99)));
        assert!(ekf.predict_to(f64::NAN).is_err());
        assert!(matches!(ekf.predict_to(t - 1.0), Err(BuoyError::TimeWentBackwards { .. })));
        assert!(ekf.predict_with_input(t + 0.1, &OdometryInput { v_mps: f64::INFINITY, ..u }).is_err());
        assert!(ekf.predict_with_input(t + 0.1, &OdometryInput { dt_s: 0.0, ..u }).is_err());
        assert!(ekf.predict_with_input(t + 0.1, &OdometryInput { var_v: -1.0, ..u }).is_err());
        assert_eq!(ekf.update_depth(3.0, 0.1), Err(BuoyError::NotInPlanarMode("a depth reading")));
        let p = Vector3::new(1.0, 2.0, 0.0);
        assert!(ekf.update_position_fix(&Vector3::new(f64::NAN, 0.0, 0.0), &Matrix3::identity()).is_err());
        assert_eq!(
            ekf.update_position_fix(&p, &-Matrix3::identity()),
            Err(BuoyError::NotPositiveDefinite("position fix covariance"))
        );
        assert_eq!(ekf, before, "nothing changed");
    }

    /// A vehicle standing among 3 buoys (planar, scale and global bias states) whose ranges all
    /// read 0.5 m long: from one place a scale cannot be told from a bias (nor either from the
    /// position), so neither is learned (counted); once the vehicle moves, the ranges determine
    /// both and they are. Returns (scale, its σ, bias, ranges the calibration did not learn
    /// from) after standing and after moving.
    fn stand_then_move(fraction: f64) -> [(f64, f64, f64, u64); 2] {
        let buoys = [[0.0, 0.0], [40.0, 0.0], [20.0, 35.0]];
        let mut cfg = BuoyConfig {
            mode: Mode::Planar,
            buoys: buoys
                .iter()
                .enumerate()
                .map(|(i, b)| BuoyEntry { id: i as u32, position_m: [b[0], b[1], 0.0] })
                .collect(),
            ..BuoyConfig::default()
        };
        cfg.init.method = InitMethod::Prior;
        cfg.init.prior_position_m = [20.0, 12.0, 0.0];
        cfg.init.prior_position_sigma_m = 1.0;
        cfg.init.prior_heading_rad = Some(0.0);
        cfg.init.min_buoys = 3;
        cfg.range.observable_sigma_fraction = fraction;
        let mut ekf = BuoyEkf::new(cfg, 0.0).unwrap();
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(3);
        let n01 = Normal::new(0.0, 1.0).unwrap();
        let mut out = [(0.0, 0.0, 0.0, 0); 2];
        for (phase, slot) in out.iter_mut().enumerate() {
            for k in 0..400 {
                let t = (phase * 400 + k + 1) as f64 * 0.25;
                // Standing at (20, 12) heading along x, then driving an 8 m circle at 0.8 m/s.
                let (omega, radius) = (0.1, 8.0);
                let (p, v) = if phase == 0 {
                    (Vector2::new(20.0, 12.0), 0.0)
                } else {
                    let a = omega * (t - 100.0);
                    (Vector2::new(20.0 + radius * a.sin(), 20.0 - radius * a.cos()), omega * radius)
                };
                let w = if phase == 0 { 0.0 } else { omega };
                let input = OdometryInput { dt_s: 0.25, v_mps: v, dtheta_rad: w * 0.25, var_v: 1e-4, var_dtheta: 1e-6 };
                ekf.predict_with_input(t, &input).unwrap();
                let j = k % 3;
                let d = (p - Vector2::new(buoys[j][0], buoys[j][1])).norm();
                let r = d + 0.5 + 0.1 * n01.sample(&mut rng);
                ekf.update_range(j as u32, r, 0.1).unwrap();
            }
            let e = ekf.estimate().unwrap();
            let (s, ss) = e.range_scale.unwrap();
            let c = ekf.counters();
            *slot = (s, ss, e.biases[0].bias_m, c.calibration_unobservable + c.calibration_held);
        }
        out
    }

    #[test]
    fn calibration_the_ranges_do_not_determine_is_held_until_they_do() {
        let prior = crate::config::RangeConfig::default().scale_prior_sigma;
        let [stood, moved] = stand_then_move(5.0);
        // Standing: neither the scale nor the bias learned (both at their priors).
        assert!(stood.3 >= 399, "held on {} of 400 ranges", stood.3);
        assert!(
            stood.0 == 0.0 && stood.1 == prior && stood.2 == 0.0,
            "scale {} ± {}, bias {}",
            stood.0,
            stood.1,
            stood.2
        );
        // Moving: both learned, the 0.5 m went to the bias.
        assert!(moved.1 < 0.5 * prior, "scale σ {} after moving", moved.1);
        assert!(moved.0.abs() < 0.01 && (moved.2 - 0.5).abs() < 0.15, "scale {} bias {}", moved.0, moved.2);
        // Without the check the split of the error between them while standing is the priors'.
        let [free, _] = stand_then_move(0.0);
        assert!(free.0.abs() > 0.005, "scale {} learned from one place", free.0);
    }

    #[test]
    fn a_non_positive_definite_covariance_is_an_error_not_a_panic() {
        let mut cfg = planar_config(BiasMode::Global);
        cfg.init.method = InitMethod::Prior;
        let mut ekf = BuoyEkf::new(cfg, 0.0).unwrap();
        if let Phase::Single(g) = &mut ekf.phase {
            g.P *= -1.0;
        }
        let before = ekf.clone();
        assert_eq!(ekf.update_range(10, 5.0, 0.3), Err(BuoyError::NotPositiveDefinite("innovation covariance S")));
        assert_eq!(ekf, before);
    }

    #[test]
    fn invalid_configuration_is_refused_with_the_keys() {
        let mut cfg = planar_config(BiasMode::Global);
        cfg.range.gate_probability = 2.0;
        match BuoyEkf::new(cfg, 0.0) {
            Err(BuoyError::InvalidConfig(p)) => assert_eq!(p[0].key, "range.gate_probability"),
            other => panic!("{other:?}"),
        }
        let mut cfg = planar_config(BiasMode::Global);
        cfg.init.odometry_window_ambiguity_margin = -1.0;
        match BuoyEkf::new(cfg, 0.0) {
            Err(BuoyError::InvalidConfig(p)) => assert_eq!(p[0].key, "init.odometry_window_ambiguity_margin"),
            other => panic!("{other:?}"),
        }
        let mut cfg = planar_config(BiasMode::Global);
        cfg.range.doubtful_sigma = 0.5;
        match BuoyEkf::new(cfg, 0.0) {
            Err(BuoyError::InvalidConfig(p)) => assert_eq!(p[0].key, "range.doubtful_sigma"),
            other => panic!("{other:?}"),
        }
    }

    fn central_difference(f: impl Fn(&DVector<f64>) -> DVector<f64>, x: &DVector<f64>) -> DMatrix<f64> {
        let h = 1e-6;
        let m = f(x).len();
        let mut J = DMatrix::zeros(m, x.len());
        for k in 0..x.len() {
            let (mut a, mut b) = (x.clone(), x.clone());
            a[k] += h;
            b[k] -= h;
            J.set_column(k, &((f(&a) - f(&b)) / (2.0 * h)));
        }
        J
    }

    fn random_state(model: &Model, seed: u64) -> DVector<f64> {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let n = Normal::new(0.0, 1.0).unwrap();
        let mut x = DVector::from_fn(model.lay.n, |_, _| n.sample(&mut rng));
        for k in 0..model.lay.d {
            x[k] = 30.0 + 20.0 * n.sample(&mut rng);
        }
        x[model.lay.psi] = 0.7;
        if let Some(i) = model.lay.scale {
            x[i] = 0.03;
        }
        x
    }

    #[test]
    fn the_range_jacobian_matches_finite_differences() {
        for (mode, bias) in
            [(Mode::Planar, BiasMode::PerBuoy), (Mode::Spatial, BiasMode::Global), (Mode::Planar, BiasMode::None)]
        {
            let mut cfg = planar_config(bias);
            cfg.mode = mode;
            cfg.planar_height_m = -3.0; // a known height difference in planar mode
            cfg.buoys[2].position_m[2] = 1.5;
            let ekf = BuoyEkf::new(cfg, 0.0).unwrap();
            let m = &ekf.model;
            for j in 0..5 {
                let x = random_state(m, j as u64);
                let (_, H, _) = m.range_model(&x, j);
                let numeric = central_difference(|x| DVector::from_element(1, m.range_model(x, j).0), &x);
                assert!((&H - &numeric).amax() < 1e-6, "{mode:?} buoy {j}:\n{H}\n{numeric}");
            }
        }
    }

    #[test]
    fn the_odometry_jacobians_match_finite_differences() {
        for mode in [Mode::Planar, Mode::Spatial] {
            let mut cfg = planar_config(BiasMode::Global);
            cfg.mode = mode;
            let ekf = BuoyEkf::new(cfg, 0.0).unwrap();
            let m = &ekf.model;
            let x = random_state(m, 3);
            let (dt, v, dtheta) = (0.1, 1.7, 0.05);
            let (_, F, G) = m.input_model(&x, dt, v, dtheta);
            let numeric_F = central_difference(|x| m.input_model(x, dt, v, dtheta).0, &x);
            assert!((&F - &numeric_F).amax() < 1e-6, "{mode:?} F:\n{F}\n{numeric_F}");
            let u = DVector::from_column_slice(&[v, dtheta]);
            let numeric_G = central_difference(|u| m.input_model(&x, dt, u[0], u[1]).0, &u);
            assert!((&G - &numeric_G).amax() < 1e-6, "{mode:?} G:\n{G}\n{numeric_G}");
        }
    }

    #[test]
    fn collinear_buoys_keep_the_filter_waiting() {
        // A table on one line is refused outright …
        let mut cfg = planar_config(BiasMode::Global);
        for (i, b) in cfg.buoys.iter_mut().enumerate() {
            b.position_m = [10.0 * i as f64, 5.0 * i as f64, 0.0];
        }
        assert!(matches!(BuoyEkf::new(cfg.clone(), 0.0), Err(BuoyError::InvalidConfig(p)) if p[0].key == "buoys"));
        // … and when only the buoys on one line answer, the filter waits.
        cfg.buoys[3].position_m = [0.0, 60.0, 0.0];
        cfg.buoys[4].position_m = [30.0, 75.0, 0.0];
        cfg.init.min_buoys = 3;
        let mut ekf = BuoyEkf::new(cfg, 0.0).unwrap();
        for k in 0..10u32 {
            let b = &ekf.config().buoys[k as usize % 3].position_m.clone();
            let r = (b[0] - 3.0).hypot(b[1] - 20.0);
            ekf.predict_to(f64::from(k) * 0.1).unwrap();
            let outcome = ekf.update_range(10 + k % 3, r, 0.1).unwrap();
            if k >= 3 {
                assert!(
                    matches!(outcome, RangeOutcome::Waiting(TrilaterationError::DegenerateGeometry(_))),
                    "{outcome:?}"
                );
            }
        }
        assert!(!ekf.is_initialised());
        assert_eq!(ekf.estimate(), Err(BuoyError::NotInitialised));
    }

    #[test]
    fn a_filter_started_while_the_vehicle_moves_in_3d_starts_where_it_is_not_along_its_path() {
        // What a buoy EKF restarted mid-mission sees: a vehicle at 12 m depth moving at 1.5 m/s
        // on a circle, ranges to the five surface buoys every second (4 % read up to 12 m long),
        // depth at 10 Hz, odometry at 10 Hz. It must start near the truth, not where a
        // trilateration that takes the moving vehicle for a standing one would put it.
        let run = |window: bool| {
            let mut cfg = planar_config(BiasMode::Global);
            cfg.mode = Mode::Spatial;
            cfg.init.odometry_window = window;
            let mut ekf = BuoyEkf::new(cfg, 0.0).unwrap();
            let mut rng = Xoshiro256PlusPlus::seed_from_u64(11);
            let n = Normal::new(0.0, 1.0).unwrap();
            let (radius, speed, z) = (20.0, 1.5, -12.0);
            let omega = speed / radius;
            let truth = |t: f64| Vector3::new(30.0 + radius * (omega * t).cos(), 30.0 + radius * (omega * t).sin(), z);
            let mut worst_after_start: f64 = 0.0;
            let mut started = None;
            for k in 1..=1200 {
                let t = f64::from(k) * 0.1;
                let input = OdometryInput {
                    dt_s: 0.1,
                    v_mps: speed + 0.02 * n.sample(&mut rng),
                    dtheta_rad: omega * 0.1 + 0.001 * n.sample(&mut rng),
                    var_v: 0.02f64.powi(2),
                    var_dtheta: 0.001f64.powi(2),
                };
                ekf.predict_with_input(t, &input).unwrap();
                if t >= 3.0 {
                    // The depth sensor comes up 3 s late: until then a 3-D fix from surface buoys
                    // has a mirror image and the filter waits, while the vehicle moves 4.5 m.
                    ekf.update_depth(-z + 0.05 * n.sample(&mut rng), 0.05).unwrap();
                }
                if k % 10 == 0 {
                    for (j, xy) in BUOYS_XY.iter().enumerate() {
                        let b = Vector3::new(xy[0], xy[1], 0.0);
                        let mut r = (truth(t) - b).norm() + 0.3 * n.sample(&mut rng);
                        if rand::RngExt::random_bool(&mut rng, 0.04) {
                            r += rand::RngExt::random_range(&mut rng, 1.0..12.0);
                        }
                        if ekf.update_range(10 + j as u32, r, 0.3).unwrap() == RangeOutcome::Initialised {
                            started.get_or_insert(t);
                        }
                    }
                    if let (Some(_), Ok(e)) = (started, ekf.estimate()) {
                        worst_after_start = worst_after_start.max((e.position_m - truth(t)).norm());
                    }
                }
            }
            (started.expect("started"), worst_after_start, ekf.heading_known())
        };
        let (t0, worst, heading_known) = run(true);
        assert!(t0 <= 15.0, "started at {t0} s");
        assert!(worst < 1.0, "worst error since the start: {worst} m");
        assert!(heading_known);
        // Without the window the stationary trilateration starts it, from the ranges of the
        // instant the depth came (not the 3 s of ranges taken along 4.5 m of path).
        let (t0, worst, _) = run(false);
        assert!(t0 <= 4.0, "started at {t0} s");
        assert!(worst < 1.0, "without the window: worst error {worst} m");
    }

    #[test]
    fn surface_buoys_in_3d_wait_for_a_depth_reading_then_track_depth() {
        let mut cfg = planar_config(BiasMode::Global);
        cfg.mode = Mode::Spatial;
        let mut ekf = BuoyEkf::new(cfg, 0.0).unwrap();
        let truth = Vector3::new(25.0, 35.0, -12.0);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(5);
        let n = Normal::new(0.0, 0.2).unwrap();
        let mut range = |ekf: &mut BuoyEkf, j: usize| {
            let b = Vector3::new(BUOYS_XY[j][0], BUOYS_XY[j][1], 0.0);
            let r = (truth - b).norm() + n.sample(&mut rng);
            ekf.update_range(10 + j as u32, r, 0.2).unwrap()
        };
        for j in 0..5 {
            let outcome = range(&mut ekf, j);
            if j >= 3 {
                assert!(
                    matches!(outcome, RangeOutcome::Waiting(TrilaterationError::DegenerateGeometry(_))),
                    "{outcome:?}"
                );
            }
        }
        assert_eq!(ekf.update_depth(12.0, 0.05).unwrap(), FixOutcome::Stored);
        assert_eq!(range(&mut ekf, 0), RangeOutcome::Initialised);
        for k in 1..200 {
            ekf.predict_to(f64::from(k) * 0.2).unwrap();
            range(&mut ekf, k as usize % 5);
            if k % 5 == 0 {
                assert!(matches!(ekf.update_depth(12.0, 0.05).unwrap(), FixOutcome::Accepted { .. }));
            }
        }
        let e = ekf.estimate().unwrap();
        assert!((e.position_m - truth).norm() < 0.5, "{} vs {truth}", e.position_m);
        assert!((e.position_m.z - truth.z).abs() < 0.1, "below the surface: z = {}", e.position_m.z);
    }

    #[test]
    fn a_position_fix_initialises_and_rejected_fixes_in_a_row_reset_the_position() {
        let mut ekf = BuoyEkf::new(planar_config(BiasMode::Global), 0.0).unwrap();
        let cov = Matrix3::identity() * 0.25;
        assert_eq!(ekf.update_position_fix(&Vector3::new(10.0, 20.0, 0.0), &cov).unwrap(), FixOutcome::Initialised);
        let e = ekf.estimate().unwrap();
        assert_eq!(e.position_m, Vector3::new(10.0, 20.0, 0.0));
        assert!((e.covariance_m2[(0, 0)] - 0.25).abs() < 1e-12 && e.covariance_m2[(2, 2)] == 0.0);
        assert!(matches!(
            ekf.update_position_fix(&Vector3::new(10.3, 20.0, 0.0), &cov).unwrap(),
            FixOutcome::Accepted { .. }
        ));
        let far = Vector3::new(50.0, -20.0, 0.0);
        assert!(matches!(ekf.update_position_fix(&far, &cov).unwrap(), FixOutcome::Rejected { .. }));
        assert_eq!(ekf.update_position_fix(&far, &cov).unwrap(), FixOutcome::Reset);
        assert_eq!(ekf.estimate().unwrap().position_m, far);
        assert_eq!(ekf.counters().fixes_rejected, 2);
    }

    #[test]
    fn a_calibration_error_two_ranges_agree_on_is_learned_and_an_outlier_is_not() {
        // Started at the true position (σ 0.1 m) with the range scale 3 % off: a range to the buoy
        // 71 m away reads 2.1 m shorter than predicted, too much for the position alone, so the
        // calibration is held on it; a second range to that buoy agreeing with it shows a
        // systematic error and teaches the scale; after a gross error the next range does not.
        let mut cfg = planar_config(BiasMode::Global);
        cfg.range.observable_sigma_fraction = 0.0;
        let start = Vector3::new(10.0, 10.0, 0.0);
        let d = (Vector2::new(60.0, 60.0) - start.xy()).norm();
        let run = |ranges: &[f64]| {
            let mut ekf = BuoyEkf::new(cfg.clone(), 0.0).unwrap();
            ekf.update_position_fix(&start, &(Matrix3::identity() * 0.01)).unwrap();
            let k = ekf.model.lay.scale.unwrap();
            let Phase::Single(g) = &mut ekf.phase else { panic!("a fix starts a single filter") };
            g.x[k] = 0.03;
            let mut scales = Vec::new();
            for &r in ranges {
                let outcome = ekf.update_range(12, r, 0.3).unwrap();
                assert!(matches!(outcome, RangeOutcome::Accepted { .. }), "{outcome:?}");
                scales.push(ekf.estimate().unwrap().range_scale.unwrap().0);
            }
            (scales, ekf.counters().calibration_held)
        };
        let (scales, held) = run(&[d, d]);
        assert!((scales[0] - 0.03).abs() < 1e-9, "the first range holds the scale: {scales:?}");
        assert!(scales[1] < 0.015, "the second, agreeing, teaches it: {scales:?}");
        assert_eq!(held, 1);
        let (scales, held) = run(&[d - 5.0, d]);
        assert!(scales.iter().all(|s| (s - 0.03).abs() < 1e-9), "an outlier confirms nothing: {scales:?}");
        assert_eq!(held, 2);
    }

    #[test]
    fn a_range_inside_an_odometry_interval_gets_the_input_pro_rata() {
        let mut cfg = planar_config(BiasMode::Global);
        cfg.init.method = InitMethod::Prior;
        cfg.init.prior_position_m = [5.0, 5.0, 0.0];
        cfg.init.prior_heading_rad = Some(0.4);
        let u = OdometryInput { dt_s: 0.1, v_mps: 2.0, dtheta_rad: 0.02, var_v: 0.01, var_dtheta: 1e-4 };
        let (mut a, mut b) = (BuoyEkf::new(cfg.clone(), 0.0).unwrap(), BuoyEkf::new(cfg, 0.0).unwrap());
        for k in 1..=20 {
            let t = f64::from(k) * 0.1;
            a.predict_with_input(t, &u).unwrap();
            if k > 1 {
                b.predict_to(t - 0.037).unwrap(); // held input up to here...
            }
            b.predict_with_input(t, &u).unwrap(); // ...and the rest of the interval
        }
        let (ea, eb) = (a.estimate().unwrap(), b.estimate().unwrap());
        // The exact arc at constant speed and turn rate; the midpoint rule is second order.
        let (w, psi0) = (0.2, 0.4);
        let exact = Vector2::new(5.0, 5.0)
            + Vector2::new((psi0 + w * 2.0f64).sin() - psi0.sin(), psi0.cos() - (psi0 + w * 2.0f64).cos()) * (2.0 / w);
        for e in [&ea, &eb] {
            assert!((e.position_m.xy() - exact).norm() < 1e-3, "{} vs {exact}", e.position_m);
        }
        assert!((ea.heading_rad.unwrap() - eb.heading_rad.unwrap()).abs() < 1e-12);
        assert!((ea.heading_rad.unwrap() - (0.4 + 20.0 * 0.02)).abs() < 1e-12);
    }
}

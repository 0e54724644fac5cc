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
mod start;
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
        Gaussian::new(x, P)
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

    /// Marks the estimate now as a published fix, and returns the cross-covariance of the
    /// position error at the previously marked fix with the position error now,
    /// cov(e_prev, e_now) (m², the position block: x, y and in spatial mode z; zeros elsewhere),
    /// carried through every prediction and update in between (docs/EQUATIONS.md §5.1a). `None`
    /// when there is no previous mark or it was lost: a re-start, a position reset, a Gaussian sum
    /// (heading not yet known) or an undone range since.
    pub fn mark_fix(&mut self) -> Option<Matrix3<f64>> {
        let d = self.model.lay.d;
        if let Some(sh) = &mut self.shadow {
            // The shadow branch's error against this fix is not tracked.
            sh.g.cross = None;
        }
        match &mut self.phase {
            Phase::Single(g) => {
                let prev = g.cross.take().map(|X| {
                    let mut c = Matrix3::zeros();
                    for a in 0..d {
                        for b in 0..d {
                            c[(a, b)] = X[(a, b)];
                        }
                    }
                    c
                });
                g.cross = Some(g.P.rows(0, d).into_owned());
                prev
            }
            Phase::Mixture(hyps) => {
                for h in hyps.iter_mut() {
                    h.g.cross = None;
                }
                None
            }
            Phase::Waiting => None,
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
mod tests;

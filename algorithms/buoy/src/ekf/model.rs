//! The filter's state-space model (EQUATIONS §1-§3): the state layout, prediction with the
//! odometry, the range and fix updates with their Jacobians, on one Gaussian hypothesis.

#![allow(non_snake_case)]

use std::collections::VecDeque;

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

use crate::config::{BiasMode, BuoyConfig, Mode};
use crate::error::BuoyError;
use crate::trilaterate::wrap_angle;

/// Indices of the state vector (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Layout {
    /// Position dimension D (2 or 3); p = 0..D, v = D..2D.
    pub(crate) d: usize,
    pub(crate) psi: usize,
    pub(crate) turn_bias: Option<usize>,
    pub(crate) scale: Option<usize>,
    pub(crate) bias: Option<usize>,
    pub(crate) n_bias: usize,
    pub(crate) n: usize,
}

impl Layout {
    pub(crate) fn new(cfg: &BuoyConfig) -> Self {
        let d = match cfg.mode {
            Mode::Planar => 2,
            Mode::Spatial => 3,
        };
        let psi = 2 * d;
        let mut n = psi + 1;
        let mut take = |on: bool| {
            on.then(|| {
                n += 1;
                n - 1
            })
        };
        let turn_bias = take(cfg.motion.estimate_turn_bias);
        let scale = take(cfg.range.estimate_scale);
        let n_bias = match cfg.range.bias {
            BiasMode::None => 0,
            BiasMode::Global => 1,
            BiasMode::PerBuoy => cfg.buoys.len(),
        };
        let bias = (n_bias > 0).then_some(n);
        n += n_bias;
        Self { d, psi, turn_bias, scale, bias, n_bias, n }
    }

    pub(crate) fn bias_of(&self, buoy: usize) -> Option<usize> {
        match self.n_bias {
            0 => None,
            1 => self.bias,
            _ => self.bias.map(|b| b + buoy),
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Gaussian {
    pub(crate) x: DVector<f64>,
    pub(crate) P: DMatrix<f64>,
    /// cov(e_m, e): the cross-covariance of the position error at the last published fix (the
    /// mark, d rows) with this state's error (n columns), carried through every prediction
    /// (·Fᵀ) and update (·(I − KH)ᵀ) since (docs/EQUATIONS.md §5.1a); `None` when not known
    /// (no mark yet, or a reset or merge since).
    pub(crate) cross: Option<DMatrix<f64>>,
}

impl Gaussian {
    /// A Gaussian with no mark.
    pub(crate) fn new(x: DVector<f64>, P: DMatrix<f64>) -> Self {
        Self { x, P, cross: None }
    }

    /// The error of state `i` no longer depends on the mark's (a reset to a prior): its column
    /// of the cross-covariance is zero.
    pub(crate) fn forget_state(&mut self, i: usize) {
        if let Some(X) = &mut self.cross {
            X.column_mut(i).fill(0.0);
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Hypothesis {
    pub(crate) log_w: f64,
    pub(crate) g: Gaussian,
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Phase {
    Waiting,
    Single(Gaussian),
    Mixture(Vec<Hypothesis>),
}

/// The last odometry input, as rates, held between inputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct HeldInput {
    pub(crate) v_mps: f64,
    pub(crate) rate_rps: f64,
    pub(crate) var_v: f64,
    /// Variance of the turn per second of interval, rad²/s.
    pub(crate) var_rate: f64,
    pub(crate) t_end_s: f64,
}

/// The result of one Kalman update.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct UpdateInfo {
    pub(crate) nu0: f64,
    pub(crate) nis: f64,
    pub(crate) accepted: bool,
    pub(crate) weight: f64,
    pub(crate) log_lik: f64,
    /// The calibration states were held (not learned) in this update.
    pub(crate) held: bool,
}

/// The models, without state.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Model {
    pub(crate) cfg: BuoyConfig,
    pub(crate) lay: Layout,
    pub(crate) buoys: Vec<Vector3<f64>>,
    pub(crate) gate1: f64,
    pub(crate) gate_fix: f64,
}

impl Model {
    pub(crate) fn prior_variances(&self) -> DVector<f64> {
        let (c, l) = (&self.cfg, &self.lay);
        let mut v = DVector::zeros(l.n);
        for k in 0..l.d {
            v[l.d + k] = c.init.initial_speed_sigma_mps.powi(2);
        }
        v[l.psi] = std::f64::consts::PI.powi(2);
        if let Some(i) = l.turn_bias {
            v[i] = c.motion.turn_bias_prior_sigma_rps.powi(2);
        }
        if let Some(i) = l.scale {
            v[i] = c.range.scale_prior_sigma.powi(2);
        }
        if let Some(b) = l.bias {
            for k in 0..l.n_bias {
                v[b + k] = c.range.bias_prior_sigma_m.powi(2);
            }
        }
        v
    }

    /// The vehicle position as a 3-vector.
    pub(crate) fn position(&self, x: &DVector<f64>) -> Vector3<f64> {
        match self.lay.d {
            2 => Vector3::new(x[0], x[1], self.cfg.planar_height_m),
            _ => Vector3::new(x[0], x[1], x[2]),
        }
    }

    /// Predicted range to buoy `j`, its Jacobian row, and the geometric distance.
    pub(crate) fn range_model(&self, x: &DVector<f64>, j: usize) -> (f64, DMatrix<f64>, f64) {
        let l = &self.lay;
        let u = self.position(x) - self.buoys[j];
        let d = u.norm().max(1e-6);
        let s = l.scale.map_or(0.0, |i| x[i]);
        let beta = l.bias_of(j).map_or(0.0, |i| x[i]);
        let mut H = DMatrix::zeros(1, l.n);
        for k in 0..l.d {
            H[(0, k)] = (1.0 + s) * u[k] / d;
        }
        if let Some(i) = l.scale {
            H[(0, i)] = d;
        }
        if let Some(i) = l.bias_of(j) {
            H[(0, i)] = 1.0;
        }
        ((1.0 + s) * d + beta, H, d)
    }

    /// Random walks of the bias states over `dt`.
    pub(crate) fn add_bias_random_walks(&self, Q: &mut DMatrix<f64>, dt: f64) {
        let (c, l) = (&self.cfg, &self.lay);
        if let Some(i) = l.turn_bias {
            Q[(i, i)] += c.motion.turn_bias_random_walk_rps_per_sqrt_s.powi(2) * dt;
        }
        if let Some(b) = l.bias {
            for k in 0..l.n_bias {
                Q[(b + k, b + k)] += c.range.bias_random_walk_m_per_sqrt_s.powi(2) * dt;
            }
        }
    }

    /// Constant-velocity noise on axis `k` (position k, velocity D + k).
    pub(crate) fn add_cv_noise(&self, Q: &mut DMatrix<f64>, k: usize, dt: f64) {
        let q = self.cfg.motion.accel_sigma_mps2.powi(2);
        let (p, v) = (k, self.lay.d + k);
        Q[(p, p)] += q * dt.powi(3) / 3.0;
        Q[(p, v)] += q * dt.powi(2) / 2.0;
        Q[(v, p)] += q * dt.powi(2) / 2.0;
        Q[(v, v)] += q * dt;
    }

    pub(crate) fn cv_predict(&self, g: &mut Gaussian, dt: f64) {
        let l = &self.lay;
        let mut F = DMatrix::identity(l.n, l.n);
        let mut Q = DMatrix::zeros(l.n, l.n);
        for k in 0..l.d {
            F[(k, l.d + k)] = dt;
            self.add_cv_noise(&mut Q, k, dt);
        }
        Q[(l.psi, l.psi)] += (self.cfg.motion.cv_turn_rate_sigma_rps * dt).powi(2);
        self.add_bias_random_walks(&mut Q, dt);
        g.x = &F * &g.x;
        g.P = &F * &g.P * F.transpose() + Q;
        symmetrise(&mut g.P);
        if let Some(X) = &mut g.cross {
            *X = &*X * F.transpose();
        }
    }

    /// The odometry transition over `dt` with speed `v` and turn `dtheta`: the new state, its
    /// Jacobian F = ∂x'/∂x and the input Jacobian G = ∂x'/∂(v, δθ) (n × 2).
    pub(crate) fn input_model(
        &self,
        x: &DVector<f64>,
        dt: f64,
        v: f64,
        dtheta: f64,
    ) -> (DVector<f64>, DMatrix<f64>, DMatrix<f64>) {
        let l = &self.lay;
        let (d, psi) = (l.d, l.psi);
        let b_w = l.turn_bias.map_or(0.0, |i| x[i]);
        let turn = dtheta - b_w * dt;
        let psi_m = x[psi] + turn / 2.0;
        let psi_1 = x[psi] + turn;
        let (sm, cm) = psi_m.sin_cos();
        let (s1, c1) = psi_1.sin_cos();

        let mut F = DMatrix::identity(l.n, l.n);
        F[(0, psi)] = -v * dt * sm;
        F[(1, psi)] = v * dt * cm;
        F[(d, d)] = 0.0;
        F[(d + 1, d + 1)] = 0.0;
        F[(d, psi)] = -v * s1;
        F[(d + 1, psi)] = v * c1;
        if let Some(i) = l.turn_bias {
            F[(0, i)] = v * dt * dt * sm / 2.0;
            F[(1, i)] = -v * dt * dt * cm / 2.0;
            F[(d, i)] = v * s1 * dt;
            F[(d + 1, i)] = -v * c1 * dt;
            F[(psi, i)] = -dt;
        }
        if d == 3 {
            F[(2, d + 2)] = dt;
        }
        let mut G = DMatrix::zeros(l.n, 2);
        G[(0, 0)] = dt * cm;
        G[(1, 0)] = dt * sm;
        G[(d, 0)] = c1;
        G[(d + 1, 0)] = s1;
        G[(0, 1)] = -v * dt * sm / 2.0;
        G[(1, 1)] = v * dt * cm / 2.0;
        G[(d, 1)] = -v * s1;
        G[(d + 1, 1)] = v * c1;
        G[(psi, 1)] = 1.0;

        let mut xn = x.clone();
        xn[0] += v * dt * cm;
        xn[1] += v * dt * sm;
        if d == 3 {
            xn[2] += x[d + 2] * dt;
        }
        xn[d] = v * c1;
        xn[d + 1] = v * s1;
        xn[psi] = wrap_angle(psi_1);
        (xn, F, G)
    }

    /// Odometry prediction over `dt` with speed `v`, turn `dtheta` and their variances.
    pub(crate) fn input_predict(&self, g: &mut Gaussian, dt: f64, v: f64, dtheta: f64, var_v: f64, var_dtheta: f64) {
        let (c, l) = (&self.cfg, &self.lay);
        let (x, F, G) = self.input_model(&g.x, dt, v, dtheta);
        let U = DMatrix::from_diagonal(&DVector::from_column_slice(&[var_v, var_dtheta]));
        let mut Q = &G * U * G.transpose();
        let slip = (c.motion.slip_fraction * v * dt).powi(2);
        Q[(0, 0)] += slip;
        Q[(1, 1)] += slip;
        Q[(l.psi, l.psi)] += c.motion.heading_random_walk_rad_per_sqrt_s.powi(2) * dt;
        if l.d == 3 {
            self.add_cv_noise(&mut Q, 2, dt);
        }
        self.add_bias_random_walks(&mut Q, dt);
        g.x = x;
        g.P = &F * &g.P * F.transpose() + Q;
        symmetrise(&mut g.P);
        if let Some(X) = &mut g.cross {
            *X = &*X * F.transpose();
        }
    }

    /// Kalman update with measurement Jacobian `H` (m × n), innovation `nu`, noise `R`, gate
    /// on νᵀS⁻¹ν and optional Huber down-weighting. Rejected or failed: `g` is unchanged.
    pub(crate) fn update(
        &self,
        g: &mut Gaussian,
        H: &DMatrix<f64>,
        nu: &DVector<f64>,
        R: &DMatrix<f64>,
        gate: f64,
        huber_k: f64,
    ) -> Result<UpdateInfo, BuoyError> {
        self.update_holding(g, H, nu, R, gate, huber_k, &[], false)
    }

    /// As [`Self::update`]; the states in `hold` are not learned from it, and when the normalised
    /// innovation exceeds `range.calibration_k` none of the range scale and bias states are
    /// (their gain rows are zeroed: a Schmidt "consider" update, which the Joseph form keeps
    /// consistent).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn update_holding(
        &self,
        g: &mut Gaussian,
        H: &DMatrix<f64>,
        nu: &DVector<f64>,
        R: &DMatrix<f64>,
        gate: f64,
        huber_k: f64,
        hold: &[usize],
        systematic: bool,
    ) -> Result<UpdateInfo, BuoyError> {
        let mut info = self.gate(g, H, nu, R, gate, huber_k)?;
        if info.accepted {
            let calibration_k = self.cfg.range.calibration_k;
            let cal = self.calibration_states();
            // The innovation against what the calibration states cannot explain: the
            // covariance without their part (known calibration).
            let mut Hn = H.clone();
            for &i in &cal {
                Hn.column_mut(i).fill(0.0);
            }
            let Sn = &Hn * &g.P * Hn.transpose() + R;
            let nis_known = Sn.cholesky().map_or(f64::INFINITY, |c| nu.dot(&c.solve(nu)));
            info.held = calibration_k > 0.0 && nis_known > calibration_k * calibration_k && !systematic;
            let held: &[usize] = if info.held { &cal } else { hold };
            self.apply(g, H, nu, &(R / info.weight), held)?;
        }
        Ok(info)
    }

    /// The range scale and bias states that the accepted ranges `seen` (with `next`, the range
    /// about to be applied) do not determine: with the estimated path over the window taken as
    /// right up to a common offset δp (unknown; in spatial mode z known to `z_sigma_m` when a
    /// depth reading is recent), the information of those ranges alone on each calibration
    /// state, the others and δp free (a Schur complement: no prior enters, so a state is not
    /// "determined" by another state's prior), gives it a σ; a state whose σ exceeds
    /// `range.observable_sigma_fraction` times its prior σ is not determined by the ranges
    /// (e.g. a scale and a bias from one place among 3 buoys, per-buoy biases from one place).
    /// Empty when the check is off.
    pub(crate) fn unobservable_calibration(
        &self,
        seen: &VecDeque<SeenRange>,
        next: &SeenRange,
        z_sigma_m: Option<f64>,
        anchor: Option<PathAnchor>,
    ) -> Vec<usize> {
        let fraction = self.cfg.range.observable_sigma_fraction;
        let cal = self.calibration_states();
        if fraction <= 0.0 || cal.is_empty() {
            return Vec::new();
        }
        let (d, l) = (self.lay.d, &self.lay);
        let m = d + cal.len();
        let col = |state: usize| cal.iter().position(|&c| c == state).map(|k| d + k);
        let prior = self.prior_variances();
        let mut A = DMatrix::<f64>::zeros(m, m);
        // No priors: tiny ones (1e-9 of the calibration's, 1e-9 m⁻² on δp) keep A invertible
        // where the ranges leave a direction open, whose σ then comes out huge.
        for (k, &c) in cal.iter().enumerate() {
            A[(d + k, d + k)] = 1e-9 / prior[c];
        }
        for a in 0..d {
            A[(a, a)] = 1e-9;
        }
        if d == 3
            && let Some(sz) = z_sigma_m
        {
            A[(2, 2)] += 1.0 / (sz * sz);
        }
        let mut h = DVector::<f64>::zeros(m);
        for r in seen.iter().chain(std::iter::once(next)) {
            // Where the vehicle was: along the odometry's path through the estimate now (so the
            // estimate's own jitter is not taken for a change of geometry), else the estimate.
            let p = match (anchor, r.odom_xy) {
                (Some(a), Some(o)) => {
                    let (sn, cs) = a.turn_rad.sin_cos();
                    let (dx, dy) = (o[0] - a.odom_xy[0], o[1] - a.odom_xy[1]);
                    Vector3::new(a.position_m.x + cs * dx - sn * dy, a.position_m.y + sn * dx + cs * dy, r.position_m.z)
                }
                _ => r.position_m,
            };
            let u = p - self.buoys[r.buoy];
            let distance = u.norm().max(1e-6);
            h.fill(0.0);
            for a in 0..d {
                h[a] = u[a] / distance;
            }
            if let Some(c) = l.scale.and_then(col) {
                h[c] = distance;
            }
            if let Some(c) = l.bias_of(r.buoy).and_then(col) {
                h[c] = 1.0;
            }
            A += &h * h.transpose() / (r.sigma_m * r.sigma_m);
        }
        let Some(chol) = A.cholesky() else { return cal };
        let cov = chol.inverse();
        cal.iter()
            .enumerate()
            .filter(|&(k, &c)| cov[(d + k, d + k)].max(0.0).sqrt() > fraction * prior[c].sqrt())
            .map(|(_, &c)| c)
            .collect()
    }

    /// Indices of the range scale and bias states.
    pub(crate) fn calibration_states(&self) -> Vec<usize> {
        let l = &self.lay;
        l.scale.into_iter().chain(l.bias.into_iter().flat_map(|b| b..b + l.n_bias)).collect()
    }

    /// The gate decision, likelihood and Huber weight of an innovation (no state change).
    pub(crate) fn gate(
        &self,
        g: &Gaussian,
        H: &DMatrix<f64>,
        nu: &DVector<f64>,
        R: &DMatrix<f64>,
        gate: f64,
        huber_k: f64,
    ) -> Result<UpdateInfo, BuoyError> {
        let m = nu.len() as f64;
        let S = H * &g.P * H.transpose() + R;
        let chol = S.cholesky().ok_or(BuoyError::NotPositiveDefinite("innovation covariance S"))?;
        let nis = nu.dot(&chol.solve(nu));
        if !nis.is_finite() {
            return Err(BuoyError::NotPositiveDefinite("innovation covariance S"));
        }
        let ln_det = 2.0 * chol.l().diagonal().iter().map(|d| d.ln()).sum::<f64>();
        let log_lik = -0.5 * (nis.min(gate) + ln_det + m * (2.0 * std::f64::consts::PI).ln());
        let e = nis.sqrt();
        let weight = if huber_k > 0.0 && e > huber_k { huber_k / e } else { 1.0 };
        Ok(UpdateInfo { nu0: nu[0], nis, accepted: nis <= gate, weight, log_lik, held: false })
    }

    /// Joseph-form update x += K·ν, P = (I − KH)P(I − KH)ᵀ + K·R·Kᵀ, with the gain rows of the
    /// `held` states zeroed (valid for any gain); on failure `g` is unchanged.
    pub(crate) fn apply(
        &self,
        g: &mut Gaussian,
        H: &DMatrix<f64>,
        nu: &DVector<f64>,
        R: &DMatrix<f64>,
        held: &[usize],
    ) -> Result<(), BuoyError> {
        let PHt = &g.P * H.transpose();
        let S = H * &PHt + R;
        let chol = S.cholesky().ok_or(BuoyError::NotPositiveDefinite("innovation covariance S"))?;
        let mut K = chol.solve(&PHt.transpose()).transpose();
        for &i in held {
            K.row_mut(i).fill(0.0);
        }
        let x = &g.x + &K * nu;
        let IKH = DMatrix::identity(self.lay.n, self.lay.n) - &K * H;
        let mut P = &IKH * &g.P * IKH.transpose() + &K * R * K.transpose();
        symmetrise(&mut P);
        if !(x.iter().all(|v| v.is_finite()) && P.iter().all(|v| v.is_finite()) && P.diagonal().min() >= 0.0) {
            return Err(BuoyError::NotPositiveDefinite("state covariance P"));
        }
        g.x = x;
        g.x[self.lay.psi] = wrap_angle(g.x[self.lay.psi]);
        g.P = P;
        // e⁺ = (I − KH)·e⁻ − K·v, v independent of the mark's error.
        if let Some(X) = &mut g.cross {
            *X = &*X * IKH.transpose();
        }
        Ok(())
    }

    pub(crate) fn range_update(
        &self,
        g: &mut Gaussian,
        j: usize,
        r: f64,
        sigma: f64,
        hold: &[usize],
        systematic: bool,
    ) -> Result<UpdateInfo, BuoyError> {
        let (h, H, _) = self.range_model(&g.x, j);
        let nu = DVector::from_element(1, r - h);
        let R = DMatrix::from_element(1, 1, sigma * sigma);
        self.update_holding(g, &H, &nu, &R, self.gate1, self.cfg.range.huber_k, hold, systematic)
    }

    pub(crate) fn depth_update(&self, g: &mut Gaussian, z: f64, sigma: f64) -> Result<UpdateInfo, BuoyError> {
        let mut H = DMatrix::zeros(1, self.lay.n);
        H[(0, 2)] = 1.0;
        let nu = DVector::from_element(1, z - g.x[2]);
        let R = DMatrix::from_element(1, 1, sigma * sigma);
        self.update(g, &H, &nu, &R, self.gate1, 0.0)
    }

    pub(crate) fn fix_update(
        &self,
        g: &mut Gaussian,
        p: &Vector3<f64>,
        cov: &Matrix3<f64>,
    ) -> Result<UpdateInfo, BuoyError> {
        let d = self.lay.d;
        let mut H = DMatrix::zeros(d, self.lay.n);
        for k in 0..d {
            H[(k, k)] = 1.0;
        }
        let nu = DVector::from_iterator(d, (0..d).map(|k| p[k] - g.x[k]));
        let R = DMatrix::from_fn(d, d, |a, b| cov[(a, b)]);
        self.update(g, &H, &nu, &R, self.gate_fix, 0.0)
    }

    /// Resets the position block of `g` to (p, cov), with no cross-covariance.
    pub(crate) fn reset_position(&self, g: &mut Gaussian, p: &Vector3<f64>, cov: &Matrix3<f64>) {
        let d = self.lay.d;
        for k in 0..d {
            g.forget_state(k);
            g.x[k] = p[k];
            g.P.row_mut(k).fill(0.0);
            g.P.column_mut(k).fill(0.0);
        }
        for a in 0..d {
            for b in 0..d {
                g.P[(a, b)] = cov[(a, b)];
            }
        }
    }

    /// Moment-matched single Gaussian of a mixture (headings unwrapped around the heaviest).
    pub(crate) fn moment_match(&self, hyps: &[Hypothesis]) -> Gaussian {
        let psi = self.lay.psi;
        let best = hyps.iter().max_by(|a, b| a.log_w.total_cmp(&b.log_w)).expect("a mixture is never empty");
        let ref_psi = best.g.x[psi];
        let unwrapped = |h: &Hypothesis| {
            let mut x = h.g.x.clone();
            x[psi] = ref_psi + wrap_angle(x[psi] - ref_psi);
            x
        };
        let mut mean = DVector::zeros(self.lay.n);
        for h in hyps {
            mean += unwrapped(h) * h.log_w.exp();
        }
        let mut P = DMatrix::zeros(self.lay.n, self.lay.n);
        for h in hyps {
            let dx = unwrapped(h) - &mean;
            P += (&h.g.P + &dx * dx.transpose()) * h.log_w.exp();
        }
        symmetrise(&mut P);
        mean[psi] = wrap_angle(mean[psi]);
        Gaussian::new(mean, P)
    }
}

/// The position-heading covariance `c` (m·rad) of a start, shrunk if needed so that with the
/// position covariance `cov` (its x, y block) and the heading variance `var` the joint covariance
/// stays positive definite (squared correlation at most 0.998).
pub(crate) fn position_heading_cov(cov: &Matrix3<f64>, var: f64, c: &nalgebra::Vector2<f64>) -> nalgebra::Vector2<f64> {
    const MAX_RHO2: f64 = 0.998;
    let Some(inv) = cov.fixed_view::<2, 2>(0, 0).into_owned().try_inverse() else {
        return nalgebra::Vector2::zeros();
    };
    let rho2 = c.dot(&(inv * c)) / var;
    if !rho2.is_finite() || var <= 0.0 {
        return nalgebra::Vector2::zeros();
    }
    if rho2 > MAX_RHO2 { c * (MAX_RHO2 / rho2).sqrt() } else { *c }
}

pub(crate) fn symmetrise(P: &mut DMatrix<f64>) {
    let t = P.transpose();
    *P += t;
    *P *= 0.5;
}

/// An accepted range, kept for the calibration's observability check
/// ([`Model::unobservable_calibration`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct SeenRange {
    pub(crate) t_s: f64,
    pub(crate) buoy: usize,
    /// The estimated position when the range came, m.
    pub(crate) position_m: Vector3<f64>,
    /// The odometry's dead-reckoned position then, when there is odometry (the path's shape
    /// without the estimate's jitter).
    pub(crate) odom_xy: Option<[f64; 2]>,
    pub(crate) sigma_m: f64,
}

/// Where the odometry path is anchored for the observability check: the estimated position
/// now, the odometry's position now, and the turn from the odometry's frame to the world.
#[derive(Debug, Clone, Copy)]
pub(crate) struct PathAnchor {
    pub(crate) position_m: Vector3<f64>,
    pub(crate) odom_xy: [f64; 2],
    pub(crate) turn_rad: f64,
}

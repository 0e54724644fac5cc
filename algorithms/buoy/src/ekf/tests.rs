//! Unit tests of the parent module.

#![allow(non_snake_case)]

use super::*;
use crate::config::{BuoyEntry, InitMethod};
use nalgebra::{Matrix2, Vector2};
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
    assert!(stood.0 == 0.0 && stood.1 == prior && stood.2 == 0.0, "scale {} ± {}, bias {}", stood.0, stood.1, stood.2);
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
            assert!(matches!(outcome, RangeOutcome::Waiting(TrilaterationError::DegenerateGeometry(_))), "{outcome:?}");
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
            assert!(matches!(outcome, RangeOutcome::Waiting(TrilaterationError::DegenerateGeometry(_))), "{outcome:?}");
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

/// The cross-covariance of two published fixes' errors ([`BuoyEkf::mark_fix`]) is what the errors
/// do: a linear case (constant velocity, position fixes) simulated from the filter's own model,
/// 4,000 times, the sample cross-covariance of the errors at t = 1 s and t = 2 s against the
/// filter's (the same in every run: it does not depend on the data).
#[test]
fn the_cross_covariance_of_successive_fixes_is_that_of_their_errors() {
    let mut cfg = planar_config(BiasMode::None);
    cfg.init.method = InitMethod::Prior;
    cfg.init.prior_position_m = [20.0, 10.0, 0.0];
    cfg.init.prior_position_sigma_m = 2.0;
    cfg.init.prior_heading_rad = Some(0.0);
    let q = cfg.motion.accel_sigma_mps2.powi(2);
    let sv = cfg.init.initial_speed_sigma_mps;
    let r = 1.5f64;
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(3);
    let n01 = Normal::new(0.0, 1.0).unwrap();
    let runs = 4000;
    let mut skipped = 0;
    let (mut emp, mut model) = (Matrix2::<f64>::zeros(), None::<Matrix3<f64>>);
    let (mut var1, mut var2) = (Matrix2::<f64>::zeros(), Matrix2::<f64>::zeros());
    for _ in 0..runs {
        let mut ekf = BuoyEkf::new(cfg.clone(), 0.0).unwrap();
        // Truth per axis: position, velocity.
        let mut truth: Vec<[f64; 2]> = (0..2)
            .map(|a| [cfg.init.prior_position_m[a] + 2.0 * n01.sample(&mut rng), sv * n01.sample(&mut rng)])
            .collect();
        let mut errors = vec![];
        for k in 1..=2 {
            // One second of white-noise acceleration, exactly: (p, v) noise [1/3, 1/2; 1/2, 1]·q.
            for t in truth.iter_mut() {
                let (a, b) = (n01.sample(&mut rng), n01.sample(&mut rng));
                let l11 = (q / 3.0).sqrt();
                let l21 = (q / 2.0) / l11;
                let l22 = (q - l21 * l21).sqrt();
                t[0] += t[1] + l11 * a;
                t[1] += l21 * a + l22 * b;
            }
            ekf.predict_to(k as f64).unwrap();
            let z = Vector3::new(truth[0][0] + r * n01.sample(&mut rng), truth[1][0] + r * n01.sample(&mut rng), 0.0);
            let outcome = ekf.update_position_fix(&z, &(Matrix3::identity() * r * r)).unwrap();
            let c = ekf.mark_fix();
            if !matches!(outcome, FixOutcome::Accepted { .. }) {
                // Gated out (a tail draw) and reset to the fix: the link to the last fix is cut.
                assert!(outcome != FixOutcome::Reset || k == 1 || c.is_some_and(|c| c.amax() == 0.0), "{c:?}");
                skipped += 1;
                break;
            }
            assert_eq!(c.is_some(), k == 2, "a cross-covariance from the second fix on");
            if let Some(c) = c {
                if let Some(m) = model {
                    assert!((m - c).amax() < 1e-12, "the same in every run: {m} {c}");
                }
                model = Some(c);
            }
            let e = ekf.estimate().unwrap().position_m;
            errors.push(Vector2::new(e.x - truth[0][0], e.y - truth[1][0]));
        }
        if errors.len() < 2 {
            continue;
        }
        emp += errors[0] * errors[1].transpose() / runs as f64;
        var1 += errors[0] * errors[0].transpose() / runs as f64;
        var2 += errors[1] * errors[1].transpose() / runs as f64;
    }
    assert!(skipped < runs / 100, "{skipped} runs with a fix gated out");
    let used = (runs - skipped) as f64;
    let (emp, var1, var2) = (emp * runs as f64 / used, var1 * runs as f64 / used, var2 * runs as f64 / used);
    let m = model.unwrap();
    let m2 = m.fixed_view::<2, 2>(0, 0).into_owned();
    assert!(m[(2, 2)] == 0.0, "planar: no z");
    for a in 0..2 {
        // The sample mean of e1·e2 over n pairs has a standard error of about
        // √((σ1²σ2² + c²)/n): within 4 of them.
        let se = ((var1[(a, a)] * var2[(a, a)] + m2[(a, a)].powi(2)) / used).sqrt();
        assert!((emp[(a, a)] - m2[(a, a)]).abs() < 4.0 * se, "axis {a}: sample {emp} against the filter's {m2}");
        // The diagonal of P itself, to the same standard (2σ⁴/n).
        let p2 = ekf_variance_at_second_fix(&cfg, r);
        assert!((var2[(a, a)] - p2).abs() < 4.0 * p2 * (2.0 / used).sqrt(), "axis {a}: {var2} against {p2}");
        assert!(m2[(a, a)] > 0.1 * var1[(a, a)], "the errors correlate: {m2} against the variance {var1}");
    }
    let se = (var1[(0, 0)] * var2[(1, 1)] / used).sqrt();
    assert!(emp[(0, 1)].abs() < 4.0 * se, "no correlation across axes: {emp}");
}

/// The filter's position variance (x) after the second fix of the test above.
fn ekf_variance_at_second_fix(cfg: &BuoyConfig, r: f64) -> f64 {
    let mut ekf = BuoyEkf::new(cfg.clone(), 0.0).unwrap();
    for k in 1..=2 {
        ekf.predict_to(k as f64).unwrap();
        let p = Vector3::from(cfg.init.prior_position_m);
        ekf.update_position_fix(&p, &(Matrix3::identity() * r * r)).unwrap();
    }
    ekf.estimate().unwrap().covariance_m2[(0, 0)]
}

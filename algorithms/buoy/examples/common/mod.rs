//! Shared by the evaluation examples: the replay loop, dead reckoning, the ATE metric and the
//! report.

use std::path::Path;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use buoy::{BuoyConfig, BuoyEkf, OdometryInput, RangeOutcome};

/// A time-stamped 2-D position (t, x, y).
pub type Stamped = (f64, f64, f64);

/// A range as replayed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeEvent {
    /// Stamp, s.
    pub t_s: f64,
    /// Beacon id.
    pub id: u32,
    /// Range, m.
    pub range_m: f64,
    /// Its σ, m.
    pub sigma_m: f64,
}

/// What a replay produced.
pub struct Run {
    /// The estimate after every event (once initialised), in time order.
    pub estimates: Vec<Stamped>,
    /// When the filter initialised, s.
    pub t_init: Option<f64>,
    /// When the heading became known, s.
    pub t_heading: Option<f64>,
    /// The filter at the end.
    pub ekf: BuoyEkf,
    /// Wall time of the filter.
    pub elapsed: Duration,
}

/// `path` without `..` components, when it exists.
pub fn tidy(path: &Path) -> std::path::PathBuf {
    std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf())
}

/// Reads a (partial) `BuoyConfig` TOML, or the defaults.
pub fn load_config(path: Option<&Path>) -> Result<BuoyConfig> {
    let Some(p) = path else { return Ok(BuoyConfig::default()) };
    let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
    toml::from_str(&text).with_context(|| format!("parsing {}", p.display()))
}

/// Runs the filter over odometry `inputs` (stamp at the end of each interval) and `ranges`,
/// merged in time order (odometry first on equal stamps), from time `t0_s`.
pub fn replay(cfg: BuoyConfig, t0_s: f64, inputs: &[(f64, OdometryInput)], ranges: &[RangeEvent]) -> Result<Run> {
    let mut ekf = BuoyEkf::new(cfg, t0_s)?;
    let mut estimates = Vec::new();
    let (mut i, mut k) = (0, 0);
    let (mut t_init, mut t_heading) = (None, None);
    let clock = std::time::Instant::now();
    while i < inputs.len() || k < ranges.len() {
        let odometry_next = k >= ranges.len() || (i < inputs.len() && inputs[i].0 <= ranges[k].t_s);
        let t = if odometry_next {
            let (t, u) = inputs[i];
            i += 1;
            ekf.predict_with_input(t, &u).with_context(|| format!("odometry at {t} s"))?;
            t
        } else {
            let r = ranges[k];
            k += 1;
            ekf.predict_to(r.t_s)?;
            let outcome =
                ekf.update_range(r.id, r.range_m, r.sigma_m).with_context(|| format!("range at {} s", r.t_s))?;
            if outcome == RangeOutcome::Initialised {
                t_init = Some(r.t_s);
            }
            r.t_s
        };
        if t_heading.is_none() && ekf.heading_known() {
            t_heading = Some(t);
        }
        if let Ok(e) = ekf.estimate() {
            estimates.push((t, e.position_m.x, e.position_m.y));
        }
    }
    if estimates.is_empty() {
        bail!("the filter never initialised");
    }
    Ok(Run { estimates, t_init, t_heading, ekf, elapsed: clock.elapsed() })
}

/// Integrates the inputs from (x, y, heading) at `start.0` (midpoint heading, as the filter).
pub fn dead_reckoning(start: (f64, f64, f64, f64), inputs: &[(f64, OdometryInput)]) -> Vec<Stamped> {
    let (t0, mut x, mut y, mut h) = start;
    let mut out = vec![(t0, x, y)];
    for (t, u) in inputs {
        let hm = h + u.dtheta_rad / 2.0;
        x += u.v_mps * u.dt_s * hm.cos();
        y += u.v_mps * u.dt_s * hm.sin();
        h += u.dtheta_rad;
        out.push((*t, x, y));
    }
    out
}

/// Per ground-truth row: the estimate with the nearest stamp (the latest of equal stamps; ties
/// between before and after go to before; rows before the first estimate get the first) and
/// the 2-D error.
pub fn matched(gt: &[Stamped], est: &[Stamped]) -> Vec<((f64, f64), f64)> {
    gt.iter()
        .map(|&(t, x, y)| {
            let i = est.partition_point(|e| e.0 <= t);
            let j = match (i.checked_sub(1), est.get(i)) {
                (Some(a), Some(b)) if t - est[a].0 > b.0 - t => i,
                (Some(a), _) => a,
                (None, _) => 0,
            };
            ((est[j].1, est[j].2), (est[j].1 - x).hypot(est[j].2 - y))
        })
        .collect()
}

/// ATE: RMSE and max of the 2-D error over every ground-truth row, nearest stamp, no alignment.
pub fn ate(gt: &[Stamped], est: &[Stamped]) -> (f64, f64) {
    let m = matched(gt, est);
    let sum: f64 = m.iter().map(|(_, e)| e * e).sum();
    ((sum / gt.len() as f64).sqrt(), m.iter().map(|(_, e)| *e).fold(0.0, f64::max))
}

/// Writes `t x y gt_x gt_y error` per ground-truth row.
pub fn dump(path: &Path, gt: &[Stamped], est: &[Stamped]) -> Result<()> {
    let mut text = String::from("# t x y gt_x gt_y error\n");
    for (g, ((x, y), e)) in gt.iter().zip(matched(gt, est)) {
        text += &format!("{:.3} {x:.3} {y:.3} {:.3} {:.3} {e:.3}\n", g.0, g.1, g.2);
    }
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

/// Prints the ATE table and the filter's final state.
pub fn report(gt: &[Stamped], run: &Run, dr: &[Stamped], t0_s: f64) -> Result<()> {
    let (ekf_rmse, ekf_max) = ate(gt, &run.estimates);
    let (dr_rmse, dr_max) = ate(gt, dr);
    println!("| estimator          | ATE RMSE (m) | max (m) |");
    println!("|--------------------|--------------|---------|");
    println!("| buoy EKF           | {ekf_rmse:12.3} | {ekf_max:7.2} |");
    println!("| dead reckoning     | {dr_rmse:12.3} | {dr_max:7.2} |");
    println!(
        "initialised at +{:.1} s, heading known at +{:.1} s; filter wall time {:.0} ms",
        run.t_init.map_or(f64::NAN, |t| t - t0_s),
        run.t_heading.map_or(f64::NAN, |t| t - t0_s),
        run.elapsed.as_secs_f64() * 1e3
    );
    let c = run.ekf.counters();
    let per_buoy: Vec<String> = c.per_buoy.iter().map(|b| format!("{}:{}", b.id, b.rejected)).collect();
    println!(
        "ranges accepted {}, rejected {} (per beacon {}), recoveries {}, bias resets {}, re-starts from the window {} \
         (lost checks without a fix {}), start checks {} (corrected {}), updates with the calibration held {} \
         (not determined by the last ranges {})",
        c.accepted,
        c.rejected,
        per_buoy.join(" "),
        c.recoveries,
        c.bias_resets,
        c.reinitialisations,
        c.lost_checks_without_fix,
        c.start_checks,
        c.start_corrections,
        c.calibration_held,
        c.calibration_unobservable
    );
    let e = run.ekf.estimate()?;
    if let Some((s, ss)) = e.range_scale {
        println!("range scale {s:.4} ± {ss:.4}");
    }
    if let Some((b, bs)) = e.turn_bias_rps {
        println!("turn-rate bias {b:.5} ± {bs:.5} rad/s");
    }
    match (run.ekf.config().range.bias, e.biases.first()) {
        (buoy::BiasMode::Global, Some(b)) => println!("range bias (all beacons): {:.3} ± {:.3} m", b.bias_m, b.sigma_m),
        _ => {
            for b in &e.biases {
                println!("range bias (beacon {}): {:.3} ± {:.3} m", b.buoy_id, b.bias_m, b.sigma_m);
            }
        }
    }
    Ok(())
}

//! Evaluates the buoy EKF on CMU Plaza2 (range-only UWB beacons, wheel odometry, GPS/INS ground
//! truth) in planar mode: odometry for the prediction, ranges for the updates, default
//! parameters.
//!
//! ```sh
//! cargo run --release -p buoy --example plaza2_eval [-- [DIR] [--config FILE.toml] [--dump FILE] [--range-sigma M]]
//! ```
//! DIR defaults to `algorithms/datasets/data/plaza2` under the workspace root. `--config` reads
//! a (partial) `BuoyConfig` TOML over the defaults (the buoy table is replaced by the data set's
//! beacons, the mode is planar); `--dump` writes `t x y gt_x gt_y error` per ground-truth row;
//! `--range-sigma` overrides the σ attached to every range (for sensitivity checks).
//!
//! Inputs as the ingest replay makes them: v = Δd/Δt, δθz = Δheading (Δt = 0.1 s for the first
//! row), σ_v = 0.1 m/s, σ_δθ = 0.01 rad per row, σ_range = 1 m (the replay's defaults; the data
//! set gives no σ).
//!
//! Metric (ATE): RMSE of the 2-D position against every ground-truth row, each matched to the
//! estimate with the nearest stamp (estimates are recorded after every odometry row and range),
//! no alignment. Rows before the filter's first estimate (the first 0.4 s) are matched to that
//! first estimate. Dead reckoning integrates the odometry (midpoint heading, as the filter) from
//! the first ground-truth pose, whose heading is offset by π from the direction of travel.

#[path = "common/mod.rs"]
mod common;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use buoy::{BuoyEntry, Mode, OdometryInput};
use common::RangeEvent;

const RANGE_SIGMA_M: f64 = 1.0;
const SPEED_SIGMA_MPS: f64 = 0.1;
const TURN_SIGMA_RAD: f64 = 0.01;

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run() -> Result<()> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut dir = root.join("algorithms/datasets/data/plaza2");
    let (mut config, mut dump, mut range_sigma_m) = (None, None, RANGE_SIGMA_M);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--config" => config = Some(PathBuf::from(args.next().context("--config needs a file")?)),
            "--dump" => dump = Some(PathBuf::from(args.next().context("--dump needs a file")?)),
            "--range-sigma" => range_sigma_m = args.next().context("--range-sigma needs a value")?.parse()?,
            s if s.starts_with("--") => bail!("unknown option {s}"),
            _ => dir = a.into(),
        }
    }
    let data = datasets::Plaza2::load(&dir).with_context(|| format!("loading Plaza2 from {}", dir.display()))?;
    let mut cfg = common::load_config(config.as_deref())?;
    cfg.mode = Mode::Planar;
    cfg.buoys = data.beacons.iter().map(|b| BuoyEntry { id: b.beacon_id, position_m: [b.x_m, b.y_m, 0.0] }).collect();
    let gt: Vec<common::Stamped> = data.ground_truth.iter().map(|g| (g.t_s, g.x_m, g.y_m)).collect();
    let Some(g0) = data.ground_truth.first() else { bail!("no ground truth") };

    let mut inputs = Vec::new();
    for (i, row) in data.odometry.iter().enumerate() {
        let dt = if i == 0 { 0.1 } else { row.t_s - data.odometry[i - 1].t_s };
        if dt > 0.0 {
            let input = OdometryInput {
                dt_s: dt,
                v_mps: row.delta_dist_m / dt,
                dtheta_rad: row.delta_heading_rad,
                var_v: SPEED_SIGMA_MPS.powi(2),
                var_dtheta: TURN_SIGMA_RAD.powi(2),
            };
            inputs.push((row.t_s, input));
        }
    }
    let ranges: Vec<RangeEvent> = data
        .ranges
        .iter()
        .map(|r| RangeEvent { t_s: r.t_s, id: r.beacon_id, range_m: r.range_m, sigma_m: range_sigma_m })
        .collect();
    let dr = common::dead_reckoning((g0.t_s, g0.x_m, g0.y_m, g0.heading_rad + std::f64::consts::PI), &inputs);

    let t0 = inputs.first().map_or(f64::MAX, |(t, u)| t - u.dt_s).min(ranges.first().map_or(f64::MAX, |r| r.t_s));
    let run = common::replay(cfg, t0, &inputs, &ranges)?;
    println!(
        "Plaza2 ({}): {} ground-truth rows, {} odometry rows, {} ranges, {} beacons",
        common::tidy(&dir).display(),
        gt.len(),
        inputs.len(),
        ranges.len(),
        data.beacons.len()
    );
    common::report(&gt, &run, &dr, t0)?;
    if let Some(path) = dump {
        common::dump(&path, &gt, &run.estimates)?;
    }
    Ok(())
}

//! The heavy-outlier benchmark (issue 18): the simulated indoor UWB robot of
//! [`buoy::scenario::OutlierScenario`] (3 beacons at 1.04-1.94 m, antenna at 1.12 m, one range a
//! second, 15 % gross errors of 1-4 m of either sign, 1,000 s in a 7 × 5 m room, drifting
//! odometry), over several seeds, with the same defaults every other evaluation uses (only the
//! mission's geometry is configured: planar mode at the antenna's height, the beacon table,
//! `init.min_buoys = 3`).
//!
//! ```sh
//! cargo run --release -p buoy --example outlier_eval [-- --seeds 1-10 --outliers 0.15 --outlier-m 1,4
//!     --range-sigma 0.1 --duration 1000 --config FILE.toml]
//! ```
//!
//! Per seed: the filter's ATE with the outliers and on the same mission with them removed (the
//! target: at most 1.2× that), the median error after each range against a plain per-step
//! least-squares trilateration of the latest range of each beacon (the target: never worse),
//! dead reckoning, and what the gate did: the share of the gross errors rejected and of the good
//! ranges rejected, and the final error (recovered: < 0.5 m).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use buoy::scenario::{OutlierScenario, median, trilaterate_each_range};
use buoy::{BuoyConfig, Geometry, RangeOutcome};

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn parse_seeds(s: &str) -> Result<Vec<u64>> {
    if let Some((a, b)) = s.split_once('-') {
        let (a, b): (u64, u64) = (a.parse()?, b.parse()?);
        if a > b {
            bail!("--seeds {s}: empty range");
        }
        return Ok((a..=b).collect());
    }
    s.split(',').map(|x| x.parse::<u64>().with_context(|| format!("--seeds: `{x}`"))).collect()
}

fn run() -> Result<()> {
    let mut seeds: Vec<u64> = (1..=10).collect();
    let mut scenario = OutlierScenario::default();
    let mut config: Option<PathBuf> = None;
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        match a.as_str() {
            "--seeds" => seeds = parse_seeds(&it.next().context("--seeds needs a list, e.g. 1-10")?)?,
            "--outliers" => {
                scenario.outlier_fraction = it.next().context("--outliers needs a fraction")?.parse()?;
            }
            "--outlier-m" => {
                let v = it.next().context("--outlier-m needs MIN,MAX")?;
                let (a, b) = v.split_once(',').context("--outlier-m needs MIN,MAX")?;
                scenario.outlier_m = [a.parse().context("--outlier-m")?, b.parse().context("--outlier-m")?];
            }
            "--range-sigma" => {
                scenario.range_sigma_m = it.next().context("--range-sigma needs metres")?.parse()?;
            }
            "--duration" => scenario.duration_s = it.next().context("--duration needs seconds")?.parse()?,
            "--config" => config = Some(PathBuf::from(it.next().context("--config needs a file")?)),
            other => bail!(
                "unknown argument {other} (options: --seeds, --outliers, --outlier-m, --range-sigma, --duration, --config)"
            ),
        }
    }
    let problems = validation::Validate::issues(&scenario);
    if !problems.is_empty() {
        bail!("invalid scenario: {problems}");
    }
    let base: BuoyConfig = match &config {
        Some(p) => toml::from_str(&std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?)
            .with_context(|| format!("parsing {}", p.display()))?,
        None => BuoyConfig::default(),
    };
    println!(
        "heavy-outlier mission: {} beacons, {:.0} % gross errors of {:.0}-{:.0} m, {:.0} s, one range every {:.1} s",
        scenario.beacons_m.len(),
        scenario.outlier_fraction * 100.0,
        scenario.outlier_m[0],
        scenario.outlier_m[1],
        scenario.duration_s,
        scenario.range_period_s
    );
    println!(
        "| seed | ATE (m) | ATE clean (m) | ratio | median (m) | median trilat. (m) | DR ATE (m) | outliers rejected | good rejected | final err (m) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let (mut ratios, mut worst_median_ratio) = (Vec::new(), 0.0f64);
    let mut sums = [0.0f64; 4];
    let clock = std::time::Instant::now();
    for &seed in &seeds {
        let m = scenario.generate(seed);
        let mut cfg = m.config();
        cfg.range = base.range.clone();
        cfg.motion = base.motion.clone();
        cfg.init = base.init.clone();
        cfg.init.min_buoys = cfg.init.min_buoys.min(m.buoys.len());
        cfg.recovery = base.recovery.clone();
        let run = m.run(cfg.clone())?;
        let clean = m.without_outliers().run(cfg)?;
        let ate = m.ate_m(&run.estimates);
        let ate_clean = m.ate_m(&clean.estimates);
        let med = median(&m.errors_m(&run.at_ranges));
        let tri: Vec<(f64, f64, f64)> =
            trilaterate_each_range(&m.range_tuples(), &m.buoys, Geometry::Planar { height_m: m.antenna_height_m })
                .into_iter()
                .map(|(t, p)| (t, p.x, p.y))
                .collect();
        let med_tri = median(&m.errors_m(&tri));
        // Dead reckoning from the true start.
        let t0 = m.truth[0];
        let (mut x, mut y, mut h) = (t0.x_m, t0.y_m, t0.heading_rad);
        let mut dr = vec![(0.0, x, y)];
        for (t, u) in &m.odometry {
            let hm = h + u.dtheta_rad / 2.0;
            x += u.v_mps * u.dt_s * hm.cos();
            y += u.v_mps * u.dt_s * hm.sin();
            h += u.dtheta_rad;
            dr.push((*t, x, y));
        }
        let ate_dr = m.ate_m(&dr);
        let (mut out_rej, mut out_n, mut good_rej, mut good_n) = (0, 0, 0, 0);
        for (r, o) in m.ranges.iter().zip(&run.outcomes) {
            let rejected = matches!(o, RangeOutcome::Rejected { .. });
            if r.outlier {
                out_n += 1;
                out_rej += usize::from(rejected);
            } else {
                good_n += 1;
                good_rej += usize::from(rejected);
            }
        }
        let last = run.estimates.last().copied().unwrap_or((0.0, f64::NAN, f64::NAN));
        let truth = m.truth_at(last.0);
        let final_err = (last.1 - truth[0]).hypot(last.2 - truth[1]);
        let ratio = ate / ate_clean;
        ratios.push(ratio);
        worst_median_ratio = worst_median_ratio.max(med / med_tri);
        for (s, v) in sums.iter_mut().zip([ate, ate_clean, med, med_tri]) {
            *s += v;
        }
        println!(
            "| {seed} | {ate:.3} | {ate_clean:.3} | {ratio:.2} | {med:.3} | {med_tri:.3} | {ate_dr:.2} | {:.0} % of {out_n} | {:.1} % of {good_n} | {final_err:.2} |",
            100.0 * out_rej as f64 / out_n.max(1) as f64,
            100.0 * good_rej as f64 / good_n.max(1) as f64,
        );
    }
    let n = seeds.len() as f64;
    println!(
        "| mean | {:.3} | {:.3} | {:.2} (max {:.2}) | {:.3} | {:.3} | | | | |",
        sums[0] / n,
        sums[1] / n,
        ratios.iter().sum::<f64>() / n,
        ratios.iter().copied().fold(0.0, f64::max),
        sums[2] / n,
        sums[3] / n
    );
    println!(
        "targets: ATE <= 1.2x clean on every seed: {}; median never worse than trilateration: {} (worst ratio {worst_median_ratio:.2}); {:.1} s",
        if ratios.iter().all(|&r| r <= 1.2) { "met" } else { "NOT met" },
        if worst_median_ratio <= 1.0 { "met" } else { "NOT met" },
        clock.elapsed().as_secs_f64()
    );
    Ok(())
}

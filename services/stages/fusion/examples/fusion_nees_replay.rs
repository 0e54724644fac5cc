//! Replays a run's fusion journal (`<out>/state/fusion/journal`) into a new engine with the
//! default configuration and scores the covariances against `<out>/ground_truth.tum`: the mean
//! position NEES (docs/EQUATIONS.md §8a) of the synchronised buoy positions, the live fused poses
//! and the final fused path, overall and by eighths of the run, with the RMS error of each
//! (against the truth row nearest each estimate). Then the fixes' error autocorrelation the
//! engine estimated from its residuals (docs/EQUATIONS.md §5.3), the final path scored with the
//! buoy's covariance instead of its own, and the buoy error's autocorrelation against the truth,
//! to compare with the engine's estimate.
//!
//! `cargo run --release -p fusion_stage --example fusion_nees_replay -- out/default`

use std::path::PathBuf;

use fusion::engine::{Fusion, FusionConfig};
use fusion_stage::journal::{Entry, read};
use geometry::trajectory::position_nees;
use nalgebra::{Matrix3, Vector3};
use pipeline_runtime::restart::Restart;

type Track = Vec<(f64, Vector3<f64>, Matrix3<f64>)>;

fn report(name: &str, est: &Track, truth: &[(f64, Vector3<f64>)]) {
    let Some(n) = position_nees(est, truth, false, 1.0) else {
        println!("{name}: nothing scored");
        return;
    };
    let rms = {
        let sum: f64 = est
            .iter()
            .filter_map(|(t, p, _)| geometry::trajectory::nearest(truth, *t).map(|q| (p - q).norm_squared()))
            .sum();
        (sum / est.len() as f64).sqrt()
    };
    let eighths: Vec<String> = (0..8)
        .map(|i| {
            let part: Track = est[i * est.len() / 8..(i + 1) * est.len() / 8].to_vec();
            position_nees(&part, truth, false, 1.0).map_or("-".into(), |n| format!("{:.2}", n.mean))
        })
        .collect();
    println!(
        "{name:<12} NEES {:7.2} [{:.2}, {:.2}] x {:6.2} y {:6.2} z {:6.2}  n {:5}  rms {rms:.3} m  eighths {}",
        n.mean,
        n.interval_95.0,
        n.interval_95.1,
        n.per_axis[0],
        n.per_axis[1],
        n.per_axis[2],
        n.samples,
        eighths.join(" ")
    );
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out: PathBuf = std::env::args().nth(1).unwrap_or_else(|| "out/default".into()).into();
    let journal = std::fs::read_to_string(out.join("state/fusion/journal"))?;
    let restart = Restart { journal: journal.lines().map(String::from).collect(), ..Default::default() };
    let entries = read(&restart)?.entries;
    let truth: Vec<(f64, Vector3<f64>)> = geometry::tum::read_tum(&out.join("ground_truth.tum"))?
        .iter()
        .map(|(t, p)| (*t, p.translation.vector))
        .collect();
    let mut engine = Fusion::new(FusionConfig::default()).map_err(|e| format!("{e:?}"))?;
    let (mut buoy, mut live) = (Track::new(), Track::new());
    for e in entries {
        match e {
            Entry::Fix(f) => engine.push_fix(f)?,
            Entry::Heading(h) => engine.push_heading(h)?,
            Entry::Pair(p) => {
                buoy.push((p.t_s, p.buoy_m, p.buoy_cov_m2));
                if let Ok(o) = engine.push_pair(*p) {
                    live.push((
                        o.t_s,
                        o.world_from_body.translation.vector,
                        o.covariance.fixed_view::<3, 3>(0, 0).into(),
                    ));
                }
            }
        }
    }
    let result = engine.finish();
    let path: Track = result
        .path
        .iter()
        .map(|o| (o.t_s, o.world_from_body.translation.vector, o.covariance.fixed_view::<3, 3>(0, 0).into()))
        .collect();
    let rho: Vec<String> = result.fix_correlation.rho().iter().map(|r| format!("{r:.2}")).collect();
    println!("fixes' error autocorrelation by lag (fixes): {}", rho.join(" "));
    println!("variance inflation of a mean of 20 fixes: {:.2}", result.fix_correlation.mean_inflation(20));
    report("buoy (sync)", &buoy, &truth);
    report("live", &live, &truth);
    report("final", &path, &truth);
    // The final positions with the buoy's covariance; the buoy error's autocorrelation against
    // the truth (by time: the buoy positions are the pairs', one per SLAM pose).
    let with_buoy_cov: Track = path.iter().zip(&buoy).map(|(p, b)| (p.0, p.1, b.2)).collect();
    report("final/Pb", &with_buoy_cov, &truth);
    let err: Vec<(f64, Vector3<f64>)> =
        buoy.iter().filter_map(|(t, p, _)| geometry::trajectory::nearest(&truth, *t).map(|q| (*t, p - q))).collect();
    let dt = (err[err.len() - 1].0 - err[0].0) / (err.len() - 1) as f64;
    let var: f64 = err.iter().map(|(_, e)| e.xy().norm_squared()).sum::<f64>() / err.len() as f64;
    let mut line = format!("buoy error (x, y) autocorrelation (dt {dt:.3} s):");
    for lag_s in [0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 40.0, 80.0] {
        let k = (lag_s / dt).round() as usize;
        let c: f64 = err.windows(k + 1).map(|w| w[0].1.xy().dot(&w[k].1.xy())).sum::<f64>() / (err.len() - k) as f64;
        line += &format!(" {lag_s}s {:.2}", c / var);
    }
    println!("{line}");
    Ok(())
}

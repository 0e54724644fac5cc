//! Replays a run's buoy EKF journal (`<out>/state/buoy/journal`) into a new filter with the
//! settings of `[processes.<name>.settings]` in a config (and overrides of its `ekf` keys), and
//! scores the estimates against `<out>/ground_truth.tum`: the ATE and the mean position NEES
//! (docs/EQUATIONS.md §8a), overall and by eighths of the run, and the mean NIS of the ranges
//! taken.
//!
//! `cargo run --release -p buoy_ekf_stage --example buoy_nees_replay -- out/default config/default.toml
//! [buoy ['motion = { level_time_constant_s = 10.0 }' ...]] [--truth-attitude]`
//!
//! The third argument names the process whose settings to take; the ones after it are TOML
//! tables merged into its `ekf` settings. `--truth-attitude` turns the odometry into planar
//! motion with the ground truth's attitude instead of the filter's levelled one.

use std::path::PathBuf;

use buoy_ekf_stage::{BuoyEkfSettings, BuoyState};
use geometry::trajectory::{ate_nearest, position_nees};
use nalgebra::{UnitQuaternion, Vector3};

fn merge(base: &mut toml::Table, over: toml::Table) {
    for (k, v) in over {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let truth_attitude = args.iter().any(|a| a == "--truth-attitude");
    args.retain(|a| a != "--truth-attitude");
    let out: PathBuf = args.first().map_or("out/default", |s| s.as_str()).into();
    let config = args.get(1).map_or("config/default.toml", |s| s.as_str());
    let process = args.get(2).map_or("buoy", |s| s.as_str());
    let cfg: toml::Table = toml::from_str(&std::fs::read_to_string(config)?)?;
    let mut settings = cfg
        .get("processes")
        .and_then(|p| p.get(process))
        .and_then(|p| p.get("settings"))
        .and_then(|s| s.as_table())
        .cloned()
        .unwrap_or_default();
    let mut ekf = settings.get("ekf").and_then(|e| e.as_table()).cloned().unwrap_or_default();
    for o in args.iter().skip(3) {
        merge(&mut ekf, toml::from_str(o)?);
    }
    settings.insert("ekf".into(), toml::Value::Table(ekf));
    let mut settings: BuoyEkfSettings = toml::Value::Table(settings).try_into()?;
    let journal = std::fs::read_to_string(out.join("state/buoy/journal"))?;
    let lines: Vec<String> = journal.lines().map(String::from).collect();
    let (mut inputs, _) = buoy_ekf_stage::journal::parse(&lines);
    if truth_attitude {
        // The odometry's increments turned into a world yaw increment and horizontal speed with
        // the true attitude, as a level vehicle's would be: the bound for
        // `motion.level_time_constant_s` (docs/buoy_ekf.md). The filter then takes them as
        // they are.
        settings.ekf.motion.level_time_constant_s = 0.0;
        let truth = geometry::tum::read_tum(&out.join("ground_truth.tum"))?;
        for a in inputs.iter_mut() {
            if let buoy_ekf_stage::Applied::Odometry { stamp_ns, input } = a {
                let t = *stamp_ns as f64 / 1e9;
                let before =
                    geometry::trajectory::nearest(&truth, t - input.dt_s).map(|p| p.rotation).unwrap_or_default();
                let d = Vector3::from(input.delta_theta_rad);
                let after = before * UnitQuaternion::from_euler_angles(d.x, d.y, d.z);
                let yaw = |q: &UnitQuaternion<f64>| {
                    let x = q * Vector3::x();
                    x.y.atan2(x.x)
                };
                input.delta_theta_rad = [0.0, 0.0, buoy::wrap_angle(yaw(&after) - yaw(&before))];
                input.v_mps *= (before * Vector3::x()).xy().norm();
            }
        }
    }
    let mut state = BuoyState::new(settings);
    let fixes = state.replay(inputs);
    let truth: Vec<(f64, Vector3<f64>)> = geometry::tum::read_tum(&out.join("ground_truth.tum"))?
        .iter()
        .map(|(t, p)| (*t, p.translation.vector))
        .collect();
    let est: Vec<_> = state.trajectory.iter().map(|s| (s.t_s, s.position_m, s.covariance_m2)).collect();
    let pos: Vec<_> = est.iter().map(|(t, p, _)| (*t, *p)).collect();
    let ate = ate_nearest(&pos, &truth, false);
    let n = position_nees(&est, &truth, false, 1.0).ok_or("nothing scored")?;
    let eighths: Vec<String> = (0..8)
        .map(|i| {
            let part = &est[i * est.len() / 8..(i + 1) * est.len() / 8];
            position_nees(part, &truth, false, 1.0).map_or("-".into(), |n| format!("{:.2}", n.mean))
        })
        .collect();
    println!(
        "fixes {} ATE {ate:.3} m NEES {:.2} [{:.2}, {:.2}] x {:.2} y {:.2} z {:.2} eighths {} range NIS {:.3} ({} ranges)",
        fixes.len(),
        n.mean,
        n.interval_95.0,
        n.interval_95.1,
        n.per_axis[0],
        n.per_axis[1],
        n.per_axis[2],
        eighths.join(" "),
        state.range_nis.0 / state.range_nis.1.max(1) as f64,
        state.range_nis.1,
    );
    // The fixes interpolated to the truth's stamps (as the synchronizer does to the camera's:
    // two fixes before and one after), with their cross-covariances and without (eq 30).
    let sync: Vec<timesync::Fix> = fixes
        .iter()
        .map(|f| timesync::Fix {
            t_s: f.stamp_ns as f64 / 1e9,
            seq: 0,
            position_m: f.estimate.position_m,
            covariance_m2: f.estimate.covariance_m2,
            velocity_mps: f.estimate.velocity_mps,
            cross_prev: f
                .cross_prev
                .map(|(prev_ns, c)| timesync::CrossPrev { prev_t_s: prev_ns as f64 / 1e9, covariance_m2: c }),
        })
        .collect();
    let linked = sync.iter().filter(|f| f.cross_prev.is_some()).count();
    for with_cross in [false, true] {
        let mut est = vec![];
        let mut correlated = 0;
        for (t, _) in &truth {
            let b = sync.partition_point(|f| f.t_s < *t);
            if b < 2 || b >= sync.len() || sync[b].t_s - sync[b - 2].t_s > 5.0 {
                continue;
            }
            let used: Vec<timesync::Fix> = sync[b - 2..=b]
                .iter()
                .map(|f| if with_cross { *f } else { timesync::Fix { cross_prev: None, ..*f } })
                .collect();
            let i = timesync::interpolate(*t, &used)?;
            correlated += usize::from(i.correlated);
            est.push((*t, i.position_m, i.covariance_m2));
        }
        let n = position_nees(&est, &truth, false, 1.0).ok_or("nothing scored")?;
        println!(
            "interpolated at the truth's stamps, {}: NEES {:.2} [{:.2}, {:.2}] x {:.2} y {:.2} z {:.2} ({} of {} with \
             the fixes' correlation; {linked} of {} fixes linked to the one before)",
            if with_cross { "the fixes' cross-covariances" } else { "eq 30" },
            n.mean,
            n.interval_95.0,
            n.interval_95.1,
            n.per_axis[0],
            n.per_axis[1],
            n.per_axis[2],
            correlated,
            est.len(),
            sync.len()
        );
    }
    Ok(())
}

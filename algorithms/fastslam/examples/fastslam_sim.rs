//! Runs FastSLAM on the simulated mission without IPC and prints accuracy and speed:
//! `cargo run --release -p fastslam --example fastslam_sim -- [particles] [motion|optimal] [legs] [threads]`.

use std::collections::BTreeMap;
use std::time::Instant;

use fastslam::eval::{TrajectorySample, evaluate, overall_ate};
use fastslam::{FastSlam, FastSlamConfig, Observation, Proposal};
use sim::{SimConfig, SimEvent, Simulator};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let particles: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(100);
    let proposal = match args.get(2).map(String::as_str) {
        Some("optimal") => Proposal::Optimal,
        _ => Proposal::Motion,
    };
    let mut sc = SimConfig::default();
    sc.sensors.depth_camera.rate_hz = 0.0;
    if let Some(legs) = args.get(3).and_then(|s| s.parse().ok()) {
        sc.mission.legs = legs;
    }
    let mut sim = Simulator::new(sc).unwrap();
    let body_from_cam = sim.body_from_stereo();
    let threads = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(0);
    let cfg = FastSlamConfig { particles, proposal, threads, ..Default::default() };
    let mut f = FastSlam::new(cfg).unwrap();
    let mut traj = vec![];
    let mut origins = BTreeMap::from([(0u32, 0.0)]);
    let (mut frames, mut update_s, mut matched, mut segs) = (0usize, 0.0, 0usize, vec![]);
    let mut update_ms: Vec<f64> = vec![];
    let mut last_t = 0.0;
    for e in sim.by_ref() {
        match e {
            SimEvent::Odometry(o) => {
                f.predict(&o.input, o.variances).unwrap();
                last_t = o.t_s;
            }
            SimEvent::Stereo(fr) => {
                let obs: Vec<Observation> = fr
                    .observations
                    .iter()
                    .filter_map(|o| {
                        Observation::from_camera(
                            &o.point_cam_m,
                            &o.covariance_cam_m2,
                            Some(o.descriptor),
                            &body_from_cam,
                        )
                        .ok()
                    })
                    .collect();
                let t0 = Instant::now();
                let r = f.update(&obs);
                update_s += t0.elapsed().as_secs_f64();
                update_ms.push(t0.elapsed().as_secs_f64() * 1e3);
                frames += 1;
                matched += r.matched;
                if let Some(reason) = r.new_segment {
                    segs.push(format!("t={:.1}s seg {}: {reason}", fr.t_s, f.segment()));
                    origins.insert(f.segment(), fr.t_s);
                    continue;
                }
                let e = f.estimate();
                traj.push(TrajectorySample {
                    t_s: fr.t_s,
                    segment: f.segment(),
                    map_from_body: e.map_from_body,
                    covariance: e.covariance,
                });
            }
            _ => {}
        }
    }
    let _ = last_t;
    let truth: Vec<_> = sim.truth().iter().map(|t| (t.t_s, t.world_from_body)).collect();
    let scores = evaluate(&traj, &truth, &origins);
    for s in &scores {
        println!(
            "segment {:>2}: {:>5} poses, ATE {:.3} m, NEES {:.2}, position NEES {:.2} ({:.0}% in the 95% interval)",
            s.segment,
            s.samples,
            s.ate_m,
            s.nees,
            s.nees_position,
            s.nees_position_in_95 * 100.0
        );
    }
    for s in &segs {
        println!("{s}");
    }
    update_ms.sort_by(f64::total_cmp);
    let q = |p: f64| update_ms.get(((update_ms.len() as f64 - 1.0) * p) as usize).copied().unwrap_or(f64::NAN);
    println!("update per frame: p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms", q(0.5), q(0.99), q(1.0));
    println!(
        "{particles} particles, {proposal:?}: ATE {:.3} m over {} segments, mean NEES {:.1}, position NEES {:.2} ({:.0}% in the 95% interval); {frames} frames, {:.2} ms/frame, {:.1} matched/frame",
        overall_ate(&scores),
        scores.len(),
        fastslam::eval::weighted_mean(&scores, |s| s.nees),
        fastslam::eval::weighted_mean(&scores, |s| s.nees_position),
        fastslam::eval::weighted_mean(&scores, |s| s.nees_position_in_95) * 100.0,
        update_s * 1e3 / frames as f64,
        matched as f64 / frames as f64
    );
    // Bar-Shalom's test of the mean position NEES over every pose scored.
    let poses: usize = scores.iter().map(|s| s.samples).sum();
    let nees = fastslam::eval::weighted_mean(&scores, |s| s.nees_position);
    if let Some((lo, hi)) = geometry::stats::mean_chi2_interval(3, poses, 0.95) {
        let verdict = if nees < lo {
            "below it: the covariance is too large"
        } else if nees > hi {
            "above it: the covariance is too small"
        } else {
            "inside: consistent"
        };
        println!(
            "position NEES {nees:.2} over {poses} poses; Bar-Shalom's 95 % interval for the mean [{lo:.2}, {hi:.2}]: {verdict}"
        );
    }
}

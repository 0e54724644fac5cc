//! The filter on real data: the first 1,500 scans (352 s) of the Freiburg building 079 log with
//! seeded synthetic odometry drift, scored against the benchmark's relations (Kümmerle et al.
//! 2009). Skips with a message when ../shared/data/carmen is absent. The full log with 30
//! particles is `grid_slam_bench` (README).

use datasets::carmen::{OdometrySource, read_carmen};
use grid_slam::drift::DriftModel;
use grid_slam::relations::{read_relations, score};
use grid_slam::{GridSlam, GridSlamConfig, Pose2, ScanGeometry};
use std::path::Path;

#[test]
fn fr079_relations_beat_the_drifting_odometry_and_the_published_gmapping_error() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/carmen");
    let (log_path, rel_path) = (dir.join("freiburg-079-corrected.log.gz"), dir.join("fr079.relations"));
    let test = "fr079_relations_beat_the_drifting_odometry_and_the_published_gmapping_error";
    if !datasets::shared_data_present(&log_path, test) || !datasets::shared_data_present(&rel_path, test) {
        return;
    }
    let log = read_carmen(&log_path).expect("read the log");
    let relations = read_relations(&rel_path).expect("read the relations");
    let odo = log.scan_odometry(OdometrySource::LaserLines);
    let n = 1500;
    let truth: Vec<Pose2> =
        odo[..n].iter().map(|o| o.map(|o| Pose2 { x_m: o[0], y_m: o[1], theta_rad: o[2] }).expect("pose")).collect();
    let drifted = DriftModel::default().apply(&truth);
    let s0 = &log.scans[0];
    let geom = ScanGeometry {
        angle_min_rad: s0.angle_min_rad,
        angle_increment_rad: s0.angle_increment_rad,
        beams: s0.ranges.len(),
        range_min_m: 0.01,
        range_max_m: 81.8,
        body_from_laser: Pose2::default(),
    };
    let mut f = GridSlam::new(GridSlamConfig { particles: 8, threads: 2, ..Default::default() }, geom).expect("filter");
    for (s, o) in log.scans[..n].iter().zip(&drifted) {
        f.process(s.stamp_s, *o, &s.ranges).expect("a valid scan");
    }
    let offset = 1211.38;
    let traj = f.trajectory();
    assert_eq!(traj.len(), n, "a pose for every scan");
    let ours = score(&traj, &relations, offset, 2.0);
    let odo_traj: Vec<(f64, Pose2)> = log.scans[..n].iter().zip(&drifted).map(|(s, p)| (s.stamp_s, *p)).collect();
    let odometry = score(&odo_traj, &relations, offset, 2.0);
    let mem = f.memory();
    let peak = f.peak_memory().expect("updates were made");
    eprintln!(
        "fr079 first {n} scans, 8 particles: {} relations, {:.4} ± {:.4} m, {:.3} ± {:.3} deg (odometry {:.4} m, {:.2} deg); \
         {} updates, {} resamples; memory {} bytes for {} in one map ({:.2}x), peak {} bytes ({:.2}x), {} tiles shared",
        ours.scored,
        ours.trans_mean_m,
        ours.trans_std_m,
        ours.rot_mean_deg,
        ours.rot_std_deg,
        odometry.trans_mean_m,
        odometry.rot_mean_deg,
        f.stats().updates,
        f.stats().resamples,
        mem.bytes,
        mem.best_bytes,
        mem.ratio,
        peak.bytes,
        peak.bytes as f64 / mem.best_bytes as f64,
        f.stats().shared_tiles
    );
    assert!(ours.scored > 350, "{ours:?}");
    assert!(ours.trans_mean_m <= 0.061, "gmapping's published 0.061 m: {ours:?}");
    assert!(ours.trans_mean_m < 0.5 * odometry.trans_mean_m, "{ours:?} against odometry {odometry:?}");
    assert!(ours.rot_mean_deg < 0.5 * odometry.rot_mean_deg, "{ours:?} against odometry {odometry:?}");
    assert!(ours.rot_mean_deg < 1.6, "{ours:?}");
    assert!(mem.ratio < 8.0, "tiles stay shared between the 8 particles: {mem:?}");
    assert!(f.stats().shared_tiles > 1000, "tiles written alike are shared: {:?}", f.stats());
    assert!(peak.bytes < 3 * mem.best_bytes, "the peak stays under 3 maps: {peak:?} against {mem:?}");
    // N_eff at every update, within [1, N]; the lineages left at the end.
    let neff = f.n_eff_summary().expect("updates were made");
    eprintln!("fr079 N_eff: {neff:?}");
    assert_eq!(f.n_eff_history().len() as u64, f.stats().updates);
    assert!(f.n_eff_history().iter().all(|(_, e)| (1.0 - 1e-9..=8.0 + 1e-9).contains(e)), "{neff:?}");
    assert!((1..=8).contains(&neff.distinct_ancestors), "{neff:?}");
    assert_eq!(f.lineages().len() as u64, f.stats().updates / u64::from(grid_slam::filter::LINEAGE_WINDOW));
    assert!(f.lineages().iter().all(|l| (1..=8).contains(l)), "{:?}", f.lineages());
}

//! The pose-graph back end on real data: the ACES building log (Austin; a scan every ~3 s, long
//! corridors around the floor) with seeded synthetic odometry drift, scored against the
//! benchmark's relations (Kümmerle et al. 2009). The filter alone leaves its long loops open
//! (relations over 60 s off by a metre, several % over 0.5 m); the back end must close them. With
//! poses between scans from the ODOM lines nearly every relation is scored.
//! Skips with a message when ../shared/data/carmen is absent.

use datasets::carmen::{OdometrySource, read_carmen};
use grid_slam::backend::{BackEnd, BackEndConfig};
use grid_slam::drift::DriftModel;
use grid_slam::relations::{read_relations, score};
use grid_slam::{GridSlam, GridSlamConfig, Pose2, ScanGeometry};
use std::path::Path;

#[test]
fn aces_long_loops_close_with_the_pose_graph() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/carmen");
    let (log_path, rel_path) = (dir.join("aces-corrected.log.gz"), dir.join("aces.relations"));
    let test = "aces_long_loops_close_with_the_pose_graph";
    if !datasets::shared_data_present(&log_path, test) || !datasets::shared_data_present(&rel_path, test) {
        return;
    }
    let log = read_carmen(&log_path).expect("read the log");
    let relations = read_relations(&rel_path).expect("read the relations");
    let odo = log.scan_odometry(OdometrySource::LaserLines);
    let (scans, truth): (Vec<_>, Vec<Pose2>) = log
        .scans
        .iter()
        .zip(&odo)
        .filter_map(|(s, o)| o.map(|o| (s, Pose2 { x_m: o[0], y_m: o[1], theta_rad: o[2] })))
        .unzip();
    // The ODOM lines (every 0.2 s) between the scans (every ~2 s), drifted like the scans.
    let at_scans: Vec<(f64, Pose2)> = scans.iter().map(|s| s.stamp_s).zip(truth.iter().copied()).collect();
    let track: Vec<(f64, Pose2)> = log
        .odometry_in_order()
        .0
        .into_iter()
        .map(|(t, o)| (t, Pose2 { x_m: o[0], y_m: o[1], theta_rad: o[2] }))
        .collect();
    let (drifted, between) = DriftModel { seed: 7, ..Default::default() }.apply_between(&at_scans, &track);
    let odometry = grid_slam::densify::interleave(
        &at_scans.iter().zip(&drifted).map(|(s, d)| (s.0, *d)).collect::<Vec<_>>(),
        &between,
    );
    let s0 = scans[0];
    let geom = ScanGeometry {
        angle_min_rad: s0.angle_min_rad,
        angle_increment_rad: s0.angle_increment_rad,
        beams: s0.ranges.len(),
        range_min_m: 0.01,
        range_max_m: s0.range_max_m.unwrap_or(81.8),
        body_from_laser: Pose2::default(),
    };
    let mut f = GridSlam::new(GridSlamConfig { particles: 8, threads: 2, ..Default::default() }, geom).expect("filter");
    let mut back = BackEnd::new(BackEndConfig { threads: 2, ..Default::default() }).expect("back end");
    let mut refused = 0;
    for (s, o) in scans.iter().zip(&drifted) {
        match f.process(s.stamp_s, *o, &s.ranges) {
            Ok(out) if out.updated => back.add_node(out.update, &s.ranges),
            Ok(_) => {}
            Err(_) => refused += 1,
        }
    }
    let offset = 70.14;
    let front = score(&f.trajectory(), &relations, offset, 2.0);
    let r = back.run(&f).expect("the pose graph");
    let traj = f.trajectory_with(&r.nodes);
    assert_eq!(traj.len(), scans.len() - refused, "a pose for every scan");
    let closed = score(&traj, &relations, offset, 2.0);
    eprintln!("aces, 8 particles, filter alone: {front:?}\nwith the pose graph: {closed:?}\n{:?}", r.report);
    assert!(r.report.loop_constraints > 20, "{:?}", r.report);
    // Every relation over 60 s apart spans a loop or most of one.
    assert!(closed.long_scored >= 20, "{closed:?}");
    assert!(closed.long_trans_mean_m < 0.25, "the long loops close: {closed:?}");
    assert!(closed.over_far_share <= 0.01, "at most 1 % of the relations over 0.5 m: {closed:?}");
    assert!(closed.trans_mean_m <= 0.08, "{closed:?}");
    assert!(
        closed.trans_mean_m <= front.trans_mean_m + 0.005,
        "the back end does not make the mean worse: {closed:?} against {front:?}"
    );
    // The rebuilt grid holds the map (every node's scan written).
    assert!(r.grid.tile_count() > 100);
    // With poses between scans from the odometry nearly every relation is scored (at the scans'
    // poses alone, only those near a scan: a few hundred), and the score stays at the one of
    // the log's own corrected poses given the same poses between scans (0.049 m).
    let dense = grid_slam::densify::densify(&traj, &odometry);
    let all = score(&dense, &relations, offset, 2.0);
    eprintln!("with poses between scans: {all:?}");
    assert!(closed.scored < 400 && all.scored >= 1250, "{} then {}", closed.scored, all.scored);
    assert!(all.trans_mean_m <= 0.065 && all.over_far_share <= 0.01, "{all:?}");
}

//! The grid_slam stage fed through `pipeline_runtime::testing::StageHarness` (no iceoryx2): a
//! simulated room scanned by a 360-beam laser while the base drives a loop with drifting
//! odometry, plus every kind of bad input mixed in. Every valid scan gets a pose, the bad ones are
//! counted by kind in summary.json and nothing else is lost, and the outputs are written.

use std::time::Duration;

use grid_slam::Pose2;
use pipeline_runtime::testing::StageHarness;
use shared_types::services::{GRID_SLAM_GRID, GRID_SLAM_POSE, GRID_SLAM_POSE3D, LASER, PLANAR_ODOMETRY};
use shared_types::{
    LASER_MAX_IS_NO_RETURN, LaserRange, LaserScanHeader, MsgHeader, OccupancyCell, OccupancyGridHeader, PlanarOdometry,
    PlanarPose, PoseEstimate,
};

const CONFIG: &str = r#"
[run]
out_dir = "out"
[processes.slam2d]
kind = "grid_slam"
[processes.slam2d.settings]
grid_every_s = 2.0
[processes.slam2d.settings.filter]
particles = 6
threads = 2
linear_update_m = 0.3
angular_update_rad = 0.2
"#;

/// Walls of a 10 × 6 m room with a 1 × 2 m block and a pillar, as segments.
fn walls() -> Vec<[f64; 4]> {
    vec![
        [-5.0, -3.0, 5.0, -3.0],
        [5.0, -3.0, 5.0, 3.0],
        [5.0, 3.0, -5.0, 3.0],
        [-5.0, 3.0, -5.0, -3.0],
        [1.0, 0.5, 2.0, 0.5],
        [2.0, 0.5, 2.0, 2.5],
        [2.0, 2.5, 1.0, 2.5],
        [1.0, 2.5, 1.0, 0.5],
        [-2.5, -1.2, -2.2, -1.2],
        [-2.2, -1.2, -2.2, -0.9],
        [-2.2, -0.9, -2.5, -0.9],
        [-2.5, -0.9, -2.5, -1.2],
    ]
}

fn cast(p: &Pose2, a: f64, walls: &[[f64; 4]]) -> f64 {
    let (dx, dy) = ((p.theta_rad + a).cos(), (p.theta_rad + a).sin());
    let mut best = f64::INFINITY;
    for w in walls {
        let (ex, ey) = (w[2] - w[0], w[3] - w[1]);
        let den = dx * ey - dy * ex;
        if den.abs() < 1e-12 {
            continue;
        }
        let (qx, qy) = (w[0] - p.x_m, w[1] - p.y_m);
        let t = (qx * ey - qy * ex) / den;
        let u = (qx * dy - qy * dx) / den;
        if t > 0.0 && (0.0..=1.0).contains(&u) {
            best = best.min(t);
        }
    }
    best
}

/// A holonomic loop around the block: (stamp s, true pose).
fn mission() -> Vec<(f64, Pose2)> {
    (0..400)
        .map(|k| {
            let t = k as f64 * 0.1;
            let a = t * std::f64::consts::TAU / 40.0;
            // An ellipse, heading turning slower than the path (the base strafes).
            (t, Pose2 { x_m: 3.0 * a.cos() - 0.5, y_m: 1.6 * a.sin(), theta_rad: omni::wrap_angle(0.5 * a) })
        })
        .collect()
}

fn header(t: f64, beams: u32) -> LaserScanHeader {
    LaserScanHeader {
        msg: MsgHeader { stamp_ns: (t * 1e9) as u64, ..Default::default() },
        angle_min_rad: -std::f64::consts::PI,
        angle_increment_rad: std::f64::consts::TAU / 360.0,
        range_min_m: 0.05,
        range_max_m: 12.0,
        beams,
        flags: LASER_MAX_IS_NO_RETURN,
        ..Default::default()
    }
}

#[test]
fn a_room_loop_is_mapped_and_bad_input_is_counted_without_losing_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let config_path = dir.path().join("c.toml");
    let mut h = StageHarness::<grid_slam_stage::stage::GridSlamStage>::from_config_str(
        CONFIG,
        &config_path,
        "slam2d",
        dir.path(),
    )
    .expect("opens");
    let walls = walls();
    let truth = mission();
    // Odometry with drift: 3% scale on translation and 2% on rotation.
    let mut odo = truth[0].1;
    let mut rng = 12345u64;
    let mut noise = || {
        rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((rng >> 33) as f64 / (1u64 << 31) as f64) - 0.5
    };
    let mut good_scans = 0;
    for (k, (t, p)) in truth.iter().enumerate() {
        if k > 0 {
            let u = truth[k - 1].1.between(p);
            odo = odo.compose(&Pose2 { x_m: u.x_m * 1.03, y_m: u.y_m * 1.03, theta_rad: u.theta_rad * 1.02 });
        }
        let o = PlanarOdometry { position_m: [odo.x_m, odo.y_m], yaw_rad: odo.theta_rad, ..Default::default() };
        h.feed(PLANAR_ODOMETRY, MsgHeader { stamp_ns: (t * 1e9) as u64, ..Default::default() }, o).unwrap();
        let mut ranges: Vec<LaserRange> = (0..360)
            .map(|b| {
                let a = -std::f64::consts::PI + b as f64 * std::f64::consts::TAU / 360.0;
                let r = cast(p, a, &walls) + 0.01 * noise();
                LaserRange { range_m: if r > 12.0 { 12.0 } else { r as f32 } }
            })
            .collect();
        // Warts: dropouts and NaN beams in every scan, negative ones now and then.
        ranges[(k * 7) % 360].range_m = f32::NAN;
        ranges[(k * 13) % 360].range_m = 0.0;
        if k % 10 == 3 {
            ranges[100].range_m = -1.0;
        }
        match k {
            50 => {
                // Header and slice disagree.
                h.feed_slice(LASER, header(*t, 361), &ranges).unwrap();
            }
            80 => {
                // A scan with another beam count.
                h.feed_slice(LASER, header(*t, 359), &ranges[..359]).unwrap();
            }
            _ => {
                h.feed_slice(LASER, header(*t, 360), &ranges).unwrap();
                good_scans += 1;
            }
        }
        if k == 120 {
            // A scan going back in time, and odometry going back.
            h.feed_slice(LASER, header(t - 1.0, 360), &ranges).unwrap();
            h.feed(PLANAR_ODOMETRY, MsgHeader { stamp_ns: ((t - 2.0) * 1e9) as u64, ..Default::default() }, o).unwrap();
        }
        if k % 20 == 0 {
            h.wake().unwrap();
        }
    }
    h.end_upstream("ingest").unwrap();
    let part = h.run_to_end(Duration::from_secs(120)).unwrap();
    let g = &part["grid_slam"];
    eprintln!("{part:#}");
    let poses = h.take::<PlanarPose, MsgHeader>(GRID_SLAM_POSE).unwrap();
    let poses3d = h.take::<PoseEstimate, MsgHeader>(GRID_SLAM_POSE3D).unwrap();
    assert_eq!(poses.len(), good_scans, "a pose for every valid scan, none for the bad ones");
    assert_eq!(poses3d.len(), good_scans);
    let rejected = &g["rejected"];
    assert_eq!(rejected["scans_beam_count_mismatch"], 1, "{g}");
    assert_eq!(rejected["scans_geometry_changed"], 1, "{g}");
    assert_eq!(rejected["scan_stamp_not_increasing"], 1, "{g}");
    assert_eq!(rejected["odometry_stamp_not_increasing"], 1, "{g}");
    assert!(g["invalid_beams"].as_u64().unwrap() >= 2 * good_scans as u64, "{g}");
    // One scan match per particle and update, less the copies that shared their parent's.
    let (updates, matches) = (g["updates"].as_u64().unwrap(), g["update_matches"].as_u64().unwrap());
    assert!(matches >= updates && matches <= 6 * updates, "{g}");
    if g["resamples"].as_u64().unwrap() > 0 {
        assert!(matches < 6 * updates, "copies after a resampling share their match: {g}");
    }
    // Accuracy against the truth at the same stamps.
    let mut sq = 0.0;
    for ((hd, p), (t, tp)) in poses.iter().zip(truth.iter().filter(|(t, _)| {
        let k = (t * 10.0).round() as usize;
        k != 50 && k != 80
    })) {
        assert_eq!(hd.stamp_ns, (t * 1e9) as u64);
        sq += (p.position_m[0] - tp.x_m).powi(2) + (p.position_m[1] - tp.y_m).powi(2);
    }
    let rmse = (sq / poses.len() as f64).sqrt();
    let final_traj = geometry::tum::read_tum(&dir.path().join("grid_slam.tum")).unwrap();
    // A pose at every scan and, between scans, at every odometry stamp: the two refused scans'
    // odometry gives the poses at 5.0 and 8.0 s (trajectory_between_scans).
    assert_eq!(final_traj.len(), truth.len());
    let mut fsq = 0.0;
    for ((t, p), (tt, tp)) in final_traj.iter().zip(&truth) {
        assert!((t - tt).abs() < 1e-6);
        fsq += (p.translation.x - tp.x_m).powi(2) + (p.translation.y - tp.y_m).powi(2);
    }
    let final_rmse = (fsq / final_traj.len() as f64).sqrt();
    eprintln!("live RMSE {rmse:.3} m, final path RMSE {final_rmse:.3} m over {} poses", poses.len());
    assert!(rmse < 0.05 && final_rmse < 0.05, "live {rmse:.3} m, final {final_rmse:.3} m");
    // The grid went out during the run and at the end; the files are there.
    let grids = h.take_slices::<OccupancyCell, OccupancyGridHeader>(GRID_SLAM_GRID).unwrap();
    assert!(grids.len() >= 10, "{}", grids.len());
    let (gh, cells) = grids.last().unwrap();
    assert_eq!(cells.len(), (gh.width * gh.height) as usize);
    for f in ["grid.pgm", "grid.yaml", "grid.png", "grid_slam.tum"] {
        assert!(dir.path().join(f).is_file(), "{f}");
    }
    // The true walls are in the map: cells along the room's walls are occupied within one cell.
    let res = gh.resolution_m;
    let occ = |x: f64, y: f64| -> bool {
        let (i, j) = (((x - gh.origin_m[0]) / res).floor() as i64, ((y - gh.origin_m[1]) / res).floor() as i64);
        (-1..=1).any(|di| {
            (-1..=1).any(|dj| {
                let (a, b) = (i + di, j + dj);
                a >= 0
                    && b >= 0
                    && (a as u32) < gh.width
                    && (b as u32) < gh.height
                    && cells[(b as u32 * gh.width + a as u32) as usize].value > 65
            })
        })
    };
    let (mut on, mut all) = (0, 0);
    for w in &walls[..4] {
        for s in 0..200 {
            let f = s as f64 / 200.0;
            all += 1;
            on += usize::from(occ(w[0] + f * (w[2] - w[0]), w[1] + f * (w[3] - w[1])));
        }
    }
    let share = on as f64 / all as f64;
    eprintln!("room walls occupied within one cell: {:.1}%", 100.0 * share);
    assert!(share > 0.95, "{share}");
}

/// Wakes the stage until it has processed what it was fed, as the process's loop does: a step
/// that ran out of its batch time (a slow or loaded machine) says Busy and is woken again at once.
fn settle(h: &mut StageHarness<grid_slam_stage::stage::GridSlamStage>) {
    while h.wake().unwrap() == Some(pipeline_runtime::stage::Step::Busy) {}
}

#[test]
fn a_restarted_instance_goes_on_from_the_killed_ones_map_and_trajectory() {
    let dir = tempfile::tempdir().unwrap();
    let config_path = dir.path().join("c.toml");
    let config = CONFIG.replace("grid_every_s = 2.0", "grid_every_s = 0.0\nsnapshot_every_s = 5.0");
    let mut h = StageHarness::<grid_slam_stage::stage::GridSlamStage>::from_config_str(
        &config,
        &config_path,
        "slam2d",
        dir.path(),
    )
    .expect("opens");
    let walls = walls();
    let truth = mission();
    let feed = |h: &StageHarness<grid_slam_stage::stage::GridSlamStage>, k: usize| {
        let (t, p) = truth[k];
        let o = PlanarOdometry { position_m: [p.x_m, p.y_m], yaw_rad: p.theta_rad, ..Default::default() };
        h.feed(PLANAR_ODOMETRY, MsgHeader { stamp_ns: (t * 1e9) as u64, ..Default::default() }, o).unwrap();
        let ranges: Vec<LaserRange> = (0..360)
            .map(|b| {
                let a = -std::f64::consts::PI + b as f64 * std::f64::consts::TAU / 360.0;
                LaserRange { range_m: cast(&p, a, &walls).min(12.0) as f32 }
            })
            .collect();
        h.feed_slice(LASER, header(t, 360), &ranges).unwrap();
    };
    for k in 0..230 {
        feed(&h, k);
        if k % 10 == 9 {
            settle(&mut h);
        }
    }
    settle(&mut h);
    assert!(dir.path().join("state/slam2d/grid_slam.bin").is_file(), "snapshots are taken");
    // Killed after 23 s; the last snapshot is from 20 s of data.
    let mut h = h.restart().unwrap();
    for k in 230..truth.len() {
        feed(&h, k);
        if k % 10 == 9 {
            settle(&mut h);
        }
    }
    h.end_upstream("ingest").unwrap();
    let part = h.run_to_end(Duration::from_secs(60)).unwrap();
    let traj = geometry::tum::read_tum(&dir.path().join("grid_slam.tum")).unwrap();
    let first = traj.first().unwrap().0;
    assert!(first < 0.05, "the trajectory starts at the mission's start: {first}");
    assert!(traj.len() > 350, "{} poses: the snapshot's and the restarted instance's", traj.len());
    let mut sq = 0.0;
    for (t, p) in &traj {
        let k = (t * 10.0).round() as usize;
        let tp = truth[k].1;
        sq += (p.translation.x - tp.x_m).powi(2) + (p.translation.y - tp.y_m).powi(2);
    }
    let rmse = (sq / traj.len() as f64).sqrt();
    eprintln!("after a restart: {} poses, RMSE {rmse:.3} m; {}", traj.len(), part["grid_slam"]);
    assert!(rmse < 0.05, "{rmse}: the restarted filter went on in the same map frame");
}

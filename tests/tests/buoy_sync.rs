//! The buoy EKF and the synchronizer in the pipeline: Plaza2 through ingest → buoy_ekf (the
//! accuracy goal and the dead-reckoning reference), and the simulated mission through ingest →
//! fastslam + buoy_ekf → synchronizer (every pose paired, the added latency within its bound).

use std::time::Duration;

use crate::summary_schema::part;
use buoy_ekf_stage::summary::BuoyEkfPart;
use pipeline_tests::TestRun;

const LONG: Duration = Duration::from_secs(150);

fn run_to_end(run: &mut TestRun, processes: &str, from: &str) -> serde_json::Value {
    let run_extra = format!("end = \"end_of_stream\"\nend_of_stream_from = [{from}]\nduration_s = 200");
    run.run_to_end(&run_extra, processes, LONG)
}

#[test]
fn the_buoy_ekf_on_plaza2_meets_the_accuracy_goal_and_beats_dead_reckoning() {
    let mut run = TestRun::new("buoyplaza");
    let dir = format!("{}/../algorithms/datasets/data/plaza2", env!("CARGO_MANIFEST_DIR"));
    let procs = format!(
        r#"
[processes.buoy]
kind = "buoy_ekf"
[processes.buoy.settings.ekf]
mode = "planar"
buoys = [
    {{ id = 0, position_m = [-33.620537, 26.967797, 0.0] }},
    {{ id = 1, position_m = [-68.926537, 18.377797, 0.0] }},
    {{ id = 5, position_m = [1.709463, -5.812203, 0.0] }},
    {{ id = 6, position_m = [-37.580537, 69.227797, 0.0] }},
]

[processes.ingest]
kind = "ingest"
after = ["buoy"]
restart = "never"
[processes.ingest.settings]
source = "plaza2"
real_time_factor = 0.0
[processes.ingest.settings.plaza2]
dir = "{dir}"
"#
    );
    let s = run_to_end(&mut run, &procs, "\"buoy\"");
    let buoy: BuoyEkfPart = part(&s);
    let ates = buoy.ate_m.as_ref().expect("ate_m");
    let ate = ates.buoy_ekf.expect("ate_m.buoy_ekf");
    let dr = ates.dead_reckoning.expect("ate_m.dead_reckoning");
    // The goal is 0.5 m; docs/buoy_ekf.md and the README claim 0.407 m (a batch smoother with
    // GTSAM: 0.41 m): the claim is what is held.
    assert!(ate <= 0.41, "buoy EKF ATE {ate} m over the 0.41 m the docs claim (goal 0.5 m): {s:#}");
    let b = &buoy.buoy_ekf;
    // Every odometry message applied in stamp order: none arrived after a range it should have
    // come before (the stage drains the ranges before the odometry), so dead reckoning is the
    // reference's.
    assert!(b.invalid_inputs.is_empty(), "{b:?}");
    assert!((dr - 31.6).abs() < 0.5, "dead reckoning {dr} m, the reference measured 31.6 m: {s:#}");
    // One fix per range message once initialised (Plaza2 has 1816; the first few initialise).
    assert!((1800..=1816).contains(&b.fixes), "{b:?}");
    assert!(b.filter_errors.is_empty(), "{b:?}");
    for f in ["buoy_ekf.tum", "dead_reckoning.tum"] {
        let text = std::fs::read_to_string(run.out_dir().join(f)).unwrap();
        assert!(text.lines().count() > 1000, "{f}");
    }
}

#[test]
fn the_synchronizer_pairs_every_slam_pose_within_its_latency_bound() {
    let mut run = TestRun::new("syncsim");
    let procs = r#"
[processes.sync]
kind = "synchronizer"
[processes.sync.settings]
end_after = ["slam", "buoy"]
[processes.sync.settings.sync]
max_latency_s = 0.3

[processes.buoy]
kind = "buoy_ekf"
after = ["sync"]
[processes.buoy.settings.ekf]
mode = "spatial"
buoys = [
    { id = 0, position_m = [-10.0, -10.0, 0.0] },
    { id = 1, position_m = [130.0, -10.0, 0.0] },
    { id = 2, position_m = [130.0, 90.0, 0.0] },
    { id = 3, position_m = [-10.0, 90.0, 0.0] },
    { id = 4, position_m = [60.0, 100.0, 0.0] },
]

[processes.slam]
kind = "fastslam"
after = ["sync"]
[processes.slam.settings.filter]
particles = 20

[processes.ingest]
kind = "ingest"
after = ["slam", "buoy"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 40.0
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#;
    let s = run_to_end(&mut run, procs, "\"sync\"");
    let slam: fastslam_stage::summary::FastSlamPart = part(&s);
    let sync: synchronizer_stage::summary::SynchronizerPart = part(&s);
    let sup: supervisor::report::SupervisorPart = part(&s);
    let frames = slam.slam.frames as u64;
    let sync = &sync.synchronizer;
    let poses = &sync.poses;
    let paired = poses.interpolated + poses.extrapolated;
    assert_eq!(paired + poses.unavailable, frames, "every SLAM pose accounted for: {sync:?}");
    assert_eq!(sync.pairs, paired);
    // Poses before the buoy EKF's first fix (trilateration needs a depth reading and 4 buoys)
    // may be unavailable or extrapolated; everything after is interpolated.
    assert!(poses.interpolated as f64 >= 0.8 * frames as f64, "{sync:?}");
    // The added latency (pose arrival to pair publication, wall time) stays within the
    // configured wait plus scheduling slack on a loaded 2-core machine.
    let max_ms = sync.added_latency_ms.max.expect("pairs were published");
    assert!(max_ms <= 300.0 + 250.0, "added latency {max_ms} ms over the 300 ms bound: {sync:?}");
    assert!(sup.processes["sync"].messages_out >= paired, "{s:#}");
    let buoy: BuoyEkfPart = part(&s);
    let ates = buoy.ate_m.as_ref().expect("ate_m");
    let (ate, dr) = (ates.buoy_ekf.unwrap(), ates.dead_reckoning.unwrap());
    assert!(ate < dr, "buoy EKF {ate} m against dead reckoning {dr} m");
}

#[test]
fn invalid_buoy_ekf_and_synchronizer_settings_name_their_keys() {
    for (kind, settings, key) in [
        (
            "buoy_ekf",
            "[processes.p.settings.ekf.range]\ngate_probability = 1.5",
            "processes.p.settings.ekf.range.gate_probability",
        ),
        ("buoy_ekf", "[processes.p.settings.ekf]\nmode = \"flat\"", "processes.p.settings.ekf.mode"),
        ("buoy_ekf", "[processes.p.settings]\nodometry_wait_s = -1.0", "processes.p.settings.odometry_wait_s"),
        ("synchronizer", "[processes.p.settings.sync]\ncapacity = 2", "processes.p.settings.sync.capacity"),
        ("synchronizer", "[processes.p.settings]\nend_aftr = [\"slam\"]", "processes.p.settings.end_aftr"),
    ] {
        let mut run = TestRun::new("badbuoy");
        let procs = format!("[processes.p]\nkind = \"{kind}\"\n{settings}\n");
        let cfg = run.write_config("end = \"signal\"", &procs);
        run.start_supervisor(&cfg, &[]);
        let status = run.wait_supervisor(Duration::from_secs(20)).expect("exits");
        assert_eq!(status.code(), Some(2), "{}", run.log());
        assert!(run.log().contains(&format!("`{key}`")), "must name `{key}`:\n{}", run.log());
    }
}

#[test]
fn the_heavy_outlier_mission_stays_within_1_2x_of_the_same_mission_with_the_outliers_removed() {
    // config/buoy_outliers.toml as committed (3 buoys, 15 % gross errors of 1-10 m of either
    // sign, sim seed 1), and the same mission with those ranges left out: every other range is
    // the same (`outliers_removed`), so the ratio is what the outliers cost the filter.
    let path = format!("{}/../config/buoy_outliers.toml", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).expect("config/buoy_outliers.toml");
    let procs = &text[text.find("\n[processes.").expect("a [processes.*] table")..];
    assert!(procs.contains("outliers_both_signs = true\n"), "config/buoy_outliers.toml changed: update this test");
    let removed_procs =
        procs.replace("outliers_both_signs = true\n", "outliers_both_signs = true\noutliers_removed = true\n");
    let mut summaries = vec![];
    for (tag, p) in [("buoyout", procs.to_string()), ("buoyrem", removed_procs)] {
        let mut run = TestRun::new(tag);
        summaries.push(run_to_end(&mut run, &p, "\"buoy\""));
    }
    let ate = |s: &serde_json::Value| part::<BuoyEkfPart>(s).ate_m.and_then(|a| a.buoy_ekf).expect("ate_m.buoy_ekf");
    let (with, removed) = (ate(&summaries[0]), ate(&summaries[1]));
    assert!(with <= 1.2 * removed, "ATE {with} m with the outliers, {removed} m with them removed");
    assert!(with < 0.5, "ATE {with} m: {:#}", summaries[0]);
    // The outliers are rejected and said so per buoy; with them removed next to nothing is.
    for (s, lo, hi) in [(&summaries[0], 0.08, 0.25), (&summaries[1], 0.0, 0.05)] {
        let b = part::<BuoyEkfPart>(s).buoy_ekf;
        assert!(b.initialised, "{b:?}");
        assert_eq!(b.per_buoy.len(), 3, "{b:?}");
        for p in &b.per_buoy {
            let share = p.rejected_share;
            assert!((lo..=hi).contains(&share), "rejected share {share} outside {lo}-{hi}: {b:?}");
        }
        assert!(b.start_checks >= 1, "{b:?}");
        assert!(b.invalid_inputs.is_empty(), "{b:?}");
    }
}

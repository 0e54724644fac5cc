//! 2-D grid SLAM under the supervisor on real data: a *truncated* copy of the Freiburg 079 CARMEN
//! log (the gzip stream cut at 30%) replayed by ingest (`source = "carmen"`, seeded odometry drift)
//! into the grid_slam process. The run ends cleanly, the truncation is counted and reported, the
//! scans read before it are all mapped, and the outputs (map_server files, PNG, TUM) and the
//! relation scores are there. Skips with a message when ../shared/data/carmen is absent.

use std::time::Duration;

use pipeline_tests::TestRun;

#[test]
fn a_truncated_carmen_log_is_mapped_up_to_the_cut_and_the_cut_is_reported() {
    let data = format!("{}/../../shared/data/carmen", env!("CARGO_MANIFEST_DIR"));
    let log = format!("{data}/freiburg-079-corrected.log.gz");
    if !datasets::shared_data_present(&log, "a_truncated_carmen_log_is_mapped_up_to_the_cut_and_the_cut_is_reported") {
        return;
    }
    let mut run = TestRun::new("gridslam");
    let bytes = std::fs::read(&log).unwrap();
    let cut = run.dir.path().join("fr079-cut.log.gz");
    std::fs::write(&cut, &bytes[..bytes.len() * 3 / 10]).unwrap();
    let processes = format!(
        r#"
[processes.slam2d]
kind = "grid_slam"
[processes.slam2d.settings]
relations = "{data}/fr079.relations"
relations_offset_s = 1211.38
grid_every_s = 10.0
[processes.slam2d.settings.filter]
particles = 8
threads = 2

[processes.ingest]
kind = "ingest"
after = ["slam2d"]
[processes.ingest.settings]
source = "carmen"
real_time_factor = 0.0
[processes.ingest.settings.carmen]
file = "{cut}"
odometry = "laser_lines"
add_drift = true
"#,
        cut = cut.display()
    );
    let summary = run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"slam2d\"]",
        &processes,
        Duration::from_secs(300),
    );
    crate::summary_schema::assert_declared(&summary);
    crate::summary_schema::assert_valid_by_jsonschema(&run.out_dir().join("summary.json"));
    use crate::summary_schema::part;
    let ingest: ingest_stage::summary::IngestPart = part(&summary);
    let grid: grid_slam_stage::summary::GridSlamPart = part(&summary);
    let ingest = &ingest.ingest;
    let scans = ingest.messages.laser;
    assert!(scans > 800 && scans < 4791, "{ingest:?}");
    // Odometry with every scan, and fr079's few ODOM lines strictly between two scans.
    let between = ingest.messages.planar_odometry - scans;
    assert!(between < scans / 20, "{ingest:?}");
    assert_eq!(ingest.data_warts.get("file_truncated"), Some(&1), "{ingest:?}");
    assert!(run.log().contains("the replay ends there"), "the cut is warned about");
    let g = grid.grid_slam.run.as_ref().expect("the filter ran");
    assert_eq!(grid.grid_slam.scans, scans, "every scan read is mapped: {g:?}");
    assert_eq!(g.poses_published, scans, "{g:?}");
    // A clean log: nothing refused. Scans placed with the latest odometry instead of interpolated
    // (`scans_with_stale_odometry`: the odometry of a scan had not arrived 0.5 s of data later)
    // happen now and then in this as-fast-as-possible replay (a race between the laser and the
    // odometry queues, not understood yet: 13 of ~1,400 scans in one of two runs); they stay few.
    for (kind, &n) in &grid.grid_slam.rejected {
        assert!(kind == "scans_with_stale_odometry" && n * 50 < scans, "{kind}: {n} of {scans}: {g:?}");
    }
    let rel = g.relations.as_ref().expect("scored against the relations");
    eprintln!("relations on the first {scans} scans: {rel:?}; ATE {}", summary["ate_m"]);
    assert!(rel.scored > 250, "{rel:?}");
    assert!(rel.trans_mean_m < 0.061, "{rel:?}");
    assert!(rel.rot_mean_deg < 1.6, "{rel:?}");
    // Against the log's corrected poses, unaligned: the first 312 s close no large loop, so this
    // is the drift of the map frame (0.53 m here; 0.12 m over the whole log, docs/grid_slam.md).
    let ate = grid.ate_m.as_ref().and_then(|a| a.grid_slam).expect("ATE");
    assert!(ate < 1.0, "against the log's corrected poses: {ate}");
    let out = run.out_dir();
    for f in ["grid.pgm", "grid.yaml", "grid.png", "grid_slam.tum", "ground_truth.tum"] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let yaml = std::fs::read_to_string(out.join("grid.yaml")).unwrap();
    assert!(yaml.contains("image: grid.pgm") && yaml.contains("resolution: 0.05"), "{yaml}");
    let pgm = std::fs::read(out.join("grid.pgm")).unwrap();
    assert!(pgm.starts_with(b"P5\n"));

    // The metric as a command gives the stage's numbers; a bad relations file is named with its line.
    let cmd = |relations: &str| {
        std::process::Command::new(pipeline_tests::bin("relations_score"))
            .args(["--trajectory", &out.join("grid_slam.tum").display().to_string(), "--relations", relations])
            .args(["--offset", "1211.38", "--json"])
            .output()
            .unwrap()
    };
    let o = cmd(&format!("{data}/fr079.relations"));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let printed: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(printed["scored"], rel.scored);
    for (k, b) in [("trans_mean_m", rel.trans_mean_m), ("rot_mean_deg", rel.rot_mean_deg)] {
        let a = printed[k].as_f64().unwrap();
        assert!((a - b).abs() < 1e-5, "{k}: {a} (command, TUM's 6 decimals) vs {b} (stage)");
    }
    let bad = run.dir.path().join("bad.relations");
    std::fs::write(&bad, "1 2 0 0 0 0 0 0\n1 2 x 0 0 0 0 0\n").unwrap();
    let o = cmd(&bad.display().to_string());
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("bad.relations:2") && err.contains("'x' is not a number"), "{err}");
}

/// The subsampled ACES log (a scan every ~2 s, an ODOM line every 0.2 s): ingest replays the ODOM
/// lines between the scans (drifted as the scans' are), grid_slam writes a
/// pose at each of them, and nearly every relation is scored (at the scans' poses alone: 349 of
/// 1,279). The resets with stamp 0 the corrected log writes after every scan are counted.
#[test]
fn odometry_between_scans_gives_poses_between_scans_and_every_relation_a_score() {
    let data = format!("{}/../../shared/data/carmen", env!("CARGO_MANIFEST_DIR"));
    let log = format!("{data}/aces-corrected.log.gz");
    let name = "odometry_between_scans_gives_poses_between_scans_and_every_relation_a_score";
    if !datasets::shared_data_present(&log, name) {
        return;
    }
    let mut run = TestRun::new("gridodom");
    let processes = format!(
        r#"
[processes.slam2d]
kind = "grid_slam"
[processes.slam2d.settings]
relations = "{data}/aces.relations"
relations_offset_s = 70.14
grid_every_s = 0.0
[processes.slam2d.settings.filter]
particles = 8
threads = 2

[processes.ingest]
kind = "ingest"
after = ["slam2d"]
[processes.ingest.settings]
source = "carmen"
real_time_factor = 0.0
[processes.ingest.settings.carmen]
file = "{log}"
odometry = "laser_lines"
add_drift = true
"#
    );
    let summary = run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"slam2d\"]",
        &processes,
        Duration::from_secs(300),
    );
    crate::summary_schema::assert_declared(&summary);
    use crate::summary_schema::part;
    let ingest: ingest_stage::summary::IngestPart = part(&summary);
    let grid: grid_slam_stage::summary::GridSlamPart = part(&summary);
    let ingest = &ingest.ingest;
    assert_eq!(ingest.messages.laser, 440, "{ingest:?}");
    assert!(ingest.messages.planar_odometry > 6000, "the ODOM lines between scans went out: {ingest:?}");
    assert_eq!(ingest.data_warts.get("odom_lines_out_of_order"), Some(&440), "{ingest:?}");
    assert!(run.log().contains("ODOM lines whose stamp is not after the one before"), "warned");
    let g = grid.grid_slam.run.as_ref().expect("the filter ran");
    let rel = g.relations.as_ref().expect("scored against the relations");
    eprintln!("aces with poses between scans: {rel:?}");
    assert!(rel.scored >= 1250, "{rel:?}");
    assert!(rel.trans_mean_m <= 0.065 && rel.over_far_share <= 0.01, "{rel:?}");
    let tum = std::fs::read_to_string(run.out_dir().join("grid_slam.tum")).unwrap();
    assert!(tum.lines().count() > 6000, "a pose at every odometry stamp: {}", tum.lines().count());
}

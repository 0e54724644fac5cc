//! The fastslam process in the pipeline: simulated mission → ingest → fastslam, and camera-only
//! on the KITTI features when they are present, and camera only (`motion_model = "stereo"`) on the
//! KITTI-like simulated drive of config/stereo_sim.toml, including a drive the front end cannot
//! register.

use std::time::Duration;

use crate::summary_schema::part;
use fastslam_stage::summary::FastSlamPart;
use ingest_stage::summary::IngestPart;
use pipeline_tests::TestRun;

const LONG: Duration = Duration::from_secs(120);

fn run_to_end(run: &mut TestRun, processes: &str, from: &str) -> serde_json::Value {
    let run_extra = format!("end = \"end_of_stream\"\nend_of_stream_from = [{from}]\nduration_s = 200");
    run.run_to_end(&run_extra, processes, LONG)
}

#[test]
fn fastslam_tracks_the_simulated_mission_and_reports_its_accuracy() {
    let mut run = TestRun::new("slamsim");
    let procs = r#"
[processes.slam]
kind = "fastslam"
[processes.slam.settings.filter]
particles = 30

[processes.ingest]
kind = "ingest"
after = ["slam"]
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
    let s = run_to_end(&mut run, procs, "\"slam\"");
    let (slam, ingest): (FastSlamPart, IngestPart) = (part(&s), part(&s));
    let frames = slam.slam.frames as u64;
    assert_eq!(frames, ingest.ingest.messages.stereo, "every stereo frame processed: {s:#}");
    let ate = slam.ate_m.as_ref().and_then(|a| a.slam).expect("ATE against the simulator's ground truth");
    assert!(ate.is_finite() && ate < 1.0, "ATE {ate} m");
    assert!(slam.nees.as_ref().and_then(|n| n.slam).is_some_and(f64::is_finite), "{:#}", s["nees"]);
    let tum = std::fs::read_to_string(run.out_dir().join("slam_local.tum")).unwrap();
    assert_eq!(tum.lines().count() as u64, frames);
    // Pose, particles and diagnostics went out once per frame (plus end of stream).
    let sup: supervisor::report::SupervisorPart = part(&s);
    assert!(sup.processes["slam"].messages_out >= 3 * frames);
}

#[test]
fn camera_only_fastslam_runs_on_the_kitti_features_when_present() {
    let dir = format!("{}/../../shared/data/stereo_vo_large", env!("CARGO_MANIFEST_DIR"));
    let factors = std::path::Path::new(&dir).join("VO_stereo_factors_large.txt");
    if !datasets::shared_data_present(factors, "camera_only_fastslam_runs_on_the_kitti_features_when_present") {
        return;
    }
    let mut run = TestRun::new("slamkitti");
    let procs = format!(
        r#"
[processes.slam]
kind = "fastslam"
[processes.slam.settings]
motion_model = "constant_velocity"
camera.identity = true
[processes.slam.settings.filter]
particles = 50

[processes.ingest]
kind = "ingest"
after = ["slam"]
restart = "never"
[processes.ingest.settings]
source = "stereo_vo"
real_time_factor = 0.0
[processes.ingest.settings.stereo_vo]
dir = "{dir}"
"#
    );
    let s = run_to_end(&mut run, &procs, "\"slam\"");
    assert_eq!(part::<FastSlamPart>(&s).slam.frames, 26, "{s:#}");
    let tum = std::fs::read_to_string(run.out_dir().join("slam_local.tum")).unwrap();
    assert_eq!(tum.lines().count(), 26);
}

/// `[processes.*]` of config/stereo_sim.toml (camera only, `motion_model = "stereo"`) on a drive of
/// `frames` frames with 30 particles, the source's track ids on, and `drive` added to the drive's
/// settings.
fn stereo_sim_processes(frames: usize, drive: &str) -> String {
    let path = format!("{}/../config/stereo_sim.toml", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).expect("config/stereo_sim.toml");
    let start = text.find("[processes.").expect("a process table");
    let mut procs = text[start..].to_string();
    for (from, to) in [
        ("particles = 100", "particles = 30".to_string()),
        ("frames = 400", format!("frames = {frames}\n{drive}")),
        ("track_ids = false", "track_ids = true".to_string()),
        ("after = [\"slam\"]", "after = [\"slam\"]\nrestart = \"never\"".to_string()),
    ] {
        assert!(procs.contains(from), "config/stereo_sim.toml no longer has `{from}`: update this test");
        procs = procs.replace(from, &to);
    }
    assert!(procs.contains("motion_model = \"stereo\""), "config/stereo_sim.toml: camera only");
    procs
}

#[test]
fn camera_only_fastslam_tracks_the_kitti_like_drive_with_the_source_track_ids() {
    let mut run = TestRun::new("slamroad");
    let s = run_to_end(&mut run, &stereo_sim_processes(150, ""), "\"slam\"");
    let (part_slam, ingest): (FastSlamPart, IngestPart) = (part(&s), part(&s));
    let slam = &part_slam.slam;
    eprintln!("ate {} nees {} slam {}", s["ate_m"], s["nees"], s["slam"]);
    assert_eq!(slam.motion_model, fastslam_stage::MotionModel::Stereo, "{slam:?}");
    let frames = slam.frames as u64;
    assert_eq!(frames, ingest.ingest.messages.stereo, "every frame processed: {s:#}");
    let fe = slam.frontend.as_ref().expect("the front end's counts");
    assert_eq!(fe.frames, frames, "{fe:?}");
    assert_eq!(fe.failed, 0, "the front end registered every frame: {fe:?}");
    assert!(fe.by_track_ids > frames / 2, "ingest's track ids reach the front end: {fe:?}");
    // 150 frames, ~150 m: 0.031 m here (2026-12-05); docs/fastslam.md 0.035 m over 400 frames.
    let ate = part_slam.ate_m.as_ref().and_then(|a| a.slam).expect("ATE against the drive's ground truth");
    assert!(ate <= 0.08, "ATE {ate} m over 150 frames of the simulated drive: {s:#}");
    assert!(!run.log().contains("found no motion"), "no front-end failure was warned about");
}

#[test]
fn a_camera_only_drive_the_front_end_cannot_register_is_warned_counted_and_still_ends() {
    // Four features a frame: too few for the stereo front end to find the motion, every frame.
    let mut run = TestRun::new("slamroadfail");
    let s = run_to_end(&mut run, &stereo_sim_processes(30, "max_features = 4"), "\"slam\"");
    let (slam, ingest): (FastSlamPart, IngestPart) = (part(&s), part(&s));
    let fe = slam.slam.frontend.as_ref().expect("the front end's counts");
    let frames = slam.slam.frames as u64;
    assert_eq!(frames, ingest.ingest.messages.stereo, "every frame still processed: {s:#}");
    // The first frame has nothing to register against; every later one fails.
    assert!(fe.failed + 1 >= frames, "{fe:?}");
    let log = run.log();
    assert!(log.contains("stereo front end found no motion"), "each failure warned (the first ten): {log}");
    assert!(log.contains(&format!("found no motion for {} of {frames} frames", fe.failed)), "and in summary: {log}");
}

#[test]
fn invalid_fastslam_settings_name_their_keys() {
    for (settings, key) in [
        ("[processes.slam.settings.filter]\nparticles = 0", "processes.slam.settings.filter.particles"),
        (
            "[processes.slam.settings.filter.association]\nratio = 2.0",
            "processes.slam.settings.filter.association.ratio",
        ),
        ("[processes.slam.settings]\nmotion_model = \"teleport\"", "processes.slam.settings.motion_model"),
    ] {
        let mut run = TestRun::new("badslam");
        let procs = format!("[processes.slam]\nkind = \"fastslam\"\n{settings}\n");
        let cfg = run.write_config("end = \"signal\"", &procs);
        run.start_supervisor(&cfg, &[]);
        let status = run.wait_supervisor(Duration::from_secs(20)).expect("exits");
        assert_eq!(status.code(), Some(2), "{}", run.log());
        assert!(run.log().contains(&format!("`{key}`")), "must name `{key}`:\n{}", run.log());
    }
}

//! The fastslam process in the pipeline: simulated mission → ingest → fastslam, and camera-only
//! on the KITTI features when they are present.

use std::time::Duration;

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
    let frames = s["slam"]["frames"].as_u64().unwrap();
    assert_eq!(frames, s["ingest"]["messages"]["stereo"].as_u64().unwrap(), "every stereo frame processed: {s:#}");
    let ate = s["ate_m"]["slam"].as_f64().expect("ATE against the simulator's ground truth");
    assert!(ate.is_finite() && ate < 1.0, "ATE {ate} m");
    assert!(s["nees"]["slam"].as_f64().unwrap().is_finite());
    let tum = std::fs::read_to_string(run.out_dir().join("slam_local.tum")).unwrap();
    assert_eq!(tum.lines().count() as u64, frames);
    // Pose, particles and diagnostics went out once per frame (plus end of stream).
    assert!(s["processes"]["slam"]["messages_out"].as_u64().unwrap() >= 3 * frames);
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
    assert_eq!(s["slam"]["frames"], 26, "{s:#}");
    let tum = std::fs::read_to_string(run.out_dir().join("slam_local.tum")).unwrap();
    assert_eq!(tum.lines().count(), 26);
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

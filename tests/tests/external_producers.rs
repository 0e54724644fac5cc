//! External producers (not using the pipeline's runtime) feed the pipeline; bad data from them is
//! rejected by reason without harm; a wrong layout under a contract name is refused by iceoryx2.

use std::process::Command;
use std::time::Duration;

use pipeline_tests::{TestRun, bin};

const LONG: Duration = Duration::from_secs(60);

fn pipeline(run: &TestRun, producer_args: &[&str]) -> std::path::PathBuf {
    let args = producer_args.iter().map(|a| format!("\"{a}\"")).collect::<Vec<_>>().join(", ");
    let procs = format!(
        "[processes.monitor]\nkind = \"sensor_monitor\"\n[processes.monitor.settings]\nknown_buoy_ids = [0, 1, 2, 3]\nmax_cloud_points = 5000\n\n\
         [processes.driver]\nkind = \"external\"\nbinary = \"{}\"\nargs = [{args}]\nafter = [\"monitor\"]\nheartbeat = false\nrestart = \"never\"\n",
        bin("external_producer").display()
    );
    run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"monitor\"]\nduration_s = 60", &procs)
}

fn counts(s: &serde_json::Value, service: &str) -> serde_json::Value {
    s["sensor_monitor"][service].clone()
}

#[test]
fn the_rust_external_producer_feeds_the_pipeline() {
    let mut run = TestRun::new("rustprod");
    let cfg = pipeline(&run, &["--frames", "60", "--rate-hz", "200", "--points", "2000"]);
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(LONG).expect("run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    let s = run.summary();
    assert_eq!(counts(&s, "pipeline/sensors/odometry")["accepted"], 60, "{s:#}");
    assert_eq!(counts(&s, "pipeline/sensors/buoy_ranges")["accepted"], 6);
    assert_eq!(counts(&s, "pipeline/sensors/cloud")["accepted"], 12);
    assert_eq!(s["sensor_monitor"]["cloud_points"], 12 * 2000);
    for svc in ["pipeline/sensors/odometry", "pipeline/sensors/buoy_ranges", "pipeline/sensors/cloud"] {
        assert_eq!(counts(&s, svc)["rejected"], serde_json::json!({}), "{svc}");
        assert_eq!(counts(&s, svc)["missed"], 0, "{svc}");
    }
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn a_hostile_producer_is_rejected_by_reason_and_crashes_nothing() {
    let mut run = TestRun::new("hostile");
    let cfg = pipeline(
        &run,
        &["--frames", "120", "--rate-hz", "300", "--points", "500", "--hostile", "--oversized-points", "20000"],
    );
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(LONG).expect("run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    let s = run.summary();
    let odo = counts(&s, "pipeline/sensors/odometry");
    assert_eq!(odo["accepted"], 120, "every valid message still arrives: {odo}");
    assert_eq!(
        odo["rejected"],
        serde_json::json!({"non_finite": 2, "bad_value": 2, "stamp_not_increasing": 2}),
        "{odo}"
    );
    let buoys = counts(&s, "pipeline/sensors/buoy_ranges");
    assert_eq!(buoys["accepted"], 12);
    assert_eq!(buoys["rejected"], serde_json::json!({"unknown_buoy": 2}));
    let cloud = counts(&s, "pipeline/sensors/cloud");
    assert_eq!(cloud["accepted"], 24);
    assert_eq!(cloud["rejected"], serde_json::json!({"oversized": 2, "non_finite": 2}));
    assert_eq!(s["processes"]["monitor"]["restarts"], 0);
    assert_eq!(s["processes"]["monitor"]["last_exit"]["code"], 0);
    assert!(run.log().contains("rejected message"), "a warning names the problem");
}

#[test]
fn a_wrong_layout_under_a_contract_service_name_is_refused() {
    let mut run = TestRun::new("wronglayout");
    let procs = "[processes.monitor]\nkind = \"sensor_monitor\"\n";
    let cfg = run.write_config("end = \"signal\"", procs);
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("ready after", 1, LONG);
    let mut cmd = Command::new(bin("external_producer"));
    cmd.arg("--wrong-layout")
        .env("SLAM_PIPELINE_IOX_PREFIX", &run.scope.prefix)
        .env("SLAM_PIPELINE_IOX_ROOT", &run.scope.root);
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).contains("REFUSED pipeline/sensors/odometry"));
    std::thread::sleep(Duration::from_millis(300));
    run.signal_supervisor(nix::sys::signal::Signal::SIGTERM);
    run.wait_supervisor(LONG).expect("stops");
    let s = run.summary();
    assert_eq!(s["processes"]["monitor"]["last_exit"]["code"], 0, "the monitor is unharmed: {s:#}");
}

#[test]
fn a_hostile_producer_crashes_neither_the_buoy_ekf_nor_fastslam_nor_the_octree_mapper() {
    let mut run = TestRun::new("hostilestages");
    let procs = format!(
        r#"
[processes.buoy]
kind = "buoy_ekf"
[processes.buoy.settings.ekf]
mode = "planar"
buoys = [
    {{ id = 0, position_m = [0.0, 0.0, 0.0] }},
    {{ id = 1, position_m = [30.0, 0.0, 0.0] }},
    {{ id = 2, position_m = [30.0, 30.0, 0.0] }},
    {{ id = 3, position_m = [0.0, 30.0, 0.0] }},
]

[processes.map]
kind = "octree_mapper"
[processes.map.settings]
pose_source = "cloud"
end_after = ["driver"]

[processes.slam]
kind = "fastslam"
[processes.slam.settings.filter]
particles = 20

[processes.driver]
kind = "external"
binary = "{}"
args = ["--frames", "120", "--rate-hz", "300", "--points", "500", "--hostile", "--oversized-points", "20000", "--stereo"]
after = ["buoy", "map", "slam"]
heartbeat = false
restart = "never"
"#,
        bin("external_producer").display()
    );
    let cfg = run.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"buoy\", \"map\", \"slam\"]\nduration_s = 60",
        &procs,
    );
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(LONG).expect("run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    let s = run.summary();
    for p in ["buoy", "map", "slam"] {
        assert_eq!(s["processes"][p]["restarts"], 0, "{p}: {s:#}");
        assert_eq!(s["processes"][p]["last_exit"]["code"], 0, "{p}: {s:#}");
    }
    // The bad messages are counted by reason, the good ones used.
    let b = &s["buoy_ekf"];
    let bad: u64 = b["invalid_inputs"].as_object().unwrap().values().map(|v| v.as_u64().unwrap()).sum::<u64>()
        + b["filter_errors"].as_object().unwrap().values().map(|v| v.as_u64().unwrap()).sum::<u64>();
    assert!(bad > 0, "{b:#}");
    let m = &s["octree_mapper"]["counters"];
    let clouds = m["clouds_inserted"].as_u64().unwrap()
        + m["clouds_dropped_no_pose"].as_u64().unwrap()
        + m["clouds_dropped_behind"].as_u64().unwrap()
        + m["clouds_missed"].as_u64().unwrap();
    assert!(clouds >= 24, "every cloud accounted for: {m:#}");
    // FastSLAM dropped the bad observations and odometry and went on with the good frames.
    let f = &s["slam"];
    assert!(f["rejected_observations"].as_u64().unwrap() > 0, "{f:#}");
    assert!(f["rejected_odometry"].as_u64().unwrap() > 0, "{f:#}");
    assert!(f["frames"].as_u64().unwrap_or(0) >= 30, "good stereo frames processed: {f:#}");
}

//! External producers (not using the pipeline's runtime) feed the pipeline; bad data from them is
//! rejected by reason without harm; a wrong layout under a contract name is refused by iceoryx2.

use std::process::Command;
use std::time::Duration;

use crate::summary_schema::part;
use pipeline_runtime::validate::GuardReport;
use pipeline_tests::{TestRun, bin};
use supervisor::report::SupervisorPart;

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

/// The sensor monitor's counters of `service`.
fn counts(s: &serde_json::Value, service: &str) -> GuardReport {
    let monitor: sensor_monitor_stage::summary::SensorMonitorPart = part(s);
    monitor.sensor_monitor.streams.get(service).cloned().unwrap_or_else(|| panic!("{service}: {s:#}"))
}

/// The exit code of process `p`'s last instance.
fn exit_code(s: &serde_json::Value, p: &str) -> Option<i32> {
    part::<SupervisorPart>(s).processes[p].last_exit.as_ref().and_then(|e| e.code)
}

/// `reason → count` as the counters hold them.
fn reasons(pairs: &[(&str, u64)]) -> std::collections::BTreeMap<String, u64> {
    pairs.iter().map(|(k, n)| (k.to_string(), *n)).collect()
}

#[test]
fn the_rust_external_producer_feeds_the_pipeline() {
    let mut run = TestRun::new("rustprod");
    let cfg = pipeline(&run, &["--frames", "60", "--rate-hz", "200", "--points", "2000"]);
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(LONG).expect("run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    let s = run.summary();
    assert_eq!(counts(&s, "pipeline/sensors/odometry").accepted, 60, "{s:#}");
    assert_eq!(counts(&s, "pipeline/sensors/buoy_ranges").accepted, 6);
    assert_eq!(counts(&s, "pipeline/sensors/cloud").accepted, 12);
    let monitor: sensor_monitor_stage::summary::SensorMonitorPart = part(&s);
    assert_eq!(monitor.sensor_monitor.cloud_points, 12 * 2000);
    for svc in ["pipeline/sensors/odometry", "pipeline/sensors/buoy_ranges", "pipeline/sensors/cloud"] {
        assert!(counts(&s, svc).rejected.is_empty(), "{svc}");
        assert_eq!(counts(&s, svc).missed, 0, "{svc}");
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
    assert_eq!(odo.accepted, 120, "every valid message still arrives: {odo:?}");
    assert_eq!(odo.rejected, reasons(&[("non_finite", 2), ("bad_value", 2), ("stamp_not_increasing", 2)]), "{odo:?}");
    let buoys = counts(&s, "pipeline/sensors/buoy_ranges");
    assert_eq!(buoys.accepted, 12);
    assert_eq!(buoys.rejected, reasons(&[("unknown_buoy", 2)]));
    let cloud = counts(&s, "pipeline/sensors/cloud");
    assert_eq!(cloud.accepted, 24);
    assert_eq!(cloud.rejected, reasons(&[("oversized", 2), ("non_finite", 2)]));
    assert_eq!(part::<SupervisorPart>(&s).processes["monitor"].restarts, 0);
    assert_eq!(exit_code(&s, "monitor"), Some(0));
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
    assert_eq!(exit_code(&s, "monitor"), Some(0), "the monitor is unharmed: {s:#}");
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
    let sup: SupervisorPart = part(&s);
    for p in ["buoy", "map", "slam"] {
        assert_eq!(sup.processes[p].restarts, 0, "{p}: {s:#}");
        assert_eq!(exit_code(&s, p), Some(0), "{p}: {s:#}");
    }
    // The bad messages are counted by reason, the good ones used.
    let b = part::<buoy_ekf_stage::summary::BuoyEkfPart>(&s).buoy_ekf;
    let bad: u64 = b.invalid_inputs.values().sum::<u64>() + b.filter_errors.values().sum::<u64>();
    assert!(bad > 0, "{b:?}");
    let m = part::<octree_mapper_stage::summary::OctreeMapperPart>(&s).octree_mapper.counters;
    let clouds = m.clouds_inserted + m.clouds_dropped_no_pose + m.clouds_dropped_behind + m.clouds_missed;
    assert!(clouds >= 24, "every cloud accounted for: {m:?}");
    // FastSLAM dropped the bad observations and odometry and went on with the good frames.
    let f = part::<fastslam_stage::summary::FastSlamPart>(&s).slam;
    assert!(f.rejected_observations > 0, "{f:?}");
    assert!(f.rejected_odometry > 0, "{f:?}");
    assert!(f.frames >= 30, "good stereo frames processed: {f:?}");
}

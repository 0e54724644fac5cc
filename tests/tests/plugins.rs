//! Kinds are plug-ins: a user's own stage built on the runtime (examples/odometer) runs under the
//! supervisor, which knows nothing of it, and its settings are checked by its own binary
//! (`--check`) in the pre-flight, issues named by key; a program that does not speak the
//! protocol is refused with a reason.

use std::time::Duration;

use pipeline_tests::TestRun;

#[test]
fn a_users_own_stage_is_a_kind_without_touching_the_supervisor() {
    let mut run = TestRun::new("plugin");
    let procs = r#"
[processes.odo]
kind = "odometer"
[processes.odo.settings]
max_speed_mps = 5.0

[processes.ingest]
kind = "ingest"
after = ["odo"]
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
[processes.ingest.settings.sim.mission]
max_duration_s = 40.0
[processes.ingest.settings.sim.sensors.depth_camera]
width_px = 16
height_px = 12
"#;
    let s = run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"odo\"]\nduration_s = 120",
        procs,
        Duration::from_secs(120),
    );
    // The user's stage writes its own part, as its own struct.
    let o = crate::summary_schema::part::<odometer::OdometerPart>(&s).odometer;
    assert_eq!(o.implausible, 0, "{o:?}");
    let sup: supervisor::report::SupervisorPart = crate::summary_schema::part(&s);
    assert_eq!(sup.processes["odo"].kind, "odometer");
    let ingest: ingest_stage::summary::IngestPart = crate::summary_schema::part(&s);
    assert_eq!(o.messages, ingest.ingest.messages.odometry, "every odometry message counted");
    // The distance it integrated is the length of the simulated path (odometry noise aside).
    let truth = std::fs::read_to_string(run.out_dir().join("ground_truth.tum")).unwrap();
    let p: Vec<[f64; 3]> = truth
        .lines()
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            [v[1], v[2], v[3]]
        })
        .collect();
    let length: f64 = p
        .windows(2)
        .map(|w| ((w[1][0] - w[0][0]).powi(2) + (w[1][1] - w[0][1]).powi(2) + (w[1][2] - w[0][2]).powi(2)).sqrt())
        .sum();
    let d = o.distance_m;
    assert!(length > 20.0 && (d - length).abs() < 0.05 * length, "odometer {d:.2} m, path {length:.2} m");
}

#[test]
fn a_plugin_kinds_settings_are_checked_by_its_own_binary_before_anything_starts() {
    for (procs, needle) in [
        (
            "[processes.odo]\nkind = \"odometer\"\n[processes.odo.settings]\nmax_speed_mps = -1.0\n",
            "`processes.odo.settings.max_speed_mps`: must be a positive speed",
        ),
        ("[processes.odo]\nkind = \"odometer\"\n[processes.odo.settings]\nmax_sped = 1.0\n", "max_sped"),
        ("[processes.x]\nkind = \"mine\"\nbinary = \"/bin/true\"\n", "does not speak the pipeline protocol"),
        ("[processes.x]\nkind = \"../odometer\"\n", "cannot name a binary"),
    ] {
        let mut run = TestRun::new("plugbad");
        let cfg = run.write_config("end = \"signal\"", procs);
        run.start_supervisor(&cfg, &["--check"]);
        let status = run.wait_supervisor(Duration::from_secs(20)).expect("exits");
        let log = run.log();
        assert_eq!(status.code(), Some(2), "{procs}: {log}");
        assert!(log.contains(needle), "{procs}: `{needle}` not in:\n{log}");
        assert!(!log.contains("started process="), "{log}");
    }
}

//! Replay as fast as possible loses nothing for a consumer that is alive, however slow; a dead
//! one is skipped, and what it missed is counted per service and consumer, in the status line
//! while it happens, in a warning at the end and in summary.json.

use std::time::Duration;

use crate::summary_schema::part;
use ingest_stage::summary::IngestPart;
use pipeline_tests::TestRun;
use supervisor::report::SupervisorPart;

/// A short simulated stereo drive with few features (the consumer does not look at them).
fn drive(frames: usize) -> String {
    format!(
        r#"
[processes.ingest]
kind = "ingest"
after = ["c"]
restart = "never"
[processes.ingest.settings]
source = "stereo_sim"
real_time_factor = 0.0
progress_interval_s = 0.0
[processes.ingest.settings.stereo_sim.drive]
frames = {frames}
max_features = 40
dropped_frame_probability = 0.0
"#
    )
}

#[test]
fn a_slow_consumer_loses_no_frame_however_long_it_waits() {
    let mut run = TestRun::new("bpslow");
    // 1.2 s per frame: the stereo queue (8) fills and the source waits longer than the second it
    // used to wait before dropping.
    let procs = format!(
        "[processes.c]\nkind = \"test_consumer\"\nrestart = \"never\"\n[processes.c.settings]\nstereo_delay_ms = 1200\n{}",
        drive(12)
    );
    let s = run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"c\"]\nduration_s = 120",
        &procs,
        Duration::from_secs(90),
    );
    let (ingest, sup): (IngestPart, SupervisorPart) = (part(&s), part(&s));
    let sent = ingest.ingest.messages.stereo;
    assert_eq!(sent, 12, "{s:#}");
    let c = part::<testkit::ConsumerPart>(&s).test_consumer;
    assert_eq!(c.stereo_frames, sent, "every frame reached the slow consumer: {s:#}");
    assert_eq!(c.stereo_missed, 0);
    assert!(ingest.ingest.backpressure_wait_s > 1.0, "the source did wait: {s:#}");
    assert!(sup.undelivered.is_empty(), "{s:#}");
    assert_eq!(sup.processes["ingest"].undelivered, 0);
    assert_eq!(sup.processes["ingest"].restarts, 0, "waiting is not a hang");
    assert!(!run.log().contains("never reached"), "{}", run.log());
}

#[test]
fn a_dead_consumer_is_skipped_and_what_it_missed_is_reported() {
    let mut run = TestRun::new("bpdead");
    let procs = format!(
        "[processes.c]\nkind = \"test_consumer\"\nrestart = \"never\"\nrequired = false\n[processes.c.settings]\nstereo_delay_ms = 300\n{}",
        drive(40)
    );
    let cfg = run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"ingest\"]\nduration_s = 120", &procs);
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("process=ingest pid=", 1, Duration::from_secs(30));
    std::thread::sleep(Duration::from_secs(3)); // the consumer is behind; the source waits for it
    let pid = *run.started_pids("c").first().expect("consumer started");
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), nix::sys::signal::Signal::SIGKILL).unwrap();
    let status = run.wait_supervisor(Duration::from_secs(60)).expect("the run ends once the source is done");
    let log = run.log();
    assert!(status.code().is_some(), "{log}");
    let s = run.summary();
    let (ingest, sup): (IngestPart, SupervisorPart) = (part(&s), part(&s));
    assert_eq!(ingest.ingest.messages.stereo, 40, "the source went on without the dead consumer: {s:#}");
    let stereo = sup
        .undelivered
        .iter()
        .find(|l| l.service == "pipeline/sensors/stereo" && l.consumer == "c")
        .unwrap_or_else(|| panic!("stereo frames missed by `c` are listed: {s:#}"));
    assert_eq!(stereo.publisher, "ingest");
    let missed = stereo.messages;
    // The consumer was killed: it wrote no part of its own, so it counts nothing received.
    let received = s.get("test_consumer").map_or(0, |_| part::<testkit::ConsumerPart>(&s).test_consumer.stereo_frames);
    assert!(missed > 0 && missed + received <= 40, "missed {missed}, received {received}");
    assert!(
        log.lines()
            .any(|l| l.contains("WARN") && l.contains("never reached c") && l.contains("pipeline/sensors/stereo")),
        "a warning names the service and the consumer:\n{log}"
    );
    assert!(log.contains("UNDELIVERED"), "the status line shows it while it happens:\n{log}");
    assert!(run.leftovers().is_empty(), "{:?}", run.leftovers());
}

#[test]
fn what_a_stage_drops_by_its_own_policy_is_counted_warned_and_listed() {
    let mut run = TestRun::new("bpdropped");
    // Clouds on the SLAM pose, but no SLAM in the run: every cloud waits `pose_wait_s` for a
    // pose that never comes and is dropped; the ingest's replay still delivers every one.
    let procs = r#"
[processes.map]
kind = "octree_mapper"
restart = "never"
[processes.map.settings]
pose_source = "slam"
pose_wait_s = 0.05
end_after = ["ingest"]

[processes.ingest]
kind = "ingest"
after = ["map"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
progress_interval_s = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 10.0
[processes.ingest.settings.sim.sensors.depth_camera]
width_px = 48
height_px = 36
"#;
    let s = run.run_to_end(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"map\"]\nduration_s = 120",
        procs,
        Duration::from_secs(90),
    );
    let (ingest, sup): (IngestPart, SupervisorPart) = (part(&s), part(&s));
    let sent = ingest.ingest.messages.cloud;
    assert!(sent >= 3, "{s:#}");
    let c = part::<octree_mapper_stage::summary::OctreeMapperPart>(&s).octree_mapper.counters;
    assert_eq!(c.clouds_dropped_no_pose, sent, "every cloud arrived and was dropped without a pose: {c:?}");
    assert!(sup.undelivered.is_empty(), "{s:#}");
    let dropped = &sup.dropped;
    assert_eq!(dropped.len(), 1, "{dropped:#?}");
    let d = &dropped[0];
    assert_eq!((d.process.as_str(), d.service.as_str()), ("map", "pipeline/sensors/cloud"));
    assert_eq!(d.reason, "no pose within pose_wait_s");
    assert_eq!(d.messages, sent);
    assert_eq!(sup.processes["map"].dropped, sent);
    let log = run.log();
    assert!(
        log.lines().any(|l| l.contains("WARN")
            && l.contains(&format!("map dropped {sent} message(s) of `pipeline/sensors/cloud`: no pose"))),
        "a warning names the process, service, reason and count:\n{log}"
    );
    assert!(
        log.contains("DROPPED") && log.contains("pipeline/sensors/cloud (no pose within pose_wait_s)"),
        "the status line shows it while it happens:\n{log}"
    );
    let status: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.out_dir().join("status.json")).expect("status.json")).unwrap();
    let map = status["processes"].as_array().unwrap().iter().find(|p| p["name"] == "map").expect("map in status.json");
    assert_eq!(map["dropped"]["pipeline/sensors/cloud (no pose within pose_wait_s)"], sent, "{status:#}");
    assert!(run.leftovers().is_empty(), "{:?}", run.leftovers());
}

//! The recorder stage fed through `pipeline_runtime::testing::StageHarness` (no iceoryx2): it
//! writes what its inputs carry, ends by the runtime's `end_after` rule, sends its own end of
//! stream when asked to, and leaves a complete file when stopped instead.

use std::path::Path;
use std::time::Duration;

use pipeline_runtime::testing::StageHarness;
use recorder_stage::stage::RecorderStage;
use shared_types::services::{BUOY_FIX, SLAM_POSE};
use shared_types::{BuoyFix, MsgHeader, PoseEstimate};

const CONFIG: &str = r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
services = ["pipeline/buoy/fix", "pipeline/slam/pose", "pipeline/control/end_of_stream"]
end_after = ["buoy", "slam"]
send_end_of_stream = true
"#;

fn open(out: &Path, config: &str) -> StageHarness<RecorderStage> {
    StageHarness::from_config_str(config, Path::new("recorder_test.toml"), "rec", out).expect("opens")
}

fn feed(h: &StageHarness<RecorderStage>) {
    for i in 0..10u64 {
        let header = MsgHeader { stamp_ns: i * 1_000_000_000, ..Default::default() };
        h.feed(BUOY_FIX, header, BuoyFix { position_m: [i as f64, 0.0, 0.0], ..Default::default() }).unwrap();
    }
    for i in 0..5u64 {
        let header = MsgHeader { stamp_ns: i * 500_000_000, ..Default::default() };
        h.feed(SLAM_POSE, header, PoseEstimate::default()).unwrap();
    }
}

#[test]
fn records_until_every_end_after_process_has_ended() {
    let dir = tempfile::tempdir().unwrap();
    let mut h = open(dir.path(), CONFIG);
    feed(&h);
    h.end_upstream("buoy").unwrap();
    h.wake().unwrap();
    assert!(h.summary().is_none(), "`slam` has not ended yet");
    h.end_upstream("slam").unwrap();
    let part = h.run_to_end(Duration::from_secs(10)).unwrap();
    let rec = &part["recorder"];
    assert_eq!(rec["ended_by"], "end of stream", "{part}");
    assert_eq!(rec["messages"][BUOY_FIX], 10, "{part}");
    assert_eq!(rec["messages"][SLAM_POSE], 5, "{part}");
    assert_eq!(rec["messages"]["pipeline/control/end_of_stream"], 2, "{part}");
    assert!(dir.path().join("recording.mcap").metadata().unwrap().len() > 0);
    let eos = h.end_of_stream().unwrap().expect("send_end_of_stream = true");
    assert_eq!(eos.messages_sent, 17, "every message written");
}

#[test]
fn a_stop_drains_what_is_queued_and_leaves_a_complete_file() {
    let dir = tempfile::tempdir().unwrap();
    let mut h = open(dir.path(), &CONFIG.replace("end_after = [\"buoy\", \"slam\"]\nsend_end_of_stream = true", ""));
    feed(&h);
    let part = h.stop().unwrap();
    assert_eq!(part["recorder"]["ended_by"], "stopped", "{part}");
    assert_eq!(part["recorder"]["messages"][BUOY_FIX], 10, "{part}");
    let file = std::fs::read(dir.path().join("recording.mcap")).unwrap();
    assert!(file.ends_with(b"\x89MCAP0\r\n"), "the file has its footer magic");
}

#[test]
fn a_restarted_recorder_keeps_the_killed_instances_file_and_records_the_rest_in_a_new_one() {
    let dir = tempfile::tempdir().unwrap();
    let config = CONFIG.replace("send_end_of_stream = true", "");
    let mut h = open(dir.path(), &config);
    feed(&h);
    h.wake().unwrap();
    let mut h = h.restart().unwrap(); // killed: its file has no summary section
    feed(&h);
    h.end_upstream("buoy").unwrap();
    h.end_upstream("slam").unwrap();
    let part = h.run_to_end(Duration::from_secs(10)).unwrap();
    let rec = &part["recorder"];
    let earlier = dir.path().join("recording.part1.mcap");
    assert_eq!(rec["earlier_parts"], serde_json::json!([earlier.display().to_string()]), "{part}");
    assert!(earlier.is_file(), "the killed instance's file is kept");
    assert_eq!(rec["messages"][BUOY_FIX], 10, "the new file has what came after the restart: {part}");
    let file = std::fs::read(dir.path().join("recording.mcap")).unwrap();
    assert!(file.ends_with(b"\x89MCAP0\r\n"), "the new file is complete");
}

//! The synchronizer stage fed through `pipeline_runtime::testing::StageHarness` (no iceoryx2):
//! the pairs it publishes, the runtime's end-of-stream rule for it (`end_after = ["slam",
//! "buoy"]` in config/default.toml), and what it does when an upstream process failed for good.

use std::path::Path;
use std::time::Duration;

use pipeline_runtime::testing::StageHarness;
use shared_types::services::{BUOY_FIX, SYNC_PAIR};
use shared_types::{BuoyFix, MsgHeader, PoseEstimate, SyncedPair};
use synchronizer_stage::stage::SynchronizerStage;

fn open(out: &Path) -> StageHarness<SynchronizerStage> {
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/default.toml");
    StageHarness::from_config_file(&config, "sync", out).expect("opens")
}

fn at(t_s: f64) -> MsgHeader {
    MsgHeader { stamp_ns: (t_s * 1e9) as u64, ..Default::default() }
}

/// The vehicle moves at 1 m/s along x; a fix every second.
fn fix(t_s: f64) -> BuoyFix {
    let mut covariance_m2 = [0.0; 9];
    covariance_m2[0] = 0.01;
    covariance_m2[4] = 0.01;
    covariance_m2[8] = 0.01;
    BuoyFix {
        position_m: [t_s, 0.0, -5.0],
        covariance_m2,
        velocity_mps: [1.0, 0.0, 0.0],
        ranges_used: 4,
        ranges_rejected: 0,
        ..Default::default()
    }
}

fn pose() -> PoseEstimate {
    PoseEstimate { orientation_xyzw: [0.0, 0.0, 0.0, 1.0], frame: 2, ..Default::default() }
}

#[test]
fn pairs_each_pose_with_the_buoy_position_at_its_stamp_and_ends_after_both_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let mut h = open(dir.path());
    for t in 0..5 {
        h.feed(BUOY_FIX, at(t as f64), fix(t as f64)).unwrap();
    }
    for t in [0.5, 1.5, 2.5] {
        h.feed(shared_types::services::SLAM_POSE, at(t), pose()).unwrap();
    }
    h.wake().unwrap();
    let pairs = h.take::<SyncedPair, MsgHeader>(SYNC_PAIR).unwrap();
    assert_eq!(pairs.len(), 3, "every pose bracketed by fixes is paired at once");
    for ((header, pair), t) in pairs.iter().zip([0.5, 1.5, 2.5]) {
        assert_eq!(header.stamp_ns, (t * 1e9) as u64, "a pair keeps the pose's stamp");
        assert!((pair.buoy_position_m[0] - t).abs() < 0.02, "buoy x at {t} s: {:?}", pair.buoy_position_m);
    }

    // One of the two upstream processes ending is not the end of its inputs.
    h.end_upstream("slam").unwrap();
    h.wake().unwrap();
    assert!(h.summary().is_none(), "still waiting for `buoy`");
    assert!(h.end_of_stream().unwrap().is_none());
    h.end_upstream("buoy").unwrap();
    let part = h.run_to_end(Duration::from_secs(5)).unwrap();
    assert_eq!(part["synchronizer"]["pairs"], 3, "{part}");
    let eos = h.end_of_stream().unwrap().expect("its own end of stream");
    assert_eq!((eos.messages_sent, eos.last_seq), (3, 2));
    assert!(dir.path().join("parts/sync.json").is_file(), "the summary part is written for the supervisor");
}

#[test]
fn a_failed_upstream_ends_its_inputs_and_is_named_in_the_summary() {
    let dir = tempfile::tempdir().unwrap();
    let mut h = open(dir.path());
    for t in 0..3 {
        h.feed(BUOY_FIX, at(t as f64), fix(t as f64)).unwrap();
    }
    // A pose after the last fix waits for the next one (up to max_latency_s), with a predicted
    // pair sent at once (the buoy position extrapolated from the newest fix) ...
    h.feed(shared_types::services::SLAM_POSE, at(2.5), pose()).unwrap();
    h.end_upstream("slam").unwrap();
    h.wake().unwrap();
    let predicted = h.take::<SyncedPair, MsgHeader>(SYNC_PAIR).unwrap();
    assert_eq!(predicted.len(), 1, "a prediction at once");
    let (ph, p) = &predicted[0];
    assert_eq!(ph.stamp_ns, 2_500_000_000);
    assert_ne!(p.flags & shared_types::SYNC_PREDICTED, 0, "flagged as predicted");
    assert!((p.buoy_position_m[0] - 2.5).abs() < 0.02, "extrapolated at 1 m/s: {:?}", p.buoy_position_m);
    // ... until the buoy EKF is given up on: then it is paired by extrapolation and the stage ends.
    h.fail_upstream("buoy").unwrap();
    let part = h.run_to_end(Duration::from_secs(5)).unwrap();
    let pairs = h.take::<SyncedPair, MsgHeader>(SYNC_PAIR).unwrap();
    assert_eq!(pairs.len(), 1);
    assert_ne!(pairs[0].1.flags & shared_types::SYNC_EXTRAPOLATED, 0, "flagged as extrapolated");
    assert_eq!(pairs[0].1.flags & shared_types::SYNC_PREDICTED, 0, "the pair proper");
    assert_eq!(part["synchronizer"]["poses"]["predicted"], 1, "{part}");
    assert_eq!(part["synchronizer"]["pairs"], 1, "pairs proper: {part}");
    assert_eq!(part["processes"]["sync"]["upstream_failed"], serde_json::json!(["buoy"]), "{part}");
}

#[test]
fn a_stop_before_the_end_writes_what_there_is() {
    let dir = tempfile::tempdir().unwrap();
    let mut h = open(dir.path());
    for t in 0..4 {
        h.feed(BUOY_FIX, at(t as f64), fix(t as f64)).unwrap();
    }
    h.feed(shared_types::services::SLAM_POSE, at(1.5), pose()).unwrap();
    h.wake().unwrap();
    let part = h.stop().unwrap();
    assert_eq!(part["synchronizer"]["pairs"], 1, "{part}");
    assert!(h.end_of_stream().unwrap().is_none(), "a stopped stage sends no end of stream");
}

/// The synchronizer of robot `r1` on a host that runs one per robot: `remap` renames its ports.
const REMAPPED: &str = r#"
[processes.sync]
kind = "synchronizer"
[processes.sync.remap]
"pipeline/buoy/fix" = "r1/pipeline/buoy/fix"
"pipeline/slam/pose" = "r1/pipeline/slam/pose"
"pipeline/sync/pair" = "r1/pipeline/sync/pair"
[processes.sync.settings]
"#;

#[test]
fn a_remapped_stage_reads_and_writes_its_own_names_and_must_say_what_it_ends_after() {
    let dir = tempfile::tempdir().unwrap();
    let text = format!("{REMAPPED}end_after = [\"slam\", \"buoy\"]\n");
    let mut h =
        StageHarness::<SynchronizerStage>::from_config_str(&text, Path::new("remap.toml"), "sync", dir.path()).unwrap();
    assert!(h.feed(BUOY_FIX, at(0.0), fix(0.0)).is_err(), "no input under the contract's name");
    for t in 0..3 {
        h.feed("r1/pipeline/buoy/fix", at(t as f64), fix(t as f64)).unwrap();
    }
    h.feed("r1/pipeline/slam/pose", at(1.5), pose()).unwrap();
    h.wake().unwrap();
    let under_contract = h.take::<SyncedPair, MsgHeader>(SYNC_PAIR).unwrap_or_default();
    assert!(under_contract.is_empty(), "nothing under the contract's name");
    let pairs = h.take::<SyncedPair, MsgHeader>("r1/pipeline/sync/pair").unwrap();
    assert_eq!(pairs.len(), 1);
    assert!((pairs[0].1.buoy_position_m[0] - 1.5).abs() < 0.02, "{:?}", pairs[0].1);
    h.end_upstream("slam").unwrap();
    h.end_upstream("buoy").unwrap();
    let part = h.run_to_end(Duration::from_secs(5)).unwrap();
    assert_eq!(part["synchronizer"]["pairs"], 1, "{part}");

    // Without `end_after`, an end of stream could not say that it fed the renamed inputs.
    let text = format!("{REMAPPED}end_after = []\n");
    let e = StageHarness::<SynchronizerStage>::from_config_str(&text, Path::new("remap.toml"), "sync", dir.path())
        .err()
        .expect("refused");
    let e = e.to_string();
    assert!(
        e.contains("`pipeline/slam/pose` as `r1/pipeline/slam/pose`") && e.contains("end_after"),
        "the error names the remapped inputs and the setting: {e}"
    );
}

//! Record and replay: a short simulated mission through ingest → buoy_ekf and fastslam with the
//! recorder writing every service to MCAP (read back by the mcap crate and by Python's `mcap`
//! reader, counts equal to what the stages report), then the buoy EKF, FastSLAM and the
//! synchronizer each rerun twice in isolation from the recording: byte-identical `buoy_ekf.tum`
//! and fixes, `slam_local.tum`, and synced pairs in both replays and in the original run.
//! Needs `python3` with the `mcap` package (scripts/test.sh installs it).

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use pipeline_tests::TestRun;

const LONG: Duration = Duration::from_secs(240);

const BUOY: &str = r#"
[processes.buoy]
kind = "buoy_ekf"
after = ["rec"]
[processes.buoy.settings.ekf]
mode = "spatial"
buoys = [
    { id = 0, position_m = [-10.0, -10.0, 0.0] },
    { id = 1, position_m = [130.0, -10.0, 0.0] },
    { id = 2, position_m = [130.0, 90.0, 0.0] },
    { id = 3, position_m = [-10.0, 90.0, 0.0] },
    { id = 4, position_m = [60.0, 100.0, 0.0] },
]
"#;

const SLAM: &str = r#"
[processes.slam]
kind = "fastslam"
after = ["rec"]
[processes.slam.settings.filter]
particles = 30
"#;

const SYNC: &str = r#"
[processes.sync]
kind = "synchronizer"
after = ["rec"]
"#;

/// The buoy fixes of a recording: (stamp, payload bytes).
type Fixes = Vec<(u64, Vec<u8>)>;

/// Messages per topic and the buoy fixes of an MCAP file, by the mcap crate.
fn read_mcap(path: &Path) -> (BTreeMap<String, u64>, Fixes) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let summary = mcap::Summary::read(&bytes).expect("readable summary").expect("a summary section");
    assert!(!summary.chunk_indexes.is_empty(), "chunk indexes");
    assert!(!summary.metadata_indexes.is_empty(), "metadata");
    let mut counts = BTreeMap::new();
    let mut fixes = vec![];
    for m in mcap::MessageStream::new(&bytes).expect("MCAP") {
        let m = m.expect("message");
        *counts.entry(m.channel.topic.clone()).or_default() += 1;
        if m.channel.topic == "pipeline/buoy/fix" {
            let schema = m.channel.schema.as_ref().expect("schema");
            assert_eq!(schema.name, "slam_pipeline::v3::BuoyFix");
            assert_eq!(m.data.len(), 32 + 208, "MsgHeader + BuoyFix (wire version 3)");
            let stamp = u64::from_le_bytes(m.data[..8].try_into().unwrap());
            let publish = u64::from_le_bytes(m.data[24..32].try_into().unwrap());
            assert_eq!(m.publish_time, publish, "publish_time is the header's publish_ns");
            assert!(m.log_time >= publish, "received after it was published");
            fixes.push((stamp, m.data[32..].to_vec()));
        }
    }
    let stats = summary.stats.expect("statistics");
    assert_eq!(stats.message_count, counts.values().sum::<u64>());
    (counts, fixes)
}

/// The messages of `topic` in an MCAP file: (stamp, user header after `MsgHeader` + payload).
fn payloads(path: &Path, topic: &str) -> Fixes {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    mcap::MessageStream::new(&bytes)
        .expect("MCAP")
        .map(|m| m.expect("message"))
        .filter(|m| m.channel.topic == topic)
        .map(|m| (u64::from_le_bytes(m.data[..8].try_into().unwrap()), m.data[32..].to_vec()))
        .collect()
}

/// Messages per topic by Python's `mcap` reader.
fn read_mcap_python(path: &Path) -> BTreeMap<String, u64> {
    let script = r#"
import collections, json, sys
from mcap.reader import make_reader
counts = collections.Counter()
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f)
    summary = reader.get_summary()
    assert summary is not None and summary.chunk_indexes, "no summary / chunk indexes"
    for schema, channel, message in reader.iter_messages():
        counts[channel.topic] += 1
print(json.dumps(counts))
"#;
    let out = std::process::Command::new("python3")
        .args(["-c", script])
        .arg(path)
        .output()
        .expect("python3 is needed for this test");
    assert!(
        out.status.success(),
        "Python's mcap reader failed (install it with `python3 -m pip install mcap`, as scripts/test.sh does): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("JSON counts")
}

/// Reruns `stage` (a process block named `name`) alone from `recording`, fed `topics`; the replay's
/// recorder records `output`.
fn replay(
    tag: &str,
    recording: &Path,
    (stage, name, output): (&str, &str, &str),
    topics: &[&str],
) -> (TestRun, serde_json::Value) {
    let mut run = TestRun::new(tag);
    let topics = topics.iter().map(|t| format!("\"{t}\"")).collect::<Vec<_>>().join(", ");
    let procs = format!(
        r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
services = ["{output}"]
end_after = ["{name}"]
send_end_of_stream = true
{stage}
[processes.replay]
kind = "replayer"
after = ["{name}", "rec"]
restart = "never"
[processes.replay.settings]
file = "{}"
topics = [{topics}, "pipeline/control/end_of_stream"]
"#,
        recording.display()
    );
    let s = run.run_to_end("end = \"end_of_stream\"\nend_of_stream_from = [\"rec\"]\nduration_s = 200", &procs, LONG);
    crate::summary_schema::assert_declared(&s);
    (run, s)
}

#[test]
fn a_recorded_run_reruns_the_buoy_ekf_fastslam_and_the_synchronizer_alone_with_identical_outputs() {
    let mut orig = TestRun::new("recorig");
    let procs = format!(
        r#"
[processes.rec]
kind = "recorder"
[processes.rec.settings]
end_after = ["ingest", "buoy", "slam", "sync"]
send_end_of_stream = true
exclude = ["pipeline/sensors/cloud", "pipeline/map/voxels"]
{BUOY}
{SLAM}
{SYNC}
[processes.ingest]
kind = "ingest"
after = ["buoy", "slam", "sync", "rec"]
restart = "never"
[processes.ingest.settings]
source = "sim"
real_time_factor = 0.0
[processes.ingest.settings.sim.mission]
legs = 1
leg_length_m = 40.0
[processes.ingest.settings.sim.sensors.depth_camera]
rate_hz = 0.0
"#
    );
    let s = orig.run_to_end("end = \"end_of_stream\"\nend_of_stream_from = [\"rec\"]\nduration_s = 200", &procs, LONG);
    use crate::summary_schema::part;
    let recorder: recorder_stage::summary::RecorderPart = part(&s);
    let ingest: ingest_stage::summary::IngestPart = part(&s);
    let buoy: buoy_ekf_stage::summary::BuoyEkfPart = part(&s);
    let rec = &recorder.recorder;
    eprintln!("original run: recorder {:#}\ningest {:#}", s["recorder"], s["ingest"]);
    let file = orig.out_dir().join("recording.mcap");
    assert_eq!(rec.file, file.to_str().unwrap(), "{rec:?}");
    assert_eq!(rec.ended_by, "end of stream", "{rec:?}");
    // Every message the stages sent is in the file, none missed.
    let m = &ingest.ingest.messages;
    for (service, published) in [
        ("pipeline/sensors/odometry", m.odometry),
        ("pipeline/sensors/stereo", m.stereo),
        ("pipeline/sensors/buoy_ranges", m.buoy_ranges),
        ("pipeline/sensors/depth", m.depth),
    ] {
        assert!(published > 0, "{service}");
        assert_eq!(rec.messages.get(service), Some(&published), "{service}: {rec:?}");
    }
    let fixes_sent = buoy.buoy_ekf.fixes;
    assert!(fixes_sent > 10, "{:#}", s["buoy_ekf"]);
    assert_eq!(rec.messages.get("pipeline/buoy/fix"), Some(&fixes_sent), "{rec:?}");
    assert!(
        rec.messages.get("pipeline/control/end_of_stream").is_some_and(|&n| n >= 4),
        "ingest, buoy, slam, sync: {rec:?}"
    );
    // Sensors (back-pressure), estimates (256-sample queues) and control lose nothing; the
    // particle sets and diagnostics are lossy streams (newest wins) and may drop under load.
    for (service, &missed) in &rec.missed {
        if !["pipeline/slam/particles", "pipeline/slam/diagnostics"].contains(&service.as_str()) {
            assert_eq!(missed, 0, "{service}: {rec:?}");
        }
    }
    // Readable by the mcap crate and by Python's reader, with the same counts.
    let (counts, orig_fixes) = read_mcap(&file);
    for (service, n) in &rec.messages {
        assert_eq!(counts.get(service), Some(n), "{service}: {counts:?}");
    }
    assert_eq!(counts.get("pipeline/buoy/fix/json").copied(), Some(fixes_sent), "JSON mirror: {counts:?}");
    assert_eq!(read_mcap_python(&file), counts, "Python's reader and the mcap crate disagree");
    assert_eq!(rec.file_bytes, std::fs::metadata(&file).unwrap().len());
    let orig_tum = std::fs::read(orig.out_dir().join("buoy_ekf.tum")).expect("original buoy_ekf.tum");
    assert!(orig_tum.len() > 1000);
    let orig_slam = std::fs::read(orig.out_dir().join("slam_local.tum")).expect("original slam_local.tum");
    assert!(orig_slam.len() > 1000);

    // Rerun the buoy EKF alone from the recording, twice.
    let mut tums = vec![];
    for tag in ["replaya", "replayb"] {
        let topics = ["pipeline/sensors/odometry", "pipeline/sensors/buoy_ranges", "pipeline/sensors/depth"];
        let (run, s) = replay(tag, &file, (BUOY, "buoy", "pipeline/buoy/fix"), &topics);
        let replayer: recorder_stage::summary::ReplayerPart = part(&s);
        let r = &replayer.replayer;
        eprintln!("{tag}: replayer {:#}", s["replayer"]);
        assert!(r.complete, "{r:?}");
        for service in ["pipeline/sensors/odometry", "pipeline/sensors/buoy_ranges", "pipeline/sensors/depth"] {
            assert_eq!(r.sent.get(service), rec.messages.get(service), "{service}: {r:?}");
        }
        assert!(r.undelivered.is_empty(), "{r:?}");
        // Only ingest's, slam's and sync's ends of stream are replayed: buoy and rec are part of
        // the replay config.
        assert_eq!(r.sent.get("pipeline/control/end_of_stream"), Some(&3), "{r:?}");
        let replayed_buoy: buoy_ekf_stage::summary::BuoyEkfPart = part(&s);
        assert_eq!(replayed_buoy.buoy_ekf.fixes, fixes_sent, "{:#}", s["buoy_ekf"]);
        let (_, fixes) = read_mcap(&run.out_dir().join("recording.mcap"));
        assert_eq!(fixes.len(), orig_fixes.len());
        assert!(fixes == orig_fixes, "{tag}: the replayed buoy fixes differ from the original run's");
        tums.push(std::fs::read(run.out_dir().join("buoy_ekf.tum")).expect("buoy_ekf.tum"));
    }
    assert!(tums[0] == tums[1], "two replays with the same config gave different buoy_ekf.tum");
    assert!(tums[0] == orig_tum, "the replay's buoy_ekf.tum differs from the original run's");

    // FastSLAM rerun alone from the recorded odometry and stereo (no fusion commands in this run),
    // twice: the same trajectory as the original run, to the byte.
    let mut slams = vec![];
    for tag in ["replayc", "replayd"] {
        let stage = SLAM.replace("after = [\"rec\"]", "");
        let topics = ["pipeline/sensors/odometry", "pipeline/sensors/stereo"];
        let (run, s) = replay(tag, &file, (&stage, "slam", "pipeline/slam/pose"), &topics);
        let replayer: recorder_stage::summary::ReplayerPart = part(&s);
        let r = &replayer.replayer;
        assert!(r.complete, "{r:?}");
        assert_eq!(r.sent.get("pipeline/sensors/stereo"), rec.messages.get("pipeline/sensors/stereo"), "{r:?}");
        assert!(r.undelivered.is_empty(), "{r:?}");
        slams.push(std::fs::read(run.out_dir().join("slam_local.tum")).expect("slam_local.tum"));
    }
    assert!(slams[0] == slams[1], "two replays with the same config gave different slam_local.tum");
    assert!(slams[0] == orig_slam, "the replay's slam_local.tum differs from the original run's");

    // The synchronizer rerun alone from the recorded SLAM poses and buoy fixes, twice: the same
    // pairs, and the original run's.
    // The pairs proper: a predicted pair (sent when a pose had to wait for its fix) depends on
    // when the fix arrived, which a replay as fast as possible does not reproduce.
    let proper = |v: Fixes| -> Fixes {
        let flags = |p: &[u8]| u32::from_le_bytes(p[456..460].try_into().unwrap());
        v.into_iter().filter(|(_, p)| flags(p) & shared_types::SYNC_PREDICTED == 0).collect()
    };
    let orig_pairs = proper(payloads(&file, "pipeline/sync/pair"));
    assert!(orig_pairs.len() > 100, "{} pairs recorded", orig_pairs.len());
    let mut pairs = vec![];
    for tag in ["replaye", "replayf"] {
        let stage = SYNC.replace("after = [\"rec\"]", "");
        let topics = ["pipeline/slam/pose", "pipeline/buoy/fix"];
        let (run, s) = replay(tag, &file, (&stage, "sync", "pipeline/sync/pair"), &topics);
        let replayer: recorder_stage::summary::ReplayerPart = part(&s);
        assert!(replayer.replayer.complete, "{:?}", replayer.replayer);
        assert!(replayer.replayer.undelivered.is_empty(), "{:?}", replayer.replayer);
        pairs.push(proper(payloads(&run.out_dir().join("recording.mcap"), "pipeline/sync/pair")));
    }
    let differ = |a: &Fixes, b: &Fixes| (0..a.len().min(b.len())).filter(|&i| a[i] != b[i]).count();
    assert_eq!(pairs[0].len(), orig_pairs.len(), "one pair per SLAM pose");
    assert_eq!(differ(&pairs[0], &pairs[1]), 0, "two replays gave different synced pairs");
    assert_eq!(pairs[1].len(), orig_pairs.len());
    assert_eq!(differ(&pairs[0], &orig_pairs), 0, "the replay's synced pairs differ from the original run's");
}

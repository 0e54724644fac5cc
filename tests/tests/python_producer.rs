//! The Python external producer (`examples/python/producer.py`, iceoryx2 0.10 from PyPI with
//! ctypes wire types) under the supervisor: the Rust test consumer verifies every point of its
//! clouds bit for bit, its end of stream ends the run, and nothing is left in shared memory.
//! Needs `python3` with `iceoryx2==0.10.0` (scripts/test.sh installs it).

use std::path::PathBuf;
use std::time::Duration;

use pipeline_tests::TestRun;

const POINTS: u64 = 5000;
const FRAMES: u64 = 20;

fn producer_script() -> PathBuf {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../examples/python/producer.py");
    let path = path.canonicalize().unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(path.is_file(), "{} is missing", path.display());
    path
}

fn python_has_iceoryx2() {
    let out = std::process::Command::new("python3")
        .args(["-c", "import iceoryx2"])
        .output()
        .expect("python3 is needed for this test");
    assert!(
        out.status.success(),
        "python3 cannot import iceoryx2 (run `python3 -m pip install iceoryx2==0.10.0`, as scripts/test.sh does): {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn python_producer_clouds_verify_bit_exact_and_its_end_of_stream_ends_the_run() {
    python_has_iceoryx2();
    let mut run = TestRun::new("python");
    let script = producer_script();
    let procs = format!(
        r#"
[processes.consumer]
kind = "test_consumer"
[processes.consumer.settings]
expect_points = {POINTS}

[processes.camera]
kind = "external"
binary = "python3"
args = ["{script}", "--points", "{POINTS}", "--frames", "{FRAMES}", "--rate-hz", "50"]
after = ["consumer"]
heartbeat = false
"#,
        script = script.display()
    );
    let cfg = run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"consumer\"]\nduration_s = 60", &procs);
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(Duration::from_secs(60)).expect("run ends on end of stream");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    let s = run.summary();
    let sup: supervisor::report::SupervisorPart = crate::summary_schema::part(&s);
    assert_eq!(sup.run.end_reason, supervisor::outcome::EndReason::EndOfStream, "{s:#}");
    let c = crate::summary_schema::part::<testkit::ConsumerPart>(&s).test_consumer;
    assert_eq!(c.frames_ok, FRAMES, "every cloud verifies: {c:?}\nlog:\n{}", run.log());
    assert_eq!(c.frames_bad, 0, "{c:?}");
    assert_eq!(c.frames_missed, 0, "{c:?}");
    assert_eq!(c.points_checked, POINTS * FRAMES, "{c:?}");
    assert_eq!(c.end_of_stream_seen, 1, "the producer's end of stream reached the consumer: {c:?}");
    let hop = &sup.latency_ms.hops["pipeline/sensors/cloud -> consumer"];
    assert!(hop.count >= FRAMES, "hop latency recorded for every cloud: {s:#}");
    assert!(hop.p50 >= 0.0 && hop.p50 <= hop.max, "{hop:?}");
    let camera = &sup.processes["camera"];
    assert_eq!(camera.restarts, 0, "{s:#}");
    assert_eq!(camera.last_exit.as_ref().and_then(|e| e.code), Some(0), "the producer exits 0 on SIGTERM: {s:#}");
    assert_eq!(run.leftovers(), Vec::<PathBuf>::new(), "iceoryx2 files left behind");
}

//! Every wire type round-trips through iceoryx2 between two processes, byte for byte.

use std::process::Command;
use std::time::{Duration, Instant};

use pipeline_tests::{TestRun, bin, wait_for_line};

#[test]
fn every_wire_type_round_trips_between_two_processes() {
    let mut run = TestRun::new("wire");
    let args = |role: &str| {
        let mut c = Command::new(bin("wire_roundtrip"));
        c.args(["--role", role, "--prefix", &run.scope.prefix, "--root"])
            .arg(&run.scope.root)
            .args(["--timeout-s", "20"]);
        c
    };
    let mut sub_cmd = args("sub");
    let mut pub_cmd = args("pub");
    let sub = run.spawn(&mut sub_cmd);
    wait_for_line(sub, "READY", Duration::from_secs(20));
    let sub_pid = sub.id();
    run.spawn(&mut pub_cmd);
    let sub = run.others_mut(sub_pid);
    let end = Instant::now() + Duration::from_secs(30);
    let status = loop {
        if let Some(s) = sub.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < end, "subscriber did not finish");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(status.success(), "a wire type did not arrive byte-identical (see stderr)");
}

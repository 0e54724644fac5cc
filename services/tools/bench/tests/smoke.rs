//! Smoke test of `ingest_bench` through the real binary with a tiny configuration: every transport
//! produces a table row and a CSV row with latency samples, and nothing is left in /dev/shm.
//! No timing is asserted (the machine is shared and noisy; speed is read from the table).

use std::process::Command;

#[test]
fn tiny_run_reports_every_transport_with_latency_samples_and_leaves_no_shared_memory() {
    let dir = tempfile::tempdir().expect("temp dir");
    let csv = dir.path().join("bench.csv");
    let child = Command::new(env!("CARGO_BIN_EXE_ingest_bench"))
        .args(["--points", "1000", "--frames", "20", "--warmup", "5", "--rate-hz", "200"])
        .args(["--transports", "iox,socket-bincode,socket-raw"])
        .arg("--csv")
        .arg(&csv)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start ingest_bench");
    let pid = child.id();
    let out = child.wait_with_output().expect("wait for ingest_bench");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "ingest_bench failed: {}\nstdout:\n{stdout}\nstderr:\n{stderr}", out.status);

    let text = std::fs::read_to_string(&csv).expect("the CSV was written");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("CSV header").split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap_or_else(|| panic!("no column {name}"));
    for name in ["transport", "points", "p50_us", "p99_us", "cpu_p50_us"] {
        col(name);
    }
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    for transport in ["gen-only", "iox", "socket-bincode", "socket-raw"] {
        let row = rows
            .iter()
            .find(|r| r[col("transport")] == transport)
            .unwrap_or_else(|| panic!("no CSV row for {transport}:\n{text}"));
        assert_eq!(row[col("points")], "1000", "{transport}");
        let cpu: f64 = row[col("cpu_p50_us")].parse().unwrap_or_else(|_| panic!("{transport} cpu:\n{text}"));
        assert!(cpu > 0.0, "{transport}: producer CPU {cpu}");
        assert!(stdout.lines().any(|l| l.starts_with(transport)), "no table row for {transport}:\n{stdout}");
        if transport == "gen-only" {
            continue;
        }
        let count: u64 = row[col("count")].parse().expect("count");
        assert!(count > 0, "{transport}: no latency samples:\n{text}");
        let p50: f64 = row[col("p50_us")].parse().unwrap_or_else(|_| panic!("{transport} p50:\n{text}"));
        assert!(p50 > 0.0, "{transport}: p50 {p50}");
    }
    assert!(stdout.contains("socket-bincode/iox: hop latency p50"), "no ratio line:\n{stdout}");

    let prefix = format!("bench{pid}_");
    let left: Vec<_> = std::fs::read_dir("/dev/shm")
        .map(|rd| rd.filter_map(|e| e.ok()).filter(|e| e.file_name().to_string_lossy().starts_with(&prefix)).collect())
        .unwrap_or_default();
    assert!(left.is_empty(), "left in /dev/shm: {:?}", left.iter().map(|e| e.path()).collect::<Vec<_>>());
}

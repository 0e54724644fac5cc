//! Smoke test of `pipeline_bench latency` through the real binary with a tiny configuration: every
//! transport and chain produces per-hop and end-to-end CSV rows with samples, the PNG is written,
//! nothing is left in /dev/shm, and a bad option is refused with a message naming it. No timing is
//! asserted (the machine is shared and noisy; speed is read from the table).

use std::process::{Command, Stdio};

fn shm_left(prefix: &str) -> Vec<String> {
    std::fs::read_dir("/dev/shm")
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with(prefix))
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn tiny_sweep_reports_every_hop_of_every_transport_and_chain() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (csv, png) = (dir.path().join("lat.csv"), dir.path().join("lat.png"));
    let child = Command::new(env!("CARGO_BIN_EXE_pipeline_bench"))
        .args(["latency", "--sizes", "64,64KiB", "--chains", "1,2", "--samples", "20", "--warmup", "5"])
        .args(["--rate-hz", "500", "--touch"])
        .arg("--csv")
        .arg(&csv)
        .arg("--png")
        .arg(&png)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start pipeline_bench");
    let pid = child.id();
    let out = child.wait_with_output().expect("wait for pipeline_bench");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "pipeline_bench failed: {}\nstdout:\n{stdout}\nstderr:\n{stderr}", out.status);

    let text = std::fs::read_to_string(&csv).expect("the CSV was written");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("CSV header").split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap_or_else(|| panic!("no column {name}"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    for transport in ["iox", "iox-bare", "socket-raw", "socket-bincode"] {
        for size in ["64", "65536"] {
            for chain in [1usize, 2] {
                let mine: Vec<&Vec<&str>> = rows
                    .iter()
                    .filter(|r| r[col("transport")] == transport && r[col("size_bytes")] == size)
                    .filter(|r| r[col("chain")] == chain.to_string())
                    .collect();
                let hops: Vec<&str> = mine.iter().map(|r| r[col("hop")]).collect();
                let want: Vec<String> = (1..=chain + 1).map(|h| h.to_string()).chain(["e2e".to_string()]).collect();
                assert_eq!(hops, want, "{transport} {size} chain {chain}:\n{text}");
                for r in &mine {
                    let count: u64 = r[col("count")].parse().expect("count");
                    assert_eq!(count, 20, "{transport} {size} chain {chain} hop {}:\n{text}", r[col("hop")]);
                    let p50: f64 = r[col("p50_us")].parse().expect("p50");
                    let p99: f64 = r[col("p99_us")].parse().expect("p99");
                    assert!(p50 > 0.0 && p99 >= p50, "{transport}: p50 {p50} p99 {p99}");
                    assert_eq!((r[col("lost")], r[col("bad")]), ("0", "0"), "{transport}:\n{text}");
                }
                // End to end is at least the slowest hop's median.
                let e2e: f64 = mine.last().expect("e2e")[col("p50_us")].parse().expect("p50");
                assert!(e2e > 0.0);
            }
        }
    }
    assert!(stdout.contains("end-to-end p50 / iox: iox-bare"), "no ratio line:\n{stdout}");
    let png_bytes = std::fs::read(&png).expect("the PNG was written");
    assert!(png_bytes.starts_with(b"\x89PNG\r\n\x1a\n") && png_bytes.len() > 10_000, "not a plot PNG");
    let left = shm_left(&format!("lat{pid}_"));
    assert!(left.is_empty(), "left in /dev/shm: {left:?}");
}

#[test]
fn a_bad_option_is_refused_with_its_name() {
    let out = Command::new(env!("CARGO_BIN_EXE_pipeline_bench"))
        .args(["latency", "--sizes", "8"])
        .output()
        .expect("run pipeline_bench");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("--sizes") && stderr.contains("8 bytes"), "{stderr}");
    let out = Command::new(env!("CARGO_BIN_EXE_pipeline_bench"))
        .args(["latency", "--chains", "0"])
        .output()
        .expect("run pipeline_bench");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--chains"));
}

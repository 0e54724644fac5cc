//! Throughput of the point-cloud readers on 300k-point files (the size of one simulated cloud).
//! The time limit is asserted in optimised builds only; debug builds just report the times.

use std::fmt::Write as _;
use std::time::{Duration, Instant};

use datasets::{PlyFormat, read_ply, read_scan_file, write_ply};

const N: usize = 300_000;

fn cloud() -> Vec<[f32; 3]> {
    (0..N)
        .map(|i| {
            let t = i as f32 * 1e-3;
            [10.0 * t.cos(), -5.0 + 1e-4 * i as f32, 3.0 * t.sin()]
        })
        .collect()
}

fn check(what: &str, elapsed: Duration) {
    println!("{what}: {N} points in {elapsed:?}");
    if !cfg!(debug_assertions) {
        assert!(elapsed < Duration::from_secs(1), "{what} took {elapsed:?}");
    }
}

#[test]
fn scan_dat_and_ply_of_300k_points() {
    let dir = tempfile::tempdir().unwrap();
    let pts = cloud();

    let mut text = String::with_capacity(N * 30);
    for p in &pts {
        writeln!(text, "{} {} {}", p[0], p[1], p[2]).unwrap();
    }
    let scan_path = dir.path().join("scan.dat");
    std::fs::write(&scan_path, text).unwrap();
    let start = Instant::now();
    let scans = read_scan_file(&scan_path).unwrap();
    check("scan.dat", start.elapsed());
    assert_eq!(scans[0].points, pts);

    for format in [PlyFormat::BinaryLittleEndian, PlyFormat::Ascii] {
        let path = dir.path().join(format!("{format:?}.ply"));
        write_ply(&path, &pts, format).unwrap();
        let start = Instant::now();
        let back = read_ply(&path).unwrap();
        check(&format!("PLY {format:?}"), start.elapsed());
        assert_eq!(back, pts);
    }
}

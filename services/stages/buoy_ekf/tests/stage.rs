//! The buoy EKF stage fed through `pipeline_runtime::testing::StageHarness` (no iceoryx2): a
//! filter that cannot initialise says why, in the log and in its summary part; a restarted one
//! goes on from the killed one's state.

use std::path::Path;
use std::time::Duration;

use buoy_ekf_stage::stage::BuoyEkfStage;
use pipeline_runtime::testing::StageHarness;
use shared_types::services::{BUOY_FIX, BUOY_RANGES, DEPTH, ODOMETRY};
use shared_types::{BuoyFix, BuoyRange, DepthReading, MsgHeader, OdometryInput};

#[test]
fn ranges_to_too_few_buoys_leave_the_filter_waiting_and_the_summary_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/default.toml");
    let mut h = StageHarness::<BuoyEkfStage>::from_config_file(&config, "buoy", dir.path()).expect("opens");
    // Two of the five buoys answer; the default needs four distinct ones to start.
    for k in 1..=6u64 {
        let header = MsgHeader { stamp_ns: k * 1_000_000_000, ..Default::default() };
        let ranges = [
            BuoyRange { buoy_id: 0, _reserved: 0, range_m: 20.0 + k as f64, sigma_m: 0.3 },
            BuoyRange { buoy_id: 1, _reserved: 0, range_m: 120.0 - k as f64, sigma_m: 0.3 },
        ];
        h.feed_slice::<BuoyRange, MsgHeader>(BUOY_RANGES, header, &ranges).unwrap();
        h.wake().unwrap();
    }
    h.end_upstream("ingest").unwrap();
    let part = h.run_to_end(Duration::from_secs(5)).unwrap();
    let b = &part["buoy_ekf"];
    assert_eq!(b["fixes"], 0, "{b:#}");
    assert_eq!(b["initialised"], false, "{b:#}");
    assert!(b["ranges_waiting_for_initialisation"].as_u64().unwrap() >= 6, "{b:#}");
    let why = b["last_waiting_reason"].as_str().unwrap_or_default();
    assert!(why.contains("2 distinct buoys") && why.contains("4 needed"), "names the reason: {why}");
}

#[test]
fn only_the_end_of_a_process_that_feeds_it_ends_the_stage() {
    let dir = tempfile::tempdir().unwrap();
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/default.toml");
    let mut h = StageHarness::<BuoyEkfStage>::from_config_file(&config, "buoy", dir.path()).expect("opens");
    let header = MsgHeader { stamp_ns: 1_000_000_000, ..Default::default() };
    let ranges = [BuoyRange { buoy_id: 0, _reserved: 0, range_m: 20.0, sigma_m: 0.3 }];
    h.feed_slice::<BuoyRange, MsgHeader>(BUOY_RANGES, header, &ranges).unwrap();
    h.wake().unwrap();
    // A recorder (publishes nothing) and the mapper (none of the EKF's inputs) end, or fail:
    // the EKF goes on.
    h.end_of_process_publishing("rec", &[]).unwrap();
    h.end_of_process_publishing("map", &[shared_types::services::MAP_VOXELS]).unwrap();
    for _ in 0..3 {
        assert!(h.wake().unwrap().is_some(), "the buoy EKF ended on the end of a process that fed it nothing");
    }
    // The source of its ranges ends: so does the EKF.
    h.end_of_process_publishing("ingest", &[BUOY_RANGES, shared_types::services::DEPTH]).unwrap();
    let part = h.run_to_end(Duration::from_secs(5)).unwrap();
    assert!(part["buoy_ekf"].is_object(), "{part:#}");
}

/// One second of a vehicle circling at 10 m depth in config/default.toml's buoy field: odometry
/// at 10 Hz, then a depth reading and ranges to the five buoys (with a deterministic error of up
/// to 0.2 m) at the whole second `s`.
fn feed_second(h: &StageHarness<BuoyEkfStage>, s: u64) {
    let buoys = [[-10.0, -10.0], [130.0, -10.0], [130.0, 90.0], [-10.0, 90.0], [60.0, 100.0]];
    let (v, r) = (1.0, 20.0);
    let position = |t: f64| [60.0 + r * (v * t / r).cos(), 40.0 + r * (v * t / r).sin(), -10.0];
    let mut input_covariance = [0.0; 16];
    input_covariance[0] = 0.01;
    input_covariance[5] = 1e-6;
    input_covariance[10] = 1e-6;
    input_covariance[15] = 1e-4;
    for k in 1..=10u64 {
        let stamp_ns = (s - 1) * 1_000_000_000 + k * 100_000_000;
        let u = OdometryInput { v_mps: v, delta_theta_rad: [0.0, 0.0, v / r * 0.1], dt_s: 0.1, input_covariance };
        h.feed::<OdometryInput, MsgHeader>(ODOMETRY, MsgHeader { stamp_ns, ..Default::default() }, u).unwrap();
    }
    let header = MsgHeader { stamp_ns: s * 1_000_000_000, ..Default::default() };
    h.feed::<DepthReading, MsgHeader>(DEPTH, header, DepthReading { depth_m: 10.0, sigma_m: 0.05 }).unwrap();
    let p = position(s as f64);
    let ranges: Vec<BuoyRange> = buoys
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let d = ((p[0] - b[0]).powi(2) + (p[1] - b[1]).powi(2) + p[2] * p[2]).sqrt();
            let error = 0.2 * ((s * 7 + i as u64 * 13) as f64).sin();
            BuoyRange { buoy_id: i as u32, _reserved: 0, range_m: d + error, sigma_m: 0.3 }
        })
        .collect();
    h.feed_slice::<BuoyRange, MsgHeader>(BUOY_RANGES, header, &ranges).unwrap();
}

#[test]
fn a_restarted_filter_goes_on_from_the_killed_ones_state() {
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/default.toml");
    let run = |kill_after: Option<u64>| {
        let dir = tempfile::tempdir().unwrap();
        let mut h = StageHarness::<BuoyEkfStage>::from_config_file(&config, "buoy", dir.path()).expect("opens");
        let mut fixes = vec![];
        for s in 1..=60u64 {
            feed_second(&h, s);
            h.wake().unwrap();
            fixes.extend(h.take::<BuoyFix, MsgHeader>(BUOY_FIX).unwrap());
            if kill_after == Some(s) {
                h = h.restart().unwrap();
            }
        }
        h.end_upstream("ingest").unwrap();
        let part = h.run_to_end(Duration::from_secs(5)).unwrap();
        fixes.extend(h.take::<BuoyFix, MsgHeader>(BUOY_FIX).unwrap());
        let samples = part["buoy_ekf"]["trajectory_samples"].as_u64().unwrap();
        (fixes, samples)
    };
    let (whole, whole_samples) = run(None);
    let (restarted, restarted_samples) = run(Some(30));
    let after: Vec<_> = whole.iter().filter(|(h, _)| h.stamp_ns > 30_000_000_000).collect();
    assert!(after.len() >= 29, "{} fixes after 30 s", after.len());
    let again: Vec<_> = restarted.iter().filter(|(h, _)| h.stamp_ns > 30_000_000_000).collect();
    // Every fix after the restart is the one the uninterrupted filter published (a filter that
    // started over would wait for a trilateration, then publish a fix metres off).
    assert_eq!(again.len(), after.len());
    for ((ha, a), (hb, b)) in after.iter().zip(&again) {
        assert_eq!(ha.stamp_ns, hb.stamp_ns);
        assert_eq!(a.position_m, b.position_m, "fix at {} ns", ha.stamp_ns);
        assert_eq!(a.covariance_m2, b.covariance_m2, "fix at {} ns", ha.stamp_ns);
    }
    // The trajectory covers the whole run: the killed instance's part was replayed.
    assert_eq!(restarted_samples, whole_samples);
}

#[test]
fn what_sat_in_the_killed_instances_queues_is_counted_as_lost_by_the_restarted_one() {
    use pipeline_runtime::stats::LOST_IN_RESTART;
    let dir = tempfile::tempdir().unwrap();
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/default.toml");
    let mut h = StageHarness::<BuoyEkfStage>::from_config_file(&config, "buoy", dir.path()).expect("opens");
    for s in 1..=10u64 {
        feed_second(&h, s);
        h.wake().unwrap();
    }
    // Two seconds of inputs wait in its queues when it is killed: 20 odometry messages, 2
    // depth readings and 2 ranges messages lost.
    feed_second(&h, 11);
    feed_second(&h, 12);
    let mut h = h.restart().unwrap();
    for s in 13..=20u64 {
        feed_second(&h, s);
        h.wake().unwrap();
    }
    let lost = |service: &str| {
        let report = h.runtime().stats_report();
        let port = report.ports.iter().find(|p| p.input && p.service == service).expect("the input");
        port.dropped_by.iter().find(|(r, _)| r == LOST_IN_RESTART).map_or(0, |(_, n)| *n)
    };
    assert_eq!((lost(ODOMETRY), lost(DEPTH), lost(BUOY_RANGES)), (20, 2, 2));
    // A second restart with nothing queued loses nothing more (the restarted instance's own
    // inputs are where the next one resumes).
    let mut h = h.restart().unwrap();
    feed_second(&h, 21);
    h.wake().unwrap();
    let report = h.runtime().stats_report();
    assert!(report.ports.iter().all(|p| p.dropped_by.is_empty()), "{report:?}");
    h.end_upstream("ingest").unwrap();
    h.run_to_end(Duration::from_secs(5)).unwrap();
}

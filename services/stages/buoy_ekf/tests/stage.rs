//! The buoy EKF stage fed through `pipeline_runtime::testing::StageHarness` (no iceoryx2): a
//! filter that cannot initialise says why, in the log and in its summary part.

use std::path::Path;
use std::time::Duration;

use buoy_ekf_stage::stage::BuoyEkfStage;
use pipeline_runtime::testing::StageHarness;
use shared_types::services::BUOY_RANGES;
use shared_types::{BuoyRange, MsgHeader};

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

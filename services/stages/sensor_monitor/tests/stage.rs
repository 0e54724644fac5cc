//! The sensor monitor stage fed through `pipeline_runtime::testing::StageHarness` (no
//! iceoryx2): valid messages are accepted, bad ones rejected by reason, a stamp going back is
//! caught per publisher, and the first upstream end of stream ends it with its own.

use std::path::Path;
use std::time::Duration;

use pipeline_runtime::testing::StageHarness;
use sensor_monitor_stage::stage::SensorMonitorStage;
use shared_types::services::{BUOY_RANGES, ODOMETRY};
use shared_types::{BuoyRange, MsgHeader, OdometryInput};

const CONFIG: &str =
    "[processes.monitor]\nkind = \"sensor_monitor\"\n[processes.monitor.settings]\nknown_buoy_ids = [0, 1]\n";

fn at(t_s: f64) -> MsgHeader {
    MsgHeader { stamp_ns: (t_s * 1e9) as u64, ..Default::default() }
}

fn odo(v_mps: f64) -> OdometryInput {
    let mut c = [0.0; 16];
    c[0] = 0.01;
    c[5] = 1e-6;
    c[10] = 1e-6;
    c[15] = 1e-6;
    OdometryInput { v_mps, delta_theta_rad: [0.0; 3], dt_s: 0.1, input_covariance: c }
}

#[test]
fn counts_accepted_and_rejected_messages_by_reason_and_ends_after_the_first_upstream() {
    let dir = tempfile::tempdir().unwrap();
    let mut h =
        StageHarness::<SensorMonitorStage>::from_config_str(CONFIG, Path::new("monitor.toml"), "monitor", dir.path())
            .unwrap();
    for k in 1..=5 {
        h.feed(ODOMETRY, at(k as f64 * 0.1), odo(1.0)).unwrap();
    }
    h.feed(ODOMETRY, at(0.2), odo(1.0)).unwrap(); // stamp going back
    h.feed(ODOMETRY, at(0.7), odo(f64::NAN)).unwrap();
    let range = |id: u32| BuoyRange { buoy_id: id, range_m: 10.0, sigma_m: 0.5, ..Default::default() };
    h.feed_slice(BUOY_RANGES, at(0.5), &[range(0), range(1)]).unwrap();
    h.feed_slice(BUOY_RANGES, at(0.6), &[range(7)]).unwrap();
    h.wake().unwrap();
    assert!(h.summary().is_none(), "no upstream has ended yet");
    h.end_upstream("ingest").unwrap();
    let part = h.run_to_end(Duration::from_secs(5)).unwrap();
    let m = &part["sensor_monitor"];
    assert_eq!(m[ODOMETRY]["accepted"], 5, "{part}");
    assert_eq!(m[ODOMETRY]["rejected"]["stamp_not_increasing"], 1, "{part}");
    assert_eq!(m[ODOMETRY]["rejected"]["non_finite"], 1, "{part}");
    assert_eq!(m[BUOY_RANGES]["accepted"], 1, "{part}");
    assert_eq!(m[BUOY_RANGES]["rejected"]["unknown_buoy"], 1, "{part}");
    let eos = h.end_of_stream().unwrap().expect("it forwards the end of stream");
    assert_eq!(eos.messages_sent, 6, "accepted messages");
}

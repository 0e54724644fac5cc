//! The buoy EKF on the real indoor UWB data set (libRSF "Labyrinth", Pfeifer & Protzel, TU
//! Chemnitz, CC BY-SA 4.0; read from `../shared/data/indoor_uwb`, never copied here) with the
//! defaults `plaza2_eval` uses: the ATE stays within 0.08 m (docs/buoy_ekf.md: 0.078 m) and well
//! under dead reckoning's. The evaluation is `uwb_eval`'s (`cargo run --release -p buoy --example
//! uwb_eval`), included here so that the number the docs give is the number tested.

#[path = "../examples/uwb_eval.rs"]
#[allow(dead_code)]
mod uwb_eval;

#[test]
fn the_indoor_uwb_data_set_is_tracked_within_8_cm() {
    let o = uwb_eval::Options::shared();
    if !datasets::shared_data_present(
        o.dir.join("Indoor_UWB_Input.txt"),
        "the_indoor_uwb_data_set_is_tracked_within_8_cm",
    ) || !datasets::shared_data_present(
        o.dir.join("Indoor_UWB_GT.txt"),
        "the_indoor_uwb_data_set_is_tracked_within_8_cm",
    ) {
        return;
    }
    let e = uwb_eval::evaluate(&o).expect("the data set replays");
    let (ate, dead_reckoning) = e.ate_m();
    eprintln!("indoor UWB: ATE {ate:.4} m, dead reckoning {dead_reckoning:.4} m, counts {:?}", e.counts);
    assert!(ate <= 0.08, "buoy EKF ATE {ate:.4} m over 0.08 m on the indoor UWB data set");
    assert!(ate < 0.5 * dead_reckoning, "ATE {ate:.4} m against dead reckoning's {dead_reckoning:.4} m");
    assert_eq!(e.counts.3, 4, "the data set's four beacons");
}

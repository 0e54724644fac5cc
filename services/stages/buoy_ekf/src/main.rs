//! `buoy_ekf`: subscribes odometry, buoy ranges and pressure depth, runs the buoy EKF in stamp
//! order and publishes a `BuoyFix` per ranges message on `pipeline/buoy/fix`; at the end of the
//! stream writes `buoy_ekf.tum`, `dead_reckoning.tum` and, with a ground truth, `ate_m.buoy_ekf`
//! and `ate_m.dead_reckoning` into summary.json. See the library docs.

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<buoy_ekf_stage::stage::BuoyEkfStage>()
}

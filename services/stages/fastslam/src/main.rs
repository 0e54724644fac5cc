//! `fastslam`: subscribes odometry and stereo, runs the filter in stamp order, publishes the
//! pose, the particle set, the best particle's landmarks and per-frame diagnostics; at the end of
//! the stream writes the trajectory and its accuracy. See the library docs.

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<fastslam_stage::stage::FastSlamStage>()
}

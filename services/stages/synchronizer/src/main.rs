//! `synchronizer`: subscribes the SLAM pose and the buoy fixes and publishes, for each SLAM pose,
//! a `SyncedPair` on `pipeline/sync/pair` with the buoy position interpolated to the pose's stamp
//! (see the library docs). At the end it writes its counts and the added latency into
//! summary.json.

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<synchronizer_stage::stage::SynchronizerStage>()
}

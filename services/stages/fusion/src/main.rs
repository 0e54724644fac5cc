//! `fusion`: subscribes the synced pairs, the buoy fixes and the SLAM landmark maps; publishes
//! the fused global pose per SLAM pose on `pipeline/fusion/pose`, asks the SLAM process for a new
//! local map when camera and buoy stop overlapping, and at the end publishes the global map on
//! `pipeline/fusion/map` and writes the globally consistent path, the map, the transforms, the
//! accuracy and a plot. See the library docs.

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<fusion_stage::stage::FusionStage>()
}

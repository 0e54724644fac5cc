//! `grid_slam`: 2-D grid SLAM on `pipeline/sensors/laser` and `pipeline/sensors/planar_odometry`
//! (see the library docs).

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<grid_slam_stage::stage::GridSlamStage>()
}

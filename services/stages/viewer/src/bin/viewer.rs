//! `viewer`: a live view of the run in Foxglove (the Foxglove SDK's WebSocket server, Foxglove's
//! own schemas): trajectories, the current cloud, landmarks, the octree, the 2-D grid and each
//! process's state. It never holds the pipeline back and counts what it skips. The stage is
//! [`viewer_stage::stage::ViewerStage`].

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<viewer_stage::stage::ViewerStage>()
}

//! `octree_mapper`: subscribes the point clouds and the poses (fused by default), inserts each
//! cloud at the pose interpolated to its stamp into an OctoMap-compatible occupancy octree,
//! publishes `MapStats` and the occupied voxels at configured rates, writes `map.bt` at the end
//! and on a checkpoint command, and at the end discovers navigable space and obstacles
//! (`navigable.ply`, `obstacles.ply`, counts in summary.json). See the library docs.

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<octree_mapper_stage::stage::OctreeMapperStage>()
}

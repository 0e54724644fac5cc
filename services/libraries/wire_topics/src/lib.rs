//! The services that can be recorded, replayed and bridged, with their wire types: one
//! [`Topic`] per service of the contract (`shared_types::services::SERVICES`) except the
//! per-process statistics. The runtime's [`Topic`] is generic over the wire types; this table
//! names the concrete ones, so that the runtime holds no domain types.

pub use pipeline_runtime::topics::Topic;
use shared_types::services;
use shared_types::*;

/// Every recordable service. Heartbeats are recordable on request but not by default (they say
/// nothing about the data); the per-process statistics (`pipeline/stats/<process>`) are not
/// recordable (internal bincode).
pub const TOPICS: &[Topic] = &[
    Topic::fixed::<OdometryInput, MsgHeader>(services::ODOMETRY, true),
    Topic::slice::<StereoObservation, MsgHeader>(services::STEREO, true),
    Topic::slice::<BuoyRange, MsgHeader>(services::BUOY_RANGES, true),
    Topic::fixed::<DepthReading, MsgHeader>(services::DEPTH, true),
    Topic::fixed::<HeadingReading, MsgHeader>(services::HEADING, true),
    Topic::slice::<CloudPoint, CloudHeader>(services::CLOUD, true),
    Topic::fixed::<PoseEstimate, MsgHeader>(services::SLAM_POSE, true),
    Topic::slice::<Particle, ParticleSetHeader>(services::SLAM_PARTICLES, true),
    Topic::slice::<Landmark, LandmarkMapHeader>(services::SLAM_LANDMARKS, true),
    Topic::fixed::<SlamDiagnostics, MsgHeader>(services::SLAM_DIAGNOSTICS, true),
    Topic::fixed::<BuoyFix, MsgHeader>(services::BUOY_FIX, true),
    Topic::fixed::<SyncedPair, MsgHeader>(services::SYNC_PAIR, true),
    Topic::fixed::<FusedPose, MsgHeader>(services::FUSION_POSE, true),
    Topic::slice::<Landmark, LandmarkMapHeader>(services::FUSION_MAP, true),
    Topic::fixed::<MapStats, MsgHeader>(services::MAP_STATS, true),
    Topic::slice::<Voxel, VoxelSetHeader>(services::MAP_VOXELS, true),
    Topic::slice::<TraversabilityCell, OccupancyGridHeader>(services::MAP_TRAVERSABILITY, true),
    Topic::slice::<LaserRange, LaserScanHeader>(services::LASER, true),
    Topic::fixed::<PlanarOdometry, MsgHeader>(services::PLANAR_ODOMETRY, true),
    Topic::fixed::<PlanarPose, MsgHeader>(services::GRID_SLAM_POSE, true),
    Topic::fixed::<PoseEstimate, MsgHeader>(services::GRID_SLAM_POSE3D, true),
    Topic::slice::<Particle, ParticleSetHeader>(services::GRID_SLAM_PARTICLES, true),
    Topic::slice::<OccupancyCell, OccupancyGridHeader>(services::GRID_SLAM_GRID, true),
    Topic::fixed::<EndOfStream, MsgHeader>(services::END_OF_STREAM, true),
    Topic::fixed::<ControlCommand, MsgHeader>(services::COMMAND, true),
    Topic::fixed::<Heartbeat, MsgHeader>(services::HEARTBEAT, false),
];

/// The topic of service `name`.
pub fn topic(name: &str) -> Option<&'static Topic> {
    TOPICS.iter().find(|t| t.service == name)
}

#[cfg(test)]
mod tests {
    use super::*;
    use pipeline_runtime::topics::LenError;

    #[test]
    fn every_service_of_the_contract_but_the_statistics_is_a_topic_with_the_contract_types() {
        for spec in services::SERVICES {
            if spec.name.starts_with(services::STATS_PREFIX) {
                assert!(topic(spec.name).is_none());
                continue;
            }
            let t = topic(spec.name).unwrap_or_else(|| panic!("{} has no topic", spec.name));
            assert_eq!(t.contract_payload(), spec.payload, "{}", spec.name);
            assert_eq!((t.header)().rust_name, spec.user_header, "{}", spec.name);
        }
        assert_eq!(TOPICS.len(), services::SERVICES.len() - 1);
    }

    #[test]
    fn message_lengths_are_checked_against_header_and_payload_sizes() {
        let odo = topic(services::ODOMETRY).unwrap();
        assert_eq!(odo.check_len(32 + 168), Ok(1));
        assert_eq!(odo.check_len(32 + 167), Err(LenError::PayloadSize { got: 167, expected: 168 }));
        assert_eq!(odo.check_len(10), Err(LenError::ShorterThanHeader { got: 10, header: 32 }));
        let cloud = topic(services::CLOUD).unwrap();
        assert_eq!(cloud.check_len(96 + 12 * 5), Ok(5));
        assert_eq!(cloud.check_len(96), Ok(0));
        assert_eq!(cloud.check_len(96 + 13), Err(LenError::SliceRemainder { got: 13, element: 12 }));
    }
}

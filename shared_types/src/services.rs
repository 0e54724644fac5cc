//! Service names and their QoS: the public contract external producers write against.
//!
//! Each data service `X` has an event service with the same name `X` (iceoryx2 keeps the two
//! messaging patterns apart); publishers notify it after every send. The QoS values below are the
//! ones the pipeline creates the services with; a process that opens a service must ask for at most
//! these values (iceoryx2 treats the opener's values as minimums).
//!
//! Every data service's `max_subscribers` leaves room for [`WATCHERS`] subscribers beyond what the
//! shipped configs use (a viewer and a recorder). A run that needs more sets
//! `run.extra_subscribers`: every process of the run then adds that many to every service's
//! `max_subscribers` and `max_nodes` ([`Qos::with_extra`]: the runtime applies the run's count
//! where it opens services); an external producer that may create a service before the pipeline
//! does must add them too.

/// Subscribers every data service admits beyond the shipped configs' own consumers: room for a
/// viewer and a recorder to attach to a running pipeline.
pub const WATCHERS: usize = 2;

/// Quality of service of one publish-subscribe service.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    /// Maximum publishers.
    pub max_publishers: usize,
    /// Maximum subscribers.
    pub max_subscribers: usize,
    /// Maximum nodes that may open the service.
    pub max_nodes: usize,
    /// Samples a subscriber queues per publisher before the oldest is overwritten.
    pub subscriber_buffer: usize,
    /// Samples a subscriber may hold at once.
    pub subscriber_borrowed: usize,
    /// Samples replayed to a late subscriber.
    pub history: usize,
    /// Overwrite the oldest queued sample instead of blocking the publisher.
    pub safe_overflow: bool,
    /// Samples a publisher may loan at once.
    pub publisher_loans: usize,
    /// For slice payloads: elements reserved up front per sample (the publisher grows by powers of two).
    pub initial_slice_len: usize,
}

impl Qos {
    /// Data that flows at sensor rate: newest wins, the publisher never blocks.
    pub const fn stream(max_subscribers: usize, initial_slice_len: usize) -> Self {
        Self {
            max_publishers: 2,
            max_subscribers,
            max_nodes: 32,
            subscriber_buffer: 4,
            subscriber_borrowed: 2,
            history: 0,
            safe_overflow: true,
            publisher_loans: 2,
            initial_slice_len,
        }
    }

    /// Estimates every sample of which a downstream stage needs (poses, fixes, pairs): newest
    /// wins and the publisher never blocks, but 1024 samples of queue (tens of seconds at camera
    /// rate, predicted and refined fused poses together) absorb a consumer that is descheduled,
    /// slower for a while, or held by a link (a bridge waiting out a cut). A loss still shows as
    /// a sequence gap (`missed` in the stats). Under 0.5 MB per subscriber for these small types.
    pub const fn estimates(max_subscribers: usize) -> Self {
        Self { subscriber_buffer: 1024, ..Self::stream(max_subscribers, 0) }
    }

    /// Sensor data: nothing is overwritten; a full subscriber queue makes the publisher either
    /// drop the new sample for that subscriber (live sources) or wait (replay with back-pressure).
    pub const fn sensor(max_subscribers: usize, subscriber_buffer: usize, initial_slice_len: usize) -> Self {
        Self { safe_overflow: false, subscriber_buffer, ..Self::stream(max_subscribers, initial_slice_len) }
    }

    /// This QoS with a run's `run.extra_subscribers` (`extra`) added to `max_subscribers` and
    /// `max_nodes`: what every process of that run opens services with.
    pub const fn with_extra(&self, extra: usize) -> Self {
        Self { max_subscribers: self.max_subscribers + extra, max_nodes: self.max_nodes + extra, ..*self }
    }

    /// Chunks one publisher of this service reserves (iceoryx2's data-segment formula); apply
    /// [`Qos::with_extra`] first for a run's real figure.
    pub const fn chunks_per_publisher(&self) -> usize {
        self.max_subscribers * (self.subscriber_buffer + self.subscriber_borrowed) + self.history + self.publisher_loans
    }
}

/// One service of the contract.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ServiceSpec {
    /// iceoryx2 service name.
    pub name: &'static str,
    /// Payload type (`[T]` for a slice).
    pub payload: &'static str,
    /// User header type.
    pub user_header: &'static str,
    /// QoS the pipeline creates it with.
    pub qos: Qos,
}

/// Odometry / input stream, [`crate::OdometryInput`].
pub const ODOMETRY: &str = "pipeline/sensors/odometry";
/// Stereo observations, `[StereoObservation]` per camera frame.
pub const STEREO: &str = "pipeline/sensors/stereo";
/// Buoy ranges, `[BuoyRange]`.
pub const BUOY_RANGES: &str = "pipeline/sensors/buoy_ranges";
/// Pressure depth, [`crate::DepthReading`].
pub const DEPTH: &str = "pipeline/sensors/depth";
/// Point clouds, `[CloudPoint]` with a [`crate::CloudHeader`].
pub const CLOUD: &str = "pipeline/sensors/cloud";
/// Heading (compass), [`crate::HeadingReading`].
pub const HEADING: &str = "pipeline/sensors/heading";
/// FastSLAM pose, [`crate::PoseEstimate`].
pub const SLAM_POSE: &str = "pipeline/slam/pose";
/// FastSLAM particle set, `[Particle]` with a [`crate::ParticleSetHeader`].
pub const SLAM_PARTICLES: &str = "pipeline/slam/particles";
/// Best particle's landmark map, `[Landmark]` with a [`crate::LandmarkMapHeader`].
pub const SLAM_LANDMARKS: &str = "pipeline/slam/landmarks";
/// FastSLAM per-frame diagnostics, [`crate::SlamDiagnostics`].
pub const SLAM_DIAGNOSTICS: &str = "pipeline/slam/diagnostics";
/// Buoy EKF fixes, [`crate::BuoyFix`].
pub const BUOY_FIX: &str = "pipeline/buoy/fix";
/// Synchronised pairs, [`crate::SyncedPair`].
pub const SYNC_PAIR: &str = "pipeline/sync/pair";
/// Fused global pose, [`crate::FusedPose`].
pub const FUSION_POSE: &str = "pipeline/fusion/pose";
/// Global landmark map, `[Landmark]` with a [`crate::LandmarkMapHeader`].
pub const FUSION_MAP: &str = "pipeline/fusion/map";
/// Octree statistics, [`crate::MapStats`].
pub const MAP_STATS: &str = "pipeline/map/stats";
/// Occupied voxels, `[Voxel]` with a [`crate::VoxelSetHeader`].
pub const MAP_VOXELS: &str = "pipeline/map/voxels";
/// The octree mapper's 2.5-D traversability grid ([`crate::OccupancyGridHeader`] +
/// `[TraversabilityCell]`), sent after each discovery of the navigable space (at the end of the
/// run, and every `traversability_interval_s` when set).
pub const MAP_TRAVERSABILITY: &str = "pipeline/map/traversability";
/// Planar laser scans ([`crate::LaserScanHeader`] + `[LaserRange]`).
pub const LASER: &str = "pipeline/sensors/laser";
/// Planar wheel odometry, [`crate::PlanarOdometry`].
pub const PLANAR_ODOMETRY: &str = "pipeline/sensors/planar_odometry";
/// The 2-D SLAM's pose, [`crate::PlanarPose`].
pub const GRID_SLAM_POSE: &str = "pipeline/grid_slam/pose";
/// The 2-D SLAM's pose lifted to 3-D (z 0, roll and pitch 0) for the 3-D stages, [`crate::PoseEstimate`].
pub const GRID_SLAM_POSE3D: &str = "pipeline/grid_slam/pose3d";
/// The 2-D SLAM's particles ([`crate::ParticleSetHeader`] + `[Particle]`).
pub const GRID_SLAM_PARTICLES: &str = "pipeline/grid_slam/particles";
/// The best particle's occupancy grid ([`crate::OccupancyGridHeader`] + `[OccupancyCell]`).
pub const GRID_SLAM_GRID: &str = "pipeline/grid_slam/grid";
/// Heartbeats of every process, [`crate::Heartbeat`].
pub const HEARTBEAT: &str = "pipeline/control/heartbeat";
/// End of stream, [`crate::EndOfStream`].
pub const END_OF_STREAM: &str = "pipeline/control/end_of_stream";
/// Commands to processes, [`crate::ControlCommand`].
pub const COMMAND: &str = "pipeline/control/command";
/// Prefix of the per-process latency statistics services (`pipeline/stats/<process>`, `[u8]`).
pub const STATS_PREFIX: &str = "pipeline/stats/";

/// Largest number of processes one pipeline may run (sizes the control services).
pub const MAX_PROCESSES: usize = 48;

/// Control-plane QoS: many publishers (one per process); subscribers: the supervisor, the end-of-stream
/// input of every stage of a pipeline, and room for a recorder and a viewer.
pub const CONTROL_QOS: Qos = Qos {
    max_publishers: MAX_PROCESSES,
    max_subscribers: 16,
    max_nodes: MAX_PROCESSES + 8,
    subscriber_buffer: 8,
    subscriber_borrowed: 2,
    history: 0,
    safe_overflow: true,
    publisher_loans: 2,
    initial_slice_len: 0,
};

/// QoS of a `pipeline/stats/<process>` service (bincode bytes, see the runtime's `StatsReport`).
pub const STATS_QOS: Qos = Qos {
    max_publishers: 1,
    max_subscribers: 4,
    max_nodes: 8,
    subscriber_buffer: 2,
    subscriber_borrowed: 1,
    history: 1,
    safe_overflow: true,
    publisher_loans: 1,
    initial_slice_len: 16 * 1024,
};

/// Every fixed service of the contract, with the QoS the pipeline creates it with.
pub const SERVICES: &[ServiceSpec] = &[
    spec(ODOMETRY, "OdometryInput", "MsgHeader", Qos::sensor(4 + WATCHERS, 16, 0)),
    spec(STEREO, "[StereoObservation]", "MsgHeader", Qos::sensor(4 + WATCHERS, 8, 1024)),
    spec(BUOY_RANGES, "[BuoyRange]", "MsgHeader", Qos::sensor(4 + WATCHERS, 8, 16)),
    spec(DEPTH, "DepthReading", "MsgHeader", Qos::sensor(4 + WATCHERS, 8, 0)),
    spec(HEADING, "HeadingReading", "MsgHeader", Qos::sensor(4 + WATCHERS, 8, 0)),
    spec(
        CLOUD,
        "[CloudPoint]",
        "CloudHeader",
        // Sensor data: a replay waits for a slow mapper, a live source drops (counted).
        Qos { subscriber_borrowed: 1, publisher_loans: 1, ..Qos::sensor(2 + WATCHERS, 2, 320 * 240) },
    ),
    spec(SLAM_POSE, "PoseEstimate", "MsgHeader", Qos::estimates(4 + WATCHERS)),
    spec(SLAM_PARTICLES, "[Particle]", "ParticleSetHeader", Qos::stream(2 + WATCHERS, 1024)),
    spec(SLAM_LANDMARKS, "[Landmark]", "LandmarkMapHeader", Qos::stream(2 + WATCHERS, 4096)),
    spec(SLAM_DIAGNOSTICS, "SlamDiagnostics", "MsgHeader", Qos::stream(4 + WATCHERS, 0)),
    spec(BUOY_FIX, "BuoyFix", "MsgHeader", Qos::estimates(4 + WATCHERS)),
    spec(SYNC_PAIR, "SyncedPair", "MsgHeader", Qos::estimates(4 + WATCHERS)),
    spec(FUSION_POSE, "FusedPose", "MsgHeader", Qos::estimates(4 + WATCHERS)),
    spec(FUSION_MAP, "[Landmark]", "LandmarkMapHeader", Qos::stream(2 + WATCHERS, 4096)),
    spec(MAP_STATS, "MapStats", "MsgHeader", Qos::stream(4 + WATCHERS, 0)),
    spec(
        MAP_VOXELS,
        "[Voxel]",
        "VoxelSetHeader",
        Qos {
            subscriber_buffer: 1,
            subscriber_borrowed: 1,
            publisher_loans: 1,
            ..Qos::stream(2 + WATCHERS, 16 * 1024)
        },
    ),
    spec(
        MAP_TRAVERSABILITY,
        "[TraversabilityCell]",
        "OccupancyGridHeader",
        // Large (the main job's: 0.8 M cells, 10 MB) and rare: zero-copy, newest wins.
        Qos {
            subscriber_buffer: 1,
            subscriber_borrowed: 1,
            publisher_loans: 1,
            ..Qos::stream(2 + WATCHERS, 1024 * 1024)
        },
    ),
    spec(LASER, "[LaserRange]", "LaserScanHeader", Qos::sensor(4 + WATCHERS, 16, 1024)),
    spec(PLANAR_ODOMETRY, "PlanarOdometry", "MsgHeader", Qos::sensor(4 + WATCHERS, 64, 0)),
    spec(GRID_SLAM_POSE, "PlanarPose", "MsgHeader", Qos::estimates(4 + WATCHERS)),
    spec(GRID_SLAM_POSE3D, "PoseEstimate", "MsgHeader", Qos::estimates(4 + WATCHERS)),
    spec(GRID_SLAM_PARTICLES, "[Particle]", "ParticleSetHeader", Qos::stream(2 + WATCHERS, 64)),
    spec(
        GRID_SLAM_GRID,
        "[OccupancyCell]",
        "OccupancyGridHeader",
        // Large (a 50 × 50 m map at 0.05 m is 1 MB): zero-copy, newest wins, one in flight.
        Qos {
            subscriber_buffer: 1,
            subscriber_borrowed: 1,
            publisher_loans: 1,
            ..Qos::stream(2 + WATCHERS, 1024 * 1024)
        },
    ),
    spec(HEARTBEAT, "Heartbeat", "MsgHeader", CONTROL_QOS),
    spec(END_OF_STREAM, "EndOfStream", "MsgHeader", CONTROL_QOS),
    spec(COMMAND, "ControlCommand", "MsgHeader", CONTROL_QOS),
    spec("pipeline/stats/<process>", "[u8]", "MsgHeader", STATS_QOS),
];

const fn spec(name: &'static str, payload: &'static str, user_header: &'static str, qos: Qos) -> ServiceSpec {
    ServiceSpec { name, payload, user_header, qos }
}

/// The spec of a fixed service by name.
pub fn service_spec(name: &str) -> Option<&'static ServiceSpec> {
    SERVICES.iter().find(|s| s.name == name)
}

/// The bit of a data service in `EndOfStream::outputs` (its index in [`SERVICES`]); `None` for
/// the control and statistics services and for names outside the contract.
pub fn data_service_bit(name: &str) -> Option<u32> {
    if name.starts_with("pipeline/control/") || name.starts_with(STATS_PREFIX) {
        return None;
    }
    SERVICES.iter().position(|s| s.name == name).map(|i| 1u32 << i)
}

const _: () = assert!(SERVICES.len() <= 31, "EndOfStream::outputs has 31 service bits");

/// The statistics service of a process.
pub fn stats_service(process: &str) -> String {
    format!("{STATS_PREFIX}{process}")
}

//! Wire types of the SLAM pipeline.
//!
//! Every payload and user header that crosses a process boundary is defined here as a
//! `#[repr(C)]`, [`ZeroCopySend`](iceoryx2::prelude::ZeroCopySend) plain-old-data struct with a pinned,
//! versioned iceoryx2 type name (`slam_pipeline::v1::…`) and a size asserted at compile time. The
//! byte layout of every type, and every service with its QoS, is in `docs/WIRE_FORMAT.md`, which is
//! rendered from this crate ([`layout::render_markdown`]). No logic lives here beyond conversions to
//! and from nalgebra ([`convert`]).

pub mod convert;
#[cfg(feature = "foxglove")]
pub mod foxglove;
pub mod layout;
pub mod services;
mod types;
pub mod voxel_stream;

pub use layout::{FieldLayout, Finite, TypeLayout, WireType};
pub use types::*;

/// Version of the wire contract, bumped on any change. A type whose layout changed carries the
/// new version in its type name (`slam_pipeline::v2::SlamDiagnostics`); the others keep theirs.
/// Version 2: `SlamDiagnostics` grew (motion source, registration, candidates, NIS), and the
/// `StereoObservation` flag `STEREO_HAS_TRACK_ID` (no layout change).
/// Version 3: `BuoyFix` grew the cross-covariance with the previous fix
/// (`slam_pipeline::v3::BuoyFix`).
pub const WIRE_VERSION: u32 = 3;

/// Layouts of every wire type, in documentation order.
pub fn all_layouts() -> Vec<TypeLayout> {
    vec![
        TypeLayout::of::<MsgHeader>(),
        TypeLayout::of::<OdometryInput>(),
        TypeLayout::of::<StereoObservation>(),
        TypeLayout::of::<BuoyRange>(),
        TypeLayout::of::<DepthReading>(),
        TypeLayout::of::<HeadingReading>(),
        TypeLayout::of::<CloudPoint>(),
        TypeLayout::of::<CloudHeader>(),
        TypeLayout::of::<PoseEstimate>(),
        TypeLayout::of::<Particle>(),
        TypeLayout::of::<ParticleSetHeader>(),
        TypeLayout::of::<Landmark>(),
        TypeLayout::of::<LandmarkMapHeader>(),
        TypeLayout::of::<SlamDiagnostics>(),
        TypeLayout::of::<BuoyFix>(),
        TypeLayout::of::<SyncedPair>(),
        TypeLayout::of::<FusedPose>(),
        TypeLayout::of::<MapStats>(),
        TypeLayout::of::<Voxel>(),
        TypeLayout::of::<VoxelSetHeader>(),
        TypeLayout::of::<LaserScanHeader>(),
        TypeLayout::of::<LaserRange>(),
        TypeLayout::of::<PlanarOdometry>(),
        TypeLayout::of::<PlanarPose>(),
        TypeLayout::of::<OccupancyGridHeader>(),
        TypeLayout::of::<OccupancyCell>(),
        TypeLayout::of::<TraversabilityCell>(),
        TypeLayout::of::<Heartbeat>(),
        TypeLayout::of::<EndOfStream>(),
        TypeLayout::of::<ControlCommand>(),
    ]
}

/// Renders docs/WIRE_FORMAT.md.
pub fn wire_format_markdown() -> String {
    layout::render_markdown(&all_layouts(), services::SERVICES)
}

/// Renders python/slam_pipeline_wire.py.
pub fn wire_format_python() -> String {
    layout::render_python(&all_layouts(), services::SERVICES)
}

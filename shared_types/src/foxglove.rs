//! The wire types as Foxglove's own schemas (feature `foxglove`): what the live viewer shows and
//! what the recorder writes next to the raw channels, so that the stock Foxglove app shows a run
//! or a recording without a plug-in. Everything is in the frame [`FRAME`]; timestamps are the
//! messages' `stamp_ns` (sensor time).

pub use ::foxglove::messages;
use ::foxglove::messages::packed_element_field::NumericType;
use ::foxglove::messages::{
    Grid, PackedElementField, PointCloud, Pose, PoseInFrame, Quaternion, Timestamp, Vector2, Vector3,
};

use crate::layout::WireType;
use crate::{
    CLOUD_HAS_POSE, CloudHeader, CloudPoint, Landmark, LandmarkMapHeader, OccupancyCell, OccupancyGridHeader,
    TraversabilityCell, Voxel,
};

/// The frame every channel is in.
pub const FRAME: &str = "world";

/// A Foxglove timestamp of `ns`.
pub fn stamp(ns: u64) -> Option<Timestamp> {
    Some(Timestamp::new((ns / 1_000_000_000) as u32, (ns % 1_000_000_000) as u32))
}

/// A pose from a position (m) and an orientation quaternion (x, y, z, w).
pub fn pose(position_m: [f64; 3], q_xyzw: [f64; 4]) -> Pose {
    Pose {
        position: Some(Vector3 { x: position_m[0], y: position_m[1], z: position_m[2] }),
        orientation: Some(Quaternion { x: q_xyzw[0], y: q_xyzw[1], z: q_xyzw[2], w: q_xyzw[3] }),
    }
}

/// The identity pose.
pub fn identity() -> Pose {
    pose([0.0; 3], [0.0, 0.0, 0.0, 1.0])
}

/// A pose in [`FRAME`] at `ns`.
pub fn pose_in_frame(ns: u64, p: Pose) -> PoseInFrame {
    PoseInFrame { timestamp: stamp(ns), frame_id: FRAME.into(), pose: Some(p) }
}

/// A point cloud of `rows`, each the `float32` values of `fields` in order, placed at `at`.
pub fn point_cloud(
    ns: u64,
    at: Pose,
    fields: &[&str],
    rows: impl Iterator<Item = impl IntoIterator<Item = f32>>,
) -> PointCloud {
    let mut data = Vec::new();
    for row in rows {
        for v in row {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    PointCloud {
        timestamp: stamp(ns),
        frame_id: FRAME.into(),
        pose: Some(at),
        point_stride: 4 * fields.len() as u32,
        fields: fields
            .iter()
            .enumerate()
            .map(|(i, n)| PackedElementField {
                name: (*n).into(),
                offset: 4 * i as u32,
                r#type: NumericType::Float32 as i32,
            })
            .collect(),
        data: data.into(),
    }
}

/// A sensor's cloud (`pipeline/sensors/cloud`), placed at its sensor pose when it has one.
pub fn cloud(h: &CloudHeader, points: &[CloudPoint]) -> PointCloud {
    let at = if h.flags & CLOUD_HAS_POSE != 0 { pose(h.sensor_origin_m, h.orientation_xyzw) } else { identity() };
    point_cloud(h.msg.stamp_ns, at, &["x", "y", "z"], points.iter().map(|p| [p.x_m, p.y_m, p.z_m]))
}

/// A landmark map as points (field `observations`).
pub fn landmarks(h: &LandmarkMapHeader, map: &[Landmark]) -> PointCloud {
    point_cloud(
        h.msg.stamp_ns,
        identity(),
        &["x", "y", "z", "observations"],
        map.iter().map(|l| [l.mean_m[0] as f32, l.mean_m[1] as f32, l.mean_m[2] as f32, l.observation_count as f32]),
    )
}

/// Voxels as points at their centres (fields `occupancy`, `class`, `size`).
pub fn voxels<'a>(ns: u64, voxels: impl Iterator<Item = &'a Voxel>) -> PointCloud {
    point_cloud(
        ns,
        identity(),
        &["x", "y", "z", "occupancy", "class", "size"],
        voxels.map(|v| [v.center_m[0], v.center_m[1], v.center_m[2], v.occupancy, v.class as f32, v.size_m]),
    )
}

/// An occupancy grid (int8 field `occupancy`: -1 unknown, 0-100).
pub fn grid(h: &OccupancyGridHeader, cells: &[OccupancyCell]) -> Grid {
    Grid {
        timestamp: stamp(h.msg.stamp_ns),
        frame_id: FRAME.into(),
        pose: Some(pose([h.origin_m[0], h.origin_m[1], 0.0], [0.0, 0.0, 0.0, 1.0])),
        column_count: h.width,
        cell_size: Some(Vector2 { x: h.resolution_m, y: h.resolution_m }),
        row_stride: h.width,
        cell_stride: 1,
        fields: vec![PackedElementField { name: "occupancy".into(), offset: 0, r#type: NumericType::Int8 as i32 }],
        data: cells.iter().map(|c| c.value as u8).collect::<Vec<u8>>().into(),
    }
}

/// The 2.5-D traversability grid: its cells' bytes as they are on the wire (fields `height`
/// float32 m, `slope` float32 deg, `class` uint8: 0 unknown, 1 navigable, 2 obstacle), at z 0.
pub fn traversability(h: &OccupancyGridHeader, cells: &[TraversabilityCell]) -> Grid {
    let field =
        |name: &str, offset: u32, t: NumericType| PackedElementField { name: name.into(), offset, r#type: t as i32 };
    let stride = size_of::<TraversabilityCell>() as u32;
    let mut data = Vec::with_capacity(cells.len() * stride as usize);
    for c in cells {
        data.extend_from_slice(c.as_bytes());
    }
    Grid {
        timestamp: stamp(h.msg.stamp_ns),
        frame_id: FRAME.into(),
        pose: Some(pose([h.origin_m[0], h.origin_m[1], 0.0], [0.0, 0.0, 0.0, 1.0])),
        column_count: h.width,
        cell_size: Some(Vector2 { x: h.resolution_m, y: h.resolution_m }),
        row_stride: h.width * stride,
        cell_stride: stride,
        fields: vec![
            field("height", std::mem::offset_of!(TraversabilityCell, height_m) as u32, NumericType::Float32),
            field("slope", std::mem::offset_of!(TraversabilityCell, slope_deg) as u32, NumericType::Float32),
            field("class", std::mem::offset_of!(TraversabilityCell, class) as u32, NumericType::Uint8),
        ],
        data: data.into(),
    }
}

/// The elements of a slice payload held as bytes (a recorded message); `None` when the length is
/// not a whole number of elements.
pub fn elements<T: WireType>(bytes: &[u8]) -> Option<Vec<T>> {
    let n = size_of::<T>();
    if n == 0 || !bytes.len().is_multiple_of(n) {
        return None;
    }
    bytes.chunks_exact(n).map(T::from_bytes).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_point_cloud_packs_its_rows_as_float32_fields() {
        let m = point_cloud(
            1_500_000_000,
            identity(),
            &["x", "y", "z", "w"],
            [[1.0f32, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0]].into_iter(),
        );
        assert_eq!(m.point_stride, 16);
        assert_eq!(m.data.len(), 32);
        assert_eq!(m.fields.iter().map(|f| f.offset).collect::<Vec<_>>(), [0, 4, 8, 12]);
        assert_eq!(f32::from_le_bytes(m.data[20..24].try_into().unwrap()), 6.0);
        let t = m.timestamp.unwrap();
        assert_eq!((t.sec(), t.nsec()), (1, 500_000_000));
    }

    #[test]
    fn recorded_messages_encode_as_their_foxglove_channels_messages() {
        use crate::{FusedPose, MsgHeader, PoseEstimate, VOXELS_DELTA, VOXELS_FULL, VoxelSetHeader, services as s};
        use ::foxglove::Decode;
        let h = MsgHeader { stamp_ns: 2_000_000_007, ..Default::default() };
        let p = FusedPose {
            pose: PoseEstimate {
                position_m: [1.0, -2.0, 3.0],
                orientation_xyzw: [0.0, 0.0, 0.6, 0.8],
                ..Default::default()
            },
            ..Default::default()
        };
        let data = [h.as_bytes(), p.as_bytes()].concat();
        let m = PoseInFrame::decode(&encode_recorded(s::FUSION_POSE, &data).unwrap()[..]).unwrap();
        let q = m.pose.unwrap();
        assert_eq!(q.position.unwrap().y, -2.0);
        assert_eq!(q.orientation.unwrap().w, 0.8);
        assert_eq!(m.frame_id, FRAME);
        assert_eq!(m.timestamp.unwrap().nsec(), 7);
        assert_eq!(mirror_of(s::FUSION_POSE).unwrap().schema.name, "foxglove.PoseInFrame");
        assert!(encode_recorded(s::FUSION_POSE, &data[..40]).is_none(), "a short message is no pose");
        assert!(encode_recorded(s::SYNC_PAIR, &data).is_none() && mirror_of(s::SYNC_PAIR).is_none());
        // The octree: a full set is the map, a delta is not shown alone.
        let v = Voxel { center_m: [0.05, 0.15, 0.25], size_m: 0.1, occupancy: 0.9, class: 2 };
        for (kind, shown) in [(VOXELS_FULL, true), (VOXELS_DELTA, false)] {
            let vh = VoxelSetHeader { kind, resolution_m: 0.1, ..Default::default() };
            let data = [vh.as_bytes(), v.as_bytes(), v.as_bytes()].concat();
            let e = encode_recorded(s::MAP_VOXELS, &data);
            assert_eq!(e.is_some(), shown);
            if let Some(e) = e {
                let c = PointCloud::decode(&e[..]).unwrap();
                assert_eq!(c.data.len(), 2 * 24);
                assert_eq!(c.fields[4].name, "class");
            }
        }
    }

    #[test]
    fn an_occupancy_grid_keeps_its_cells_rows_origin_and_resolution() {
        let h = OccupancyGridHeader {
            resolution_m: 0.05,
            origin_m: [-2.0, 3.0],
            width: 3,
            height: 2,
            ..Default::default()
        };
        let cells: Vec<OccupancyCell> =
            [-1i8, 0, 100, 50, -1, 7].iter().map(|&value| OccupancyCell { value }).collect();
        let g = grid(&h, &cells);
        assert_eq!((g.column_count, g.row_stride, g.cell_stride), (3, 3, 1));
        assert_eq!(g.data.iter().map(|&b| b as i8).collect::<Vec<_>>(), [-1, 0, 100, 50, -1, 7]);
        assert_eq!(g.cell_size.unwrap().x, 0.05);
        let at = g.pose.unwrap().position.unwrap();
        assert_eq!((at.x, at.y, at.z), (-2.0, 3.0, 0.0));
        assert_eq!(g.fields[0].r#type, NumericType::Int8 as i32);
    }

    #[test]
    fn a_traversability_grid_keeps_its_cells_bytes_and_names_their_three_fields() {
        use crate::{TRAVERSABILITY_NAVIGABLE, TRAVERSABILITY_OBSTACLE, services as s};
        use ::foxglove::Decode;
        let h =
            OccupancyGridHeader { resolution_m: 0.1, origin_m: [-1.0, 2.0], width: 2, height: 1, ..Default::default() };
        let cells = [
            TraversabilityCell { height_m: -20.25, slope_deg: 3.5, class: TRAVERSABILITY_NAVIGABLE, _reserved: [0; 3] },
            TraversabilityCell { height_m: -18.0, slope_deg: 0.0, class: TRAVERSABILITY_OBSTACLE, _reserved: [0; 3] },
        ];
        let data = [h.as_bytes(), cells[0].as_bytes(), cells[1].as_bytes()].concat();
        let g = Grid::decode(&encode_recorded(s::MAP_TRAVERSABILITY, &data).unwrap()[..]).unwrap();
        assert_eq!(mirror_of(s::MAP_TRAVERSABILITY).unwrap().topic, "/traversability");
        assert_eq!((g.column_count, g.row_stride, g.cell_stride), (2, 24, 12));
        let names: Vec<&str> = g.fields.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["height", "slope", "class"]);
        // Each field read where the grid says it is, in the second cell.
        let at = |f: usize| 12 + g.fields[f].offset as usize;
        assert_eq!(f32::from_le_bytes(g.data[at(0)..at(0) + 4].try_into().unwrap()), -18.0);
        assert_eq!(g.data[at(2)], TRAVERSABILITY_OBSTACLE);
        assert_eq!(f32::from_le_bytes(g.data[g.fields[1].offset as usize..][..4].try_into().unwrap()), 3.5);
        assert_eq!(g.fields[2].r#type, NumericType::Uint8 as i32);
        assert!(encode_recorded(s::MAP_TRAVERSABILITY, &data[..data.len() - 1]).is_none(), "a partial cell");
    }

    #[test]
    fn landmarks_become_points_with_their_observation_counts() {
        let l = Landmark { mean_m: [1.5, -2.5, 30.0], observation_count: 12, ..Default::default() };
        let c = landmarks(&LandmarkMapHeader::default(), &[l, l]);
        assert_eq!(c.point_stride, 16);
        assert_eq!(c.data.len(), 32);
        assert_eq!(f32::from_le_bytes(c.data[12..16].try_into().unwrap()), 12.0);
        assert_eq!(f32::from_le_bytes(c.data[4..8].try_into().unwrap()), -2.5);
    }

    #[test]
    fn recorded_bytes_become_elements_or_nothing() {
        let pts = [CloudPoint { x_m: 1.0, y_m: 2.0, z_m: 3.0 }, CloudPoint { x_m: 4.0, y_m: 5.0, z_m: 6.0 }];
        let bytes: Vec<u8> = pts.iter().flat_map(|p| p.as_bytes().to_vec()).collect();
        let back = elements::<CloudPoint>(&bytes).unwrap();
        assert_eq!(back.len(), 2);
        assert_eq!(back[1].y_m, 5.0);
        assert!(elements::<CloudPoint>(&bytes[..13]).is_none());
    }
}

/// A Foxglove-schema channel that mirrors a recorded service ([`mirror_of`]).
#[derive(Debug, Clone)]
pub struct Mirror {
    /// Its topic (the live viewer's name where it shows the same thing).
    pub topic: &'static str,
    /// Its schema (a protobuf FileDescriptorSet of Foxglove's schema).
    pub schema: ::foxglove::Schema,
    /// Its message encoding (`protobuf`).
    pub message_encoding: String,
}

fn mirror<T: ::foxglove::Encode>(topic: &'static str) -> Option<Mirror> {
    Some(Mirror { topic, schema: T::get_schema()?, message_encoding: T::get_message_encoding() })
}

/// The Foxglove channel a recording writes next to `service`'s raw one: poses as
/// `foxglove.PoseInFrame` (`/slam/pose`, `/buoy/pose`, `/fused/pose`, `/grid_slam/pose`), clouds,
/// landmark maps and the octree's full voxel sets as `foxglove.PointCloud` (`/cloud`,
/// `/slam/landmarks`, `/landmarks`, `/octree`), the 2-D grid and the traversability grid as
/// `foxglove.Grid` (`/grid`, `/traversability`).
pub fn mirror_of(service: &str) -> Option<Mirror> {
    use crate::services as s;
    match service {
        s::SLAM_POSE => mirror::<PoseInFrame>("/slam/pose"),
        s::BUOY_FIX => mirror::<PoseInFrame>("/buoy/pose"),
        s::FUSION_POSE => mirror::<PoseInFrame>("/fused/pose"),
        s::GRID_SLAM_POSE3D => mirror::<PoseInFrame>("/grid_slam/pose"),
        s::CLOUD => mirror::<PointCloud>("/cloud"),
        s::SLAM_LANDMARKS => mirror::<PointCloud>("/slam/landmarks"),
        s::FUSION_MAP => mirror::<PointCloud>("/landmarks"),
        s::MAP_VOXELS => mirror::<PointCloud>("/octree"),
        s::GRID_SLAM_GRID => mirror::<Grid>("/grid"),
        s::MAP_TRAVERSABILITY => mirror::<Grid>("/traversability"),
        _ => None,
    }
}

fn split<H: WireType>(data: &[u8]) -> Option<(H, &[u8])> {
    let n = size_of::<H>();
    Some((H::from_bytes(data.get(..n)?)?, &data[n..]))
}

fn encoded<T: ::foxglove::Encode>(m: &T) -> Option<Vec<u8>> {
    let mut buf = Vec::with_capacity(m.encoded_len().unwrap_or(0));
    m.encode(&mut buf).ok()?;
    Some(buf)
}

/// A recorded message of `service` (its user header's bytes, then its payload's) as the message
/// of its [`mirror_of`] channel, encoded. `None` for another service, bytes that are not such a
/// message, and an octree delta (only full voxel sets show the map).
pub fn encode_recorded(service: &str, data: &[u8]) -> Option<Vec<u8>> {
    use crate::services as s;
    use crate::{BuoyFix, FusedPose, MsgHeader, PoseEstimate, VOXELS_FULL, VoxelSetHeader};
    let pose_of =
        |h: MsgHeader, p: &PoseEstimate| encoded(&pose_in_frame(h.stamp_ns, pose(p.position_m, p.orientation_xyzw)));
    match service {
        s::SLAM_POSE | s::GRID_SLAM_POSE3D => {
            let (h, p) = split::<MsgHeader>(data)?;
            pose_of(h, &PoseEstimate::from_bytes(p)?)
        }
        s::FUSION_POSE => {
            let (h, p) = split::<MsgHeader>(data)?;
            pose_of(h, &FusedPose::from_bytes(p)?.pose)
        }
        s::BUOY_FIX => {
            let (h, p) = split::<MsgHeader>(data)?;
            let f = BuoyFix::from_bytes(p)?;
            encoded(&pose_in_frame(h.stamp_ns, pose(f.position_m, [0.0, 0.0, 0.0, 1.0])))
        }
        s::CLOUD => {
            let (h, p) = split::<CloudHeader>(data)?;
            encoded(&cloud(&h, &elements::<CloudPoint>(p)?))
        }
        s::SLAM_LANDMARKS | s::FUSION_MAP => {
            let (h, p) = split::<LandmarkMapHeader>(data)?;
            encoded(&landmarks(&h, &elements::<Landmark>(p)?))
        }
        s::MAP_VOXELS => {
            let (h, p) = split::<VoxelSetHeader>(data)?;
            if h.kind != VOXELS_FULL {
                return None;
            }
            encoded(&voxels(h.msg.stamp_ns, elements::<Voxel>(p)?.iter()))
        }
        s::GRID_SLAM_GRID => {
            let (h, p) = split::<OccupancyGridHeader>(data)?;
            encoded(&grid(&h, &elements::<OccupancyCell>(p)?))
        }
        s::MAP_TRAVERSABILITY => {
            let (h, p) = split::<OccupancyGridHeader>(data)?;
            encoded(&traversability(&h, &elements::<TraversabilityCell>(p)?))
        }
        _ => None,
    }
}

//! Unit tests of the parent module.

use super::*;
use shared_types::{MsgHeader, VOXELS_DELTA, VOXELS_FULL};

fn fused(x: f64, refined: bool) -> FusedPose {
    let mut p = FusedPose::default();
    p.pose.position_m = [x, 0.0, -1.0];
    p.pose.orientation_xyzw = [0.0, 0.0, 0.0, 1.0];
    p.flags = if refined { FUSED_REFINED } else { 0 };
    p
}

#[test]
fn poses_go_out_at_once_and_paths_as_coalesced_snapshots() {
    let routes = [
        OutRoute::of(OutKind::FusedOdometry),
        OutRoute { max_rate_hz: 1e-3, ..OutRoute::of(OutKind::FusedPath) },
        OutRoute::of(OutKind::Tf),
    ];
    let mut t = Translator::new(&routes, &Frames::default());
    assert!(t.needs().fused && !t.needs().voxels);
    let mut out = vec![];
    t.fused(1, 10, &fused(1.0, false), &mut out);
    assert!(out.is_empty(), "a prediction is not published");
    t.fused(2, 20, &fused(2.0, true), &mut out);
    assert_eq!(out.len(), 2, "odometry and tf at once");
    assert!(matches!(out[0].msg, RosOut::Odometry(_)) && matches!(out[1].msg, RosOut::Tf(_)));
    assert_eq!(out[0].source_publish_ns, 20);
    out.clear();
    assert!(t.flush(false, &mut out).is_none());
    let RosOut::Path(p) = &out[0].msg else { panic!("{:?}", out[0]) };
    assert_eq!(p.poses.len(), 1);
    out.clear();
    t.fused(3, 30, &fused(3.0, true), &mut out);
    t.fused(4, 40, &fused(4.0, true), &mut out);
    out.clear();
    assert!(t.flush(false, &mut out).is_some(), "not due yet: kept");
    assert!(out.is_empty());
    t.flush(true, &mut out);
    let RosOut::Path(p) = &out[0].msg else { panic!() };
    assert_eq!((p.poses.len(), p.header.stamp.to_ns()), (3, Some(4)));
    assert_eq!(t.route_coalesced(1), 1, "the second update folded into the third");
    assert_eq!((t.route_taken(0), t.route_taken(1), t.taken()), (3, 3, 4));
}

#[test]
fn an_unheard_route_emits_nothing_keeps_its_path_and_its_first_listener_gets_it_at_once() {
    let routes = [OutRoute::of(OutKind::FusedOdometry), OutRoute::of(OutKind::FusedPath)];
    let mut t = Translator::new(&routes, &Frames::default());
    t.set_listened(0, false);
    t.set_listened(1, false);
    let mut out = vec![];
    for k in 1..=5 {
        t.fused(k, k * 10, &fused(k as f64, true), &mut out);
    }
    assert!(t.flush(false, &mut out).is_none());
    assert!(out.is_empty(), "{out:?}");
    assert_eq!((t.route_not_emitted_unheard(0), t.route_coalesced(1)), (5, 0));
    t.set_listened(1, true);
    t.flush(false, &mut out);
    let [Emitted { route: 1, msg: RosOut::Path(p), .. }] = &out[..] else { panic!("{out:?}") };
    assert_eq!(p.poses.len(), 5, "the whole path so far");
    out.clear();
    t.set_listened(0, true);
    t.fused(6, 60, &fused(6.0, true), &mut out);
    assert_eq!(out.len(), 1, "odometry again once heard; the path is due later");
    assert_eq!(t.route_not_emitted_unheard(0), 5);
}

#[test]
fn voxels_wait_for_a_full_set_and_a_gap_asks_for_a_new_one() {
    let routes = [OutRoute::of(OutKind::Voxels), OutRoute::of(OutKind::Obstacles)];
    let mut t = Translator::new(&routes, &Frames::default());
    let h = |seq, kind| VoxelSetHeader {
        msg: MsgHeader { seq, stamp_ns: seq, ..Default::default() },
        kind,
        resolution_m: 0.5,
        ..Default::default()
    };
    let v = |x: f32, class| Voxel { center_m: [x, 0.0, 0.0], size_m: 0.5, occupancy: 0.9, class };
    let mut out = vec![];
    t.voxels(&h(0, VOXELS_DELTA), &[v(0.25, 0)]);
    t.flush(true, &mut out);
    assert!(out.is_empty(), "a delta before any full set is not a map");
    t.voxels(&h(1, VOXELS_FULL), &[v(0.25, 0), v(1.25, VOXEL_OBSTACLE), v(2.25, VOXEL_WALL), v(2.75, VOXEL_WALL)]);
    t.flush(true, &mut out);
    assert_eq!(out.len(), 2);
    let RosOut::Cloud(c) = &out[0].msg else { panic!() };
    assert_eq!(c.width * c.height, 4);
    let RosOut::Markers(m) = &out[1].msg else { panic!() };
    assert_eq!(m.markers[0].points.len(), 1, "the obstacles");
    assert_eq!((&*m.markers[1].ns, m.markers[1].points.len()), ("walls", 2));
    out.clear();
    t.voxels(&h(5, VOXELS_DELTA), &[v(2.25, 0)]);
    assert_eq!(t.voxel_gaps().0, 3);
    assert!(t.wants_voxel_snapshot());
    assert!(!t.wants_voxel_snapshot(), "asked at most every 5 s");
    t.flush(true, &mut out);
    assert!(out.is_empty(), "nothing until the next full set");
}

#[test]
fn tf_with_odometry_gives_map_to_odom_and_odom_to_base_link() {
    let routes = [OutRoute { from: TfFrom::GridSlam, odom: TfOdom::PlanarOdometry, ..OutRoute::of(OutKind::Tf) }];
    let mut t = Translator::new(&routes, &Frames::default());
    assert!(t.needs().odometry && t.needs().grid_pose);
    let mut out = vec![];
    let pose = PlanarPose { position_m: [2.0, 0.0], yaw_rad: 0.0, ..Default::default() };
    t.grid_pose(5, 1, &pose, &mut out);
    assert!(out.is_empty(), "no odometry yet: no map → odom");
    assert_eq!(t.route_no_odometry(0), 1, "counted");
    let o = PlanarOdometry { position_m: [1.5, 0.0], yaw_rad: 0.0, ..Default::default() };
    t.odometry(4, 1, &o, &mut out);
    t.grid_pose(5, 1, &pose, &mut out);
    let tf: Vec<(String, String, f64)> = out
        .iter()
        .map(|e| match &e.msg {
            RosOut::Tf(m) => {
                let t = &m.transforms[0];
                (t.header.frame_id.clone(), t.child_frame_id.clone(), t.transform.translation.x)
            }
            _ => panic!(),
        })
        .collect();
    assert_eq!(tf, [("odom".into(), "base_link".into(), 1.5), ("map".into(), "odom".into(), 0.5)]);
}

#[test]
fn routes_are_checked_and_static_tf_has_the_mounts_and_the_identity_map_to_odom() {
    let routes = [OutRoute::of(OutKind::Tf), OutRoute { topic: Some("/my map".into()), ..OutRoute::of(OutKind::Map) }];
    let statics = [StaticTransform {
        parent: "base_link".into(),
        child: "cam".into(),
        xyz_m: [0.5, 0.0, 0.0],
        rpy_rad: [0.0; 3],
    }];
    let mut issues = validation::Issues::new();
    validate(&routes, &Frames::default(), &statics, &mut Default::default(), &mut issues);
    assert_eq!(issues.len(), 1, "{issues}");
    assert!(issues.has("out[1].topic"), "{issues}");
    let tf = static_tf(&statics, &routes, &Frames::default()).unwrap();
    assert_eq!(tf.transforms.len(), 2);
    assert_eq!(tf.transforms[1].header.frame_id, "map");
    assert!(static_tf(&[], &routes[1..], &Frames::default()).is_none());
}

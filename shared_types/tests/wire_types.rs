//! Wire types: layouts, names, the generated layout document, and nalgebra conversions.

use nalgebra::{Isometry3, Matrix3, Matrix6, UnitQuaternion, Vector3};
use proptest::prelude::*;
use shared_types::convert::*;
use shared_types::services::SERVICES;
use shared_types::*;

#[test]
fn docs_wire_format_md_matches_the_code() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/WIRE_FORMAT.md");
    let on_disk = std::fs::read_to_string(path).expect("docs/WIRE_FORMAT.md exists");
    assert!(
        on_disk == wire_format_markdown(),
        "docs/WIRE_FORMAT.md is out of date: cargo run -p shared_types --example wire_doc > docs/WIRE_FORMAT.md"
    );
}

#[test]
fn every_type_has_a_unique_versioned_name_and_contiguous_fields() {
    let layouts = all_layouts();
    let mut names: Vec<_> = layouts.iter().map(|l| l.type_name).collect();
    names.sort();
    names.dedup();
    assert_eq!(names.len(), layouts.len(), "type names must be unique");
    for l in &layouts {
        // `slam_pipeline::v<N>::<Type>`: N is the wire version of the type's last layout change.
        let version = (1..=shared_types::WIRE_VERSION)
            .find(|v| l.type_name == format!("slam_pipeline::v{v}::{}", l.rust_name))
            .unwrap_or_else(|| {
                panic!(
                    "{}: type name `{}` is not slam_pipeline::v<1..={}>::{}",
                    l.rust_name,
                    l.type_name,
                    shared_types::WIRE_VERSION,
                    l.rust_name
                )
            });
        assert!(version >= 1);
        let mut next = 0;
        for f in &l.fields {
            assert_eq!(f.offset, next, "{}.{} does not follow the previous field", l.rust_name, f.name);
            assert!(!f.doc.trim().is_empty(), "{}.{} has no documentation", l.rust_name, f.name);
            next += f.size;
        }
        assert_eq!(next, l.size, "{}: fields do not fill the struct", l.rust_name);
        assert!(l.size % l.align == 0);
    }
}

#[test]
fn service_names_are_unique_and_payloads_are_documented_types() {
    let layouts = all_layouts();
    let mut names: Vec<_> = SERVICES.iter().map(|s| s.name).collect();
    names.sort();
    names.dedup();
    assert_eq!(names.len(), SERVICES.len());
    for s in SERVICES {
        let payload = s.payload.trim_start_matches('[').trim_end_matches(']');
        assert!(payload == "u8" || layouts.iter().any(|l| l.rust_name == payload), "{}: {payload}", s.name);
        assert!(layouts.iter().any(|l| l.rust_name == s.user_header), "{}: {}", s.name, s.user_header);
        assert!(s.qos.max_publishers > 0 && s.qos.max_subscribers > 0 && s.qos.subscriber_buffer > 0);
    }
}

#[test]
fn header_fields_sit_at_the_start_of_every_user_header() {
    for l in all_layouts() {
        if l.fields.first().is_some_and(|f| f.ty == "MsgHeader") {
            assert_eq!(l.fields[0].offset, 0, "{}", l.rust_name);
        }
    }
    assert_eq!(std::mem::offset_of!(CloudHeader, msg), 0);
}

#[test]
fn quaternion_goes_on_the_wire_as_x_y_z_w() {
    let q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2);
    let w = quat_to_xyzw(&q);
    let h = std::f64::consts::FRAC_1_SQRT_2;
    assert!((w[0]).abs() < 1e-12 && (w[1]).abs() < 1e-12);
    assert!((w[2] - h).abs() < 1e-12 && (w[3] - h).abs() < 1e-12, "{w:?}");
    // The identity is (0, 0, 0, 1), not (1, 0, 0, 0).
    assert_eq!(quat_to_xyzw(&UnitQuaternion::identity()), [0.0, 0.0, 0.0, 1.0]);
    let back = quat_from_xyzw(&[0.0, 0.0, 0.0, 1.0]);
    assert!(back.angle() < 1e-12);
}

#[test]
fn matrices_go_on_the_wire_row_major() {
    let m = Matrix3::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0);
    assert_eq!(mat3_to_row_major(&m), [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
    assert_eq!(mat3_from_row_major(&mat3_to_row_major(&m)), m);
    let m6 = Matrix6::from_fn(|r, c| (r * 6 + c) as f64);
    let a = mat6_to_row_major(&m6);
    assert_eq!(a[1], 1.0);
    assert_eq!(a[6], 6.0);
    assert_eq!(mat6_from_row_major(&a), m6);
}

#[test]
fn names_are_nul_padded_and_truncated_on_char_boundaries() {
    assert_eq!(name_from32(&name32("consumer")), "consumer");
    let long = "ä".repeat(20); // 40 bytes
    let field = name32(&long);
    assert_eq!(name_from32(&field), "ä".repeat(16));
}

#[test]
fn bytes_round_trip_and_wrong_lengths_are_refused() {
    let p = PoseEstimate { position_m: [1.0, -2.0, 3.5], segment_id: 7, ..Default::default() };
    let b = p.as_bytes().to_vec();
    assert_eq!(b.len(), 352);
    assert_eq!(PoseEstimate::from_bytes(&b), Some(p));
    assert_eq!(PoseEstimate::from_bytes(&b[1..]), None);
}

proptest! {
    #[test]
    fn pose_estimate_round_trips_through_nalgebra(
        x in -1e3..1e3f64, y in -1e3..1e3f64, z in -1e3..1e3f64,
        ax in -1.0..1.0f64, ay in -1.0..1.0f64, az in -1.0..1.0f64, angle in -3.1..3.1f64,
        seg in 0u32..1000,
    ) {
        let axis = Vector3::new(ax, ay, az);
        prop_assume!(axis.norm() > 1e-3);
        let rot = UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle);
        let iso = Isometry3::from_parts(nalgebra::Translation3::new(x, y, z), rot);
        let cov = Matrix6::from_fn(|r, c| 1.0 / (1.0 + (r + c) as f64) + if r == c { 1.0 } else { 0.0 });
        let wire = PoseEstimate::from_nalgebra(&iso, &cov, seg, FRAME_LOCAL_MAP);
        let back = wire.frame_from_body();
        prop_assert!((back.translation.vector - iso.translation.vector).norm() < 1e-9);
        prop_assert!(back.rotation.angle_to(&iso.rotation) < 1e-9);
        prop_assert_eq!(wire.covariance_matrix(), cov);
        prop_assert_eq!(wire.segment_id, seg);
        // wire (x, y, z, w) against nalgebra's coords [i, j, k, w]
        prop_assert_eq!(wire.orientation_xyzw, [rot.coords[0], rot.coords[1], rot.coords[2], rot.coords[3]]);
        let particle = Particle::from_nalgebra(&iso, -1.5);
        prop_assert!(particle.map_from_body().rotation.angle_to(&rot) < 1e-9);
    }
}

#[test]
fn python_ctypes_module_matches_the_code() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../python/slam_pipeline_wire.py");
    let on_disk = std::fs::read_to_string(path).expect("python/slam_pipeline_wire.py exists");
    assert!(
        on_disk == wire_format_python(),
        "python/slam_pipeline_wire.py is out of date: cargo run -p shared_types --example wire_py > python/slam_pipeline_wire.py"
    );
}

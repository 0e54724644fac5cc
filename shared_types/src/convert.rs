//! Conversions between wire arrays and nalgebra (row-major on the wire, quaternion (x, y, z, w)).
//!
//! nalgebra stores matrices column-major and builds quaternions as `Quaternion::new(w, i, j, k)`
//! while `coords` is `[i, j, k, w]`; these helpers are the only place that knows it.

use nalgebra::{Isometry3, Matrix3, Matrix6, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::{Particle, PoseEstimate};

/// Row-major 3×3 array to a matrix.
pub fn mat3_from_row_major(a: &[f64; 9]) -> Matrix3<f64> {
    Matrix3::from_row_slice(a)
}

/// Matrix to a row-major 3×3 array.
pub fn mat3_to_row_major(m: &Matrix3<f64>) -> [f64; 9] {
    let mut out = [0.0; 9];
    for r in 0..3 {
        for c in 0..3 {
            out[r * 3 + c] = m[(r, c)];
        }
    }
    out
}

/// Row-major 6×6 array to a matrix.
pub fn mat6_from_row_major(a: &[f64; 36]) -> Matrix6<f64> {
    Matrix6::from_row_slice(a)
}

/// Matrix to a row-major 6×6 array.
pub fn mat6_to_row_major(m: &Matrix6<f64>) -> [f64; 36] {
    let mut out = [0.0; 36];
    for r in 0..6 {
        for c in 0..6 {
            out[r * 6 + c] = m[(r, c)];
        }
    }
    out
}

/// Wire quaternion (x, y, z, w) to a unit quaternion (normalised).
pub fn quat_from_xyzw(q: &[f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[3], q[0], q[1], q[2]))
}

/// Unit quaternion to the wire order (x, y, z, w).
pub fn quat_to_xyzw(q: &UnitQuaternion<f64>) -> [f64; 4] {
    [q.i, q.j, q.k, q.w]
}

/// Position and wire quaternion to `frame_from_body`.
pub fn isometry_from_wire(position_m: &[f64; 3], orientation_xyzw: &[f64; 4]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(position_m[0], position_m[1], position_m[2]),
        quat_from_xyzw(orientation_xyzw),
    )
}

/// `frame_from_body` to position and wire quaternion.
pub fn isometry_to_wire(iso: &Isometry3<f64>) -> ([f64; 3], [f64; 4]) {
    let t = iso.translation.vector;
    ([t.x, t.y, t.z], quat_to_xyzw(&iso.rotation))
}

impl PoseEstimate {
    /// Builds a pose estimate from `frame_from_body`, its 6×6 covariance, segment and frame.
    pub fn from_nalgebra(
        frame_from_body: &Isometry3<f64>,
        covariance: &Matrix6<f64>,
        segment_id: u32,
        frame: u32,
    ) -> Self {
        let (position_m, orientation_xyzw) = isometry_to_wire(frame_from_body);
        Self { position_m, orientation_xyzw, covariance: mat6_to_row_major(covariance), segment_id, frame }
    }

    /// `frame_from_body` of this estimate.
    pub fn frame_from_body(&self) -> Isometry3<f64> {
        isometry_from_wire(&self.position_m, &self.orientation_xyzw)
    }

    /// The 6×6 covariance as a matrix.
    pub fn covariance_matrix(&self) -> Matrix6<f64> {
        mat6_from_row_major(&self.covariance)
    }

    /// Position as a vector, m.
    pub fn position(&self) -> Vector3<f64> {
        Vector3::from(self.position_m)
    }
}

impl Particle {
    /// Builds a particle from `map_from_body` and its log weight.
    pub fn from_nalgebra(map_from_body: &Isometry3<f64>, log_weight: f64) -> Self {
        let (position_m, orientation_xyzw) = isometry_to_wire(map_from_body);
        Self { position_m, orientation_xyzw, log_weight }
    }

    /// `map_from_body` of this particle.
    pub fn map_from_body(&self) -> Isometry3<f64> {
        isometry_from_wire(&self.position_m, &self.orientation_xyzw)
    }
}

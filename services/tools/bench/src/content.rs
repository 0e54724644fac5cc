//! What travels: the deterministic cloud content (the same for every transport), the checksum the
//! consumer computes over every point, and the socket baselines' framing.
//!
//! Socket framing (all integers little-endian `u64`):
//! - `socket-bincode`: `len`, then `len` bytes of bincode (serde, standard config) of
//!   [`BincodeCloud`]; `len == 0` ends the stream.
//! - `socket-raw`: a [`RawHeader`] of 4 × u64 (`points`, `seq`, `stamp_ns`, `publish_ns`), then
//!   `points × 12` bytes (`[f32; 3]` in native = little-endian order); `points == u64::MAX` ends it.

use serde::{Deserialize, Serialize};
use shared_types::CloudPoint;

/// Point `i` of cloud `seq`: the formula of `testkit::cloud_point` (a cheap, deterministic function
/// of frame and index, so every transport produces exactly the same bytes).
#[inline]
pub fn bench_xyz(seq: u64, i: usize) -> [f32; 3] {
    [(i % 1024) as f32 * 0.01, (i / 1024) as f32 * 0.01, (seq % 4096) as f32 + (i % 7) as f32]
}

/// [`bench_xyz`] as a wire [`CloudPoint`].
#[inline]
pub fn bench_point(seq: u64, i: usize) -> CloudPoint {
    let [x_m, y_m, z_m] = bench_xyz(seq, i);
    CloudPoint { x_m, y_m, z_m }
}

#[inline]
fn fold_xyz(acc: u32, [x, y, z]: [f32; 3]) -> u32 {
    acc.wrapping_add(x.to_bits() ^ y.to_bits().rotate_left(11) ^ z.to_bits().rotate_left(22))
}

/// Checksum over every point of a wire cloud (the consumer's "read every point").
pub fn checksum_points(points: &[CloudPoint]) -> u32 {
    points.iter().fold(0, |acc, p| fold_xyz(acc, [p.x_m, p.y_m, p.z_m]))
}

/// Checksum over every point of a baseline cloud; equal to [`checksum_points`] for equal points.
pub fn checksum_xyz(points: &[[f32; 3]]) -> u32 {
    points.iter().fold(0, |acc, p| fold_xyz(acc, *p))
}

/// Cheap content check of a received cloud: the size, and the first, middle and last point against
/// [`bench_xyz`] (the full content goes into the checksum).
pub fn spot_check(seq: u64, expected_len: usize, len: usize, point: impl Fn(usize) -> [f32; 3]) -> bool {
    len == expected_len && (len == 0 || [0, len / 2, len - 1].into_iter().all(|i| point(i) == bench_xyz(seq, i)))
}

/// The baseline's header: the fields of the wire `CloudHeader` (common `MsgHeader` + sensor pose).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct SocketCloudHeader {
    /// Measurement time, ns (CLOCK_MONOTONIC).
    pub stamp_ns: u64,
    /// Sequence number, from 0.
    pub seq: u64,
    /// Time the oldest input entered the pipeline, ns.
    pub origin_ns: u64,
    /// CLOCK_MONOTONIC right before serialisation started, ns.
    pub publish_ns: u64,
    /// Sensor origin in the world frame, m.
    pub sensor_origin_m: [f64; 3],
    /// world_from_sensor rotation (x, y, z, w).
    pub orientation_xyzw: [f64; 4],
    /// Frame of the points.
    pub frame: u32,
    /// Flags (as `CloudHeader::flags`).
    pub flags: u32,
}

/// A baseline cloud as the producer serialises it (borrowing its points).
#[derive(Debug, Serialize)]
pub struct BincodeCloudRef<'a> {
    /// Header.
    pub header: SocketCloudHeader,
    /// Points (x, y, z), m.
    pub points: &'a [[f32; 3]],
}

/// A baseline cloud as the consumer deserialises it (same encoding as [`BincodeCloudRef`]).
#[derive(Debug, Deserialize)]
pub struct BincodeCloud {
    /// Header.
    pub header: SocketCloudHeader,
    /// Points (x, y, z), m.
    pub points: Vec<[f32; 3]>,
}

/// The bincode configuration of the baseline.
pub fn bincode_config() -> bincode::config::Configuration {
    bincode::config::standard()
}

/// Header of a `socket-raw` frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RawHeader {
    /// Points that follow ([`RAW_END`] = end of stream).
    pub points: u64,
    /// Sequence number.
    pub seq: u64,
    /// Measurement time, ns.
    pub stamp_ns: u64,
    /// CLOCK_MONOTONIC right before the write started, ns.
    pub publish_ns: u64,
}

/// `RawHeader::points` value that ends the stream.
pub const RAW_END: u64 = u64::MAX;

impl RawHeader {
    /// Encoded size, bytes.
    pub const SIZE: usize = 32;

    /// Little-endian bytes.
    pub fn to_bytes(self) -> [u8; Self::SIZE] {
        let mut b = [0u8; Self::SIZE];
        for (chunk, v) in b.chunks_exact_mut(8).zip([self.points, self.seq, self.stamp_ns, self.publish_ns]) {
            chunk.copy_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// Decodes [`RawHeader::to_bytes`].
    pub fn from_bytes(b: &[u8; Self::SIZE]) -> Self {
        let f = |k: usize| u64::from_le_bytes(b[8 * k..8 * k + 8].try_into().expect("8-byte field"));
        Self { points: f(0), seq: f(1), stamp_ns: f(2), publish_ns: f(3) }
    }
}

/// The bytes of a slice of points, for the raw baseline (12 bytes per point, native order).
pub fn xyz_as_bytes(points: &[[f32; 3]]) -> &[u8] {
    // SAFETY: `[f32; 3]` is 12 bytes with no padding, so every byte of the slice is initialised;
    // u8 has alignment 1; the length is exactly the slice's size in bytes and the borrow is shared.
    unsafe { std::slice::from_raw_parts(points.as_ptr().cast::<u8>(), size_of_val(points)) }
}

/// The bytes of a mutable slice of points, for reading the raw baseline into it.
pub fn xyz_as_bytes_mut(points: &mut [[f32; 3]]) -> &mut [u8] {
    // SAFETY: as in `xyz_as_bytes`; in addition every bit pattern is a valid f32, so any bytes
    // written through the returned slice leave valid points; the borrow is exclusive.
    unsafe { std::slice::from_raw_parts_mut(points.as_mut_ptr().cast::<u8>(), size_of_val(points)) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_checksums_agree_on_the_same_points_and_see_a_changed_point() {
        let wire: Vec<_> = (0..5000).map(|i| bench_point(7, i)).collect();
        let mut xyz: Vec<_> = (0..5000).map(|i| bench_xyz(7, i)).collect();
        assert_eq!(checksum_points(&wire), checksum_xyz(&xyz));
        xyz[1234][1] += 1.0;
        assert_ne!(checksum_points(&wire), checksum_xyz(&xyz));
    }

    #[test]
    fn spot_check_catches_a_wrong_size_or_frame() {
        assert!(spot_check(3, 100, 100, |i| bench_xyz(3, i)));
        assert!(!spot_check(3, 100, 99, |i| bench_xyz(3, i)));
        assert!(!spot_check(3, 100, 100, |i| bench_xyz(4, i)));
    }

    #[test]
    fn bincode_ref_and_owned_clouds_share_one_encoding() {
        let points: Vec<_> = (0..100).map(|i| bench_xyz(1, i)).collect();
        let header = SocketCloudHeader { seq: 1, publish_ns: 5, ..Default::default() };
        let bytes =
            bincode::serde::encode_to_vec(BincodeCloudRef { header, points: &points }, bincode_config()).unwrap();
        let (back, used): (BincodeCloud, usize) = bincode::serde::decode_from_slice(&bytes, bincode_config()).unwrap();
        assert_eq!(used, bytes.len());
        assert_eq!(back.header, header);
        assert_eq!(back.points, points);
    }

    #[test]
    fn raw_header_and_point_bytes_round_trip() {
        let h = RawHeader { points: 3, seq: 9, stamp_ns: 11, publish_ns: 13 };
        assert_eq!(RawHeader::from_bytes(&h.to_bytes()), h);
        let points = [bench_xyz(2, 0), bench_xyz(2, 1), bench_xyz(2, 2)];
        let mut back = [[0.0f32; 3]; 3];
        xyz_as_bytes_mut(&mut back).copy_from_slice(xyz_as_bytes(&points));
        assert_eq!(back, points);
        assert_eq!(xyz_as_bytes(&points).len(), 36);
    }
}

//! Readers for the OctoMap benchmark files (`shared/bench/octomap`): `scans.bin` (the point
//! clouds) and `occupied_voxels_res*.bin` (OctoMap's occupied finest-level voxels).

use std::path::Path;

use crate::OcTreeKey;

/// Errors of the benchmark-file readers.
#[derive(Debug, thiserror::Error)]
pub enum BenchDataError {
    /// The file does not start with the expected magic bytes.
    #[error("bad magic {found:?}, expected {expected:?}")]
    BadMagic {
        /// What the file starts with.
        found: Vec<u8>,
        /// The expected magic.
        expected: &'static [u8],
    },
    /// The file ends before the structure it announces.
    #[error("truncated: need {needed} bytes at offset {offset} for {what}, file has {len}")]
    Truncated {
        /// What was being read.
        what: String,
        /// Offset of the read.
        offset: usize,
        /// Bytes needed.
        needed: usize,
        /// File length.
        len: usize,
    },
    /// Bytes remain after the announced content.
    #[error("{0} trailing bytes after the announced content")]
    TrailingBytes(usize),
    /// An I/O error.
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
}

/// Magic of `scans.bin`.
pub const SCANS_MAGIC: &[u8; 8] = b"OCTSCAN1";

/// One frame of `scans.bin`: sensor origin and world-frame points.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanFrame {
    /// Sensor origin (world frame, m).
    pub origin: [f32; 3],
    /// Points (world frame, m).
    pub points: Vec<[f32; 3]>,
}

/// Contents of `scans.bin`.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanFile {
    /// Maximum range the data was generated for (m).
    pub max_range: f32,
    /// The frames.
    pub frames: Vec<ScanFrame>,
}

impl ScanFile {
    /// Total number of points.
    pub fn num_points(&self) -> usize {
        self.frames.iter().map(|f| f.points.len()).sum()
    }
}

/// One entry of `occupied_voxels_res*.bin`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OccupiedVoxel {
    /// Finest-level key.
    pub key: OcTreeKey,
    /// Log-odds of the leaf containing it.
    pub log_odds: f32,
}

struct Cursor<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize, what: impl FnOnce() -> String) -> Result<&'a [u8], BenchDataError> {
        match self.pos.checked_add(n).filter(|&e| e <= self.b.len()) {
            Some(end) => {
                let s = &self.b[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(BenchDataError::Truncated { what: what(), offset: self.pos, needed: n, len: self.b.len() }),
        }
    }
    fn u32(&mut self, what: &str) -> Result<u32, BenchDataError> {
        let s = self.take(4, || what.to_string())?;
        Ok(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
    }
    fn f32(&mut self, what: &str) -> Result<f32, BenchDataError> {
        Ok(f32::from_bits(self.u32(what)?))
    }
}

fn f32_at(s: &[u8], i: usize) -> f32 {
    f32::from_le_bytes([s[4 * i], s[4 * i + 1], s[4 * i + 2], s[4 * i + 3]])
}

/// Parses `scans.bin` bytes: magic "OCTSCAN1", u32 frames, f32 max range, then per frame
/// f32 x3 origin, u32 n, n x f32 x3 points (little-endian).
pub fn parse_scans(bytes: &[u8]) -> Result<ScanFile, BenchDataError> {
    let mut c = Cursor { b: bytes, pos: 0 };
    let magic = c.take(8, || "magic".into())?;
    if magic != SCANS_MAGIC {
        return Err(BenchDataError::BadMagic { found: magic.to_vec(), expected: SCANS_MAGIC });
    }
    let n_frames = c.u32("frame count")?;
    let max_range = c.f32("max range")?;
    let mut frames = Vec::with_capacity((n_frames as usize).min(1 << 16));
    for f in 0..n_frames {
        let o = c.take(12, || format!("origin of frame {f}"))?;
        let origin = [f32_at(o, 0), f32_at(o, 1), f32_at(o, 2)];
        let n = c.u32(&format!("point count of frame {f}"))? as usize;
        let raw = c.take(n.saturating_mul(12), || format!("{n} points of frame {f}"))?;
        let points = raw.chunks_exact(12).map(|p| [f32_at(p, 0), f32_at(p, 1), f32_at(p, 2)]).collect();
        frames.push(ScanFrame { origin, points });
    }
    if c.pos != bytes.len() {
        return Err(BenchDataError::TrailingBytes(bytes.len() - c.pos));
    }
    Ok(ScanFile { max_range, frames })
}

/// Reads `scans.bin` (see [`parse_scans`]).
pub fn read_scans(path: impl AsRef<Path>) -> Result<ScanFile, BenchDataError> {
    parse_scans(&std::fs::read(path)?)
}

/// Parses `occupied_voxels_res*.bin`: u32 count, then count x (u16 kx, ky, kz, f32 log-odds).
pub fn parse_occupied_voxels(bytes: &[u8]) -> Result<Vec<OccupiedVoxel>, BenchDataError> {
    let mut c = Cursor { b: bytes, pos: 0 };
    let n = c.u32("voxel count")? as usize;
    let raw = c.take(n.saturating_mul(10), || format!("{n} voxels"))?;
    if c.pos != bytes.len() {
        return Err(BenchDataError::TrailingBytes(bytes.len() - c.pos));
    }
    Ok(raw
        .chunks_exact(10)
        .map(|v| OccupiedVoxel {
            key: OcTreeKey([
                u16::from_le_bytes([v[0], v[1]]),
                u16::from_le_bytes([v[2], v[3]]),
                u16::from_le_bytes([v[4], v[5]]),
            ]),
            log_odds: f32::from_le_bytes([v[6], v[7], v[8], v[9]]),
        })
        .collect())
}

/// Reads `occupied_voxels_res*.bin` (see [`parse_occupied_voxels`]).
pub fn read_occupied_voxels(path: impl AsRef<Path>) -> Result<Vec<OccupiedVoxel>, BenchDataError> {
    parse_occupied_voxels(&std::fs::read(path)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Vec<u8> {
        let mut b = SCANS_MAGIC.to_vec();
        b.extend(2u32.to_le_bytes());
        b.extend(6.0f32.to_le_bytes());
        for (f, n) in [(0u32, 2u32), (1, 1)] {
            for v in [f as f32, 0.5, 1.5] {
                b.extend(v.to_le_bytes());
            }
            b.extend(n.to_le_bytes());
            for i in 0..n * 3 {
                b.extend((i as f32 * 0.25).to_le_bytes());
            }
        }
        b
    }

    #[test]
    fn parses_scans() {
        let s = parse_scans(&sample()).unwrap();
        assert_eq!(s.max_range, 6.0);
        assert_eq!(s.frames.len(), 2);
        assert_eq!(s.frames[1].origin, [1.0, 0.5, 1.5]);
        assert_eq!(s.frames[0].points, vec![[0.0, 0.25, 0.5], [0.75, 1.0, 1.25]]);
        assert_eq!(s.num_points(), 3);
    }

    #[test]
    fn scan_errors() {
        let mut b = sample();
        b[0] = b'X';
        assert!(matches!(parse_scans(&b), Err(BenchDataError::BadMagic { .. })));
        let b = sample();
        for cut in [0, 7, 12, 20, b.len() - 1] {
            assert!(matches!(parse_scans(&b[..cut]), Err(BenchDataError::Truncated { .. })), "cut {cut}");
        }
        let mut b = sample();
        b.push(0);
        assert!(matches!(parse_scans(&b), Err(BenchDataError::TrailingBytes(1))));
        // A huge announced point count must fail cleanly, not allocate.
        let mut b = sample();
        b[28..32].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(parse_scans(&b), Err(BenchDataError::Truncated { .. })));
    }

    #[test]
    fn parses_voxels() {
        let mut b = 2u32.to_le_bytes().to_vec();
        for (k, l) in [([1u16, 2, 3], 3.5f32), ([40000, 5, 6], 0.85)] {
            for v in k {
                b.extend(v.to_le_bytes());
            }
            b.extend(l.to_le_bytes());
        }
        let v = parse_occupied_voxels(&b).unwrap();
        assert_eq!(v[1], OccupiedVoxel { key: OcTreeKey([40000, 5, 6]), log_odds: 0.85 });
        assert!(matches!(parse_occupied_voxels(&b[..b.len() - 1]), Err(BenchDataError::Truncated { .. })));
        assert!(matches!(parse_occupied_voxels(&[1, 0]), Err(BenchDataError::Truncated { .. })));
    }
}

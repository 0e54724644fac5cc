//! Voxel keys and their conversion to and from metric coordinates (OctoMap convention).

/// Depth of the tree: 16 levels below the root, so keys are 16-bit per axis.
pub const TREE_DEPTH: u32 = 16;
/// Key of the voxel whose lower corner is the coordinate origin (2^15).
pub const TREE_MAX_VAL: u32 = 32768;

/// Discrete address of a finest-level voxel: `k = floor(coord * (1 / res)) + 32768` per axis.
///
/// The voxel with key `k` spans `[(k - 32768) * res, (k - 32767) * res)` and has its centre at
/// `(k - 32768 + 0.5) * res`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct OcTreeKey(pub [u16; 3]);

impl OcTreeKey {
    /// Packs the key into the low 48 bits of a `u64` (x | y << 16 | z << 32).
    #[inline]
    pub fn pack(self) -> u64 {
        self.0[0] as u64 | (self.0[1] as u64) << 16 | (self.0[2] as u64) << 32
    }

    /// Inverse of [`OcTreeKey::pack`] (bits above 48 are ignored).
    #[inline]
    pub fn unpack(v: u64) -> Self {
        OcTreeKey([v as u16, (v >> 16) as u16, (v >> 32) as u16])
    }

    /// Morton (Z-order) code: bit `3b` is bit `b` of x, `3b + 1` of y, `3b + 2` of z. Sorting by
    /// it gives the tree's depth-first child order (child index = x + 2y + 4z at every level).
    #[inline]
    pub fn morton(self) -> u64 {
        spread3(self.0[0]) | spread3(self.0[1]) << 1 | spread3(self.0[2]) << 2
    }

    /// Inverse of [`OcTreeKey::morton`].
    #[inline]
    pub fn from_morton(m: u64) -> Self {
        OcTreeKey([compact3(m), compact3(m >> 1), compact3(m >> 2)])
    }

    /// Index (0..8) of the child at tree depth `depth` (0 = root's children) containing this key:
    /// x bit + 2 * y bit + 4 * z bit of key bit `15 - depth`.
    #[inline]
    pub fn child_index(self, depth: u32) -> usize {
        let b = TREE_DEPTH - 1 - depth;
        (((self.0[0] >> b) & 1) | ((self.0[1] >> b) & 1) << 1 | ((self.0[2] >> b) & 1) << 2) as usize
    }
}

#[inline]
fn spread3(v: u16) -> u64 {
    let mut y = v as u64;
    y = (y | y << 32) & 0x001F_0000_0000_FFFF;
    y = (y | y << 16) & 0x001F_0000_FF00_00FF;
    y = (y | y << 8) & 0x100F_00F0_0F00_F00F;
    y = (y | y << 4) & 0x10C3_0C30_C30C_30C3;
    y = (y | y << 2) & 0x1249_2492_4924_9249;
    y
}

#[inline]
fn compact3(m: u64) -> u16 {
    let mut x = m & 0x1249_2492_4924_9249;
    x = (x | x >> 2) & 0x10C3_0C30_C30C_30C3;
    x = (x | x >> 4) & 0x100F_00F0_0F00_F00F;
    x = (x | x >> 8) & 0x001F_0000_FF00_00FF;
    x = (x | x >> 16) & 0x001F_0000_0000_FFFF;
    x = (x | x >> 32) & 0xFFFF;
    x as u16
}

/// `coordToKeyChecked`: `floor(coord * res_factor) + 32768` in double precision, `None` when
/// outside `[0, 65536)` or not finite.
#[inline]
pub(crate) fn coord_to_key_checked(coord: f64, res_factor: f64) -> Option<u16> {
    let s = (res_factor * coord).floor();
    // Range check in f64 first: the float-to-int cast of a huge or NaN value would saturate.
    if !(s >= -(TREE_MAX_VAL as f64) && s < TREE_MAX_VAL as f64) {
        return None;
    }
    Some((s as i32 + TREE_MAX_VAL as i32) as u16)
}

/// `keyToCoord`: centre coordinate of a key along one axis.
#[inline]
pub(crate) fn key_to_coord(key: u16, resolution: f64) -> f64 {
    ((key as i32 - TREE_MAX_VAL as i32) as f64 + 0.5) * resolution
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_round_trip_and_child_order() {
        for &k in &[[0u16, 0, 0], [1, 2, 3], [65535, 0, 32768], [12345, 54321, 777], [65535, 65535, 65535]] {
            let key = OcTreeKey(k);
            assert_eq!(OcTreeKey::from_morton(key.morton()), key);
            assert_eq!(OcTreeKey::unpack(key.pack()), key);
            for d in 0..16 {
                assert_eq!(((key.morton() >> (3 * (15 - d))) & 7) as usize, key.child_index(d));
            }
        }
    }

    #[test]
    fn coord_key_convention() {
        let f = 1.0 / 0.1;
        assert_eq!(coord_to_key_checked(0.0, f), Some(32768));
        assert_eq!(coord_to_key_checked(-0.0001, f), Some(32767));
        assert_eq!(coord_to_key_checked(0.25, f), Some(32770));
        assert_eq!(coord_to_key_checked(1e9, f), None);
        assert_eq!(coord_to_key_checked(f64::NAN, f), None);
        assert_eq!(coord_to_key_checked(-3276.8, f), Some(0));
        assert!((key_to_coord(32770, 0.1) - 0.25).abs() < 1e-12);
    }
}

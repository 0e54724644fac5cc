//! The consumer's side of `pipeline/map/voxels`: after a full set ([`VOXELS_FULL`]), each message
//! carries only the voxels that changed ([`VOXELS_DELTA`]; one no longer occupied has class
//! [`VOXEL_CLASS_REMOVED`]). [`apply`] keeps a consumer's copy of the map (the octree mapper's
//! `voxels` module is the sender's side).

use std::collections::HashMap;

use crate::{VOXEL_CLASS_REMOVED, VOXELS_FULL, Voxel};

/// A voxel's identity: its cell at its own size (centre / size, floored) and the size's bits.
pub type VoxelKey = (i32, i32, i32, u32);

/// The key of `v`.
pub fn key(v: &Voxel) -> VoxelKey {
    let s = v.size_m;
    let cell = |c: f32| (c / s).floor() as i32;
    (cell(v.center_m[0]), cell(v.center_m[1]), cell(v.center_m[2]), s.to_bits())
}

/// Applies one message (`kind` = `VoxelSetHeader::kind`) to the voxels a consumer holds. Returns
/// false for a delta with no full set before it (`map` is then left empty: wait for the next
/// full set, or ask for one with `COMMAND_VOXEL_SNAPSHOT`).
pub fn apply(map: &mut HashMap<VoxelKey, Voxel>, have_full: &mut bool, kind: u32, voxels: &[Voxel]) -> bool {
    if kind == VOXELS_FULL {
        map.clear();
        *have_full = true;
    } else if !*have_full {
        return false;
    }
    for v in voxels {
        if v.class == VOXEL_CLASS_REMOVED {
            map.remove(&key(v));
        } else {
            map.insert(key(v), *v);
        }
    }
    true
}

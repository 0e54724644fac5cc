//! Ray traversal (OctoMap's `computeRayKeys`) and the per-scan free/occupied key computation
//! (OctoMap's `computeUpdate`), reproducing its mixed float/double arithmetic.

use crate::key::{OcTreeKey, coord_to_key_checked, key_to_coord};
use crate::keyset::KeySet;

/// Upper bound on DDA steps of one ray (a ray crosses at most 3 * 65536 voxel borders); only
/// reached for degenerate float input, where OctoMap itself could loop for a long time.
const MAX_STEPS: usize = 3 * 65536;

/// Keys of one point (each component through `coordToKeyChecked`), `None` when out of the tree.
#[inline]
pub(crate) fn point_key(p: [f32; 3], res_factor: f64) -> Option<OcTreeKey> {
    Some(OcTreeKey([
        coord_to_key_checked(p[0] as f64, res_factor)?,
        coord_to_key_checked(p[1] as f64, res_factor)?,
        coord_to_key_checked(p[2] as f64, res_factor)?,
    ]))
}

/// OctoMap's `Vector3::norm()`: squared length summed in `f32`, square root in `f64`.
#[inline]
pub(crate) fn norm_f32(v: [f32; 3]) -> f64 {
    ((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) as f64).sqrt()
}

/// Voxels traversed by the ray `origin -> end` (OctoMap 1.9.7 `computeRayKeys`): a 3-D DDA
/// (Amanatides & Woo) that calls `visit` for the origin voxel and every voxel entered after it,
/// excluding the end-point voxel; it also stops once the distance travelled to the far border
/// of the current voxel exceeds the ray length. Nothing is visited when origin and end share a
/// voxel. Returns false (and visits nothing) when origin or end lies outside the tree.
pub fn compute_ray_keys(origin: [f32; 3], end: [f32; 3], resolution: f64, mut visit: impl FnMut(OcTreeKey)) -> bool {
    ray_keys_packed(origin, end, resolution, |k| visit(OcTreeKey::unpack(k)))
}

/// Adds `step` (±1, wrapping like OctoMap's `unsigned short`) to the 16-bit key field at `shift`
/// of a packed key ([`OcTreeKey::pack`]).
#[inline(always)]
fn step_field(packed: u64, shift: u32, step: u16) -> u64 {
    let f = ((packed >> shift) as u16).wrapping_add(step);
    (packed & !(0xFFFF_u64 << shift)) | (f as u64) << shift
}

/// [`compute_ray_keys`] on packed keys, the key and the three crossing distances in registers
/// (stepping a key held as an array by a run-time axis index kept it in memory, and reading it
/// back whole after a 16-bit store stalled on store forwarding: a quarter of the ray time).
/// The same arithmetic in the same order, so the same voxels.
#[inline]
pub(crate) fn ray_keys_packed(origin: [f32; 3], end: [f32; 3], resolution: f64, mut visit: impl FnMut(u64)) -> bool {
    let res_factor = 1.0 / resolution;
    let (Some(key_origin), Some(key_end)) = (point_key(origin, res_factor), point_key(end, res_factor)) else {
        return false;
    };
    if key_origin == key_end {
        return true;
    }
    let mut current = key_origin.pack();
    let end_packed = key_end.pack();
    visit(current);

    let mut dir = [end[0] - origin[0], end[1] - origin[1], end[2] - origin[2]];
    let length = norm_f32(dir) as f32;
    for d in &mut dir {
        *d /= length;
    }

    let mut step = [0i32; 3];
    let mut t_max = [f64::MAX; 3];
    let mut t_delta = [f64::MAX; 3];
    for i in 0..3 {
        step[i] = if dir[i] > 0.0 {
            1
        } else if dir[i] < 0.0 {
            -1
        } else {
            0
        };
        if step[i] != 0 {
            let mut border = key_to_coord(key_origin.0[i], resolution);
            border += (step[i] as f64 * resolution * 0.5) as f32 as f64;
            t_max[i] = (border - origin[i] as f64) / dir[i] as f64;
            t_delta[i] = resolution / dir[i].abs() as f64;
        }
    }

    let length = length as f64;
    let [mut t0, mut t1, mut t2] = t_max;
    let [d0, d1, d2] = t_delta;
    let [s0, s1, s2] = step.map(|s| s as u16);
    for _ in 0..MAX_STEPS {
        if t0 < t1 {
            if t0 < t2 {
                current = step_field(current, 0, s0);
                t0 += d0;
            } else {
                current = step_field(current, 32, s2);
                t2 += d2;
            }
        } else if t1 < t2 {
            current = step_field(current, 16, s1);
            t1 += d1;
        } else {
            current = step_field(current, 32, s2);
            t2 += d2;
        }
        if current == end_packed {
            break;
        }
        let dist = t0.min(t1).min(t2);
        if dist > length {
            break;
        }
        visit(current);
    }
    true
}

/// End point of a ray truncated at `max_range` (OctoMap: `origin + (p - origin).normalized() *
/// (float) maxrange`, all in `f32`).
#[inline]
pub(crate) fn truncated_end(origin: [f32; 3], p: [f32; 3], max_range: f64) -> [f32; 3] {
    let mut d = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
    let len = norm_f32(d);
    if len > 0.0 {
        let l = len as f32;
        for c in &mut d {
            *c /= l;
        }
    }
    let r = max_range as f32;
    [origin[0] + d[0] * r, origin[1] + d[1] * r, origin[2] + d[2] * r]
}

/// Per-thread scratch of the ray casting phase.
#[derive(Debug, Default, Clone)]
pub(crate) struct RayScratch {
    pub(crate) free: KeySet,
    pub(crate) occupied: KeySet,
    /// Sorted `(morton << 1) | is_hit` codes of this thread's keys.
    pub(crate) codes: Vec<u64>,
    pub(crate) skipped: usize,
}

impl RayScratch {
    pub(crate) fn clear(&mut self) {
        self.free.clear();
        self.occupied.clear();
        self.codes.clear();
        self.skipped = 0;
    }

    /// Casts one measurement (OctoMap `computeUpdate` without bounding box).
    #[inline]
    pub(crate) fn cast(&mut self, origin: [f32; 3], p: [f32; 3], max_range: f64, resolution: f64, res_factor: f64) {
        if !(p[0].is_finite() && p[1].is_finite() && p[2].is_finite()) {
            self.skipped += 1;
            return;
        }
        let d = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
        let free = &mut self.free;
        if max_range < 0.0 || norm_f32(d) <= max_range {
            ray_keys_packed(origin, p, resolution, |k| {
                free.insert(k);
            });
            match point_key(p, res_factor) {
                Some(k) => {
                    self.occupied.insert(k.pack());
                }
                None => self.skipped += 1,
            }
        } else {
            let end = truncated_end(origin, p, max_range);
            ray_keys_packed(origin, end, resolution, |k| {
                free.insert(k);
            });
        }
    }

    /// Fills `codes` with this thread's keys as sorted `(morton << 1) | hit` codes.
    pub(crate) fn finish(&mut self) {
        self.codes.clear();
        self.codes.reserve(self.free.len() + self.occupied.len());
        self.codes.extend(self.free.iter().map(|k| OcTreeKey::unpack(k).morton() << 1));
        self.codes.extend(self.occupied.iter().map(|k| OcTreeKey::unpack(k).morton() << 1 | 1));
        radix_sort(&mut self.codes);
    }
}

/// LSD radix sort (8-bit digits, as many passes as the largest value needs).
pub(crate) fn radix_sort(v: &mut Vec<u64>) {
    if v.len() < 4096 {
        v.sort_unstable();
        return;
    }
    let mut buf = vec![0u64; v.len()];
    let max = v.iter().copied().max().unwrap_or(0);
    let bits = 64 - max.leading_zeros();
    let passes = bits.div_ceil(8);
    let mut src: &mut Vec<u64> = v;
    let mut dst: &mut Vec<u64> = &mut buf;
    for pass in 0..passes {
        let shift = pass * 8;
        let mut count = [0usize; 256];
        for &x in src.iter() {
            count[((x >> shift) & 0xFF) as usize] += 1;
        }
        let mut sum = 0;
        for c in count.iter_mut() {
            let t = *c;
            *c = sum;
            sum += t;
        }
        for &x in src.iter() {
            let b = ((x >> shift) & 0xFF) as usize;
            dst[count[b]] = x;
            count[b] += 1;
        }
        std::mem::swap(&mut src, &mut dst);
    }
    if passes % 2 == 1 {
        // The sorted data ended in `buf`.
        std::mem::swap(v, &mut buf);
    }
}

/// Merges sorted code lists into `out`, one entry per key: the hit flag wins over free.
pub(crate) fn merge_codes(lists: &[&[u64]], out: &mut Vec<u64>) {
    out.clear();
    let mut tmp: Vec<u64>;
    let merged: &[u64] = match lists.len() {
        0 => return,
        1 => lists[0],
        _ => {
            tmp = lists[0].to_vec();
            for l in &lists[1..] {
                tmp = merge2(&tmp, l);
            }
            &tmp
        }
    };
    out.reserve(merged.len());
    for &c in merged {
        match out.last_mut() {
            Some(last) if *last >> 1 == c >> 1 => *last |= c & 1,
            _ => out.push(c),
        }
    }
}

fn merge2(a: &[u64], b: &[u64]) -> Vec<u64> {
    let mut out = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i] <= b[j] {
            out.push(a[i]);
            i += 1;
        } else {
            out.push(b[j]);
            j += 1;
        }
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radix_matches_sort() {
        let mut x = 1u64;
        let mut v: Vec<u64> = (0..10000)
            .map(|_| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
                x >> 15
            })
            .collect();
        let mut w = v.clone();
        w.sort_unstable();
        radix_sort(&mut v);
        assert_eq!(v, w);
    }

    #[test]
    fn merge_dedups_with_hit_priority() {
        let a = [2u64 << 1, 5 << 1 | 1, 7 << 1];
        let b = [2u64 << 1 | 1, 5 << 1, 9 << 1];
        let mut out = Vec::new();
        merge_codes(&[&a, &b], &mut out);
        assert_eq!(out, vec![2 << 1 | 1, 5 << 1 | 1, 7 << 1, 9 << 1]);
    }
}

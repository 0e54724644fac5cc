//! Voxel deltas on `pipeline/map/voxels`: after a full set, each message carries only the voxels
//! that changed since the previous one (new, or a changed occupancy or class; one no longer
//! occupied with class [`VOXEL_CLASS_REMOVED`]), with a full set again every
//! `voxels_full_interval_s` and when a [`shared_types::COMMAND_VOXEL_SNAPSHOT`] asks for one. A
//! viewer then follows the map at the voxel rate with a stream that grows with what changes, not
//! with the map. [`apply`] (in `shared_types::voxel_stream`) is what a consumer does with a message.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use shared_types::{VOXEL_CLASS_REMOVED, VOXELS_DELTA, VOXELS_FULL, Voxel};

use crate::{MapperError, MapperState};

pub use shared_types::voxel_stream::{VoxelKey, apply, key};

/// What the voxel stream has sent, in messages and bytes (payload), per kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct VoxelStreamCounters {
    /// Full sets sent.
    pub full_messages: u64,
    /// Deltas sent.
    pub delta_messages: u64,
    /// Payload bytes of the full sets.
    pub full_bytes: u64,
    /// Payload bytes of the deltas.
    pub delta_bytes: u64,
    /// Voxels sent as removed.
    pub removed: u64,
    /// Full sets sent because a command asked for one.
    pub snapshots_requested: u64,
    /// Payload bytes had every message been a full set (the stream before deltas).
    pub full_only_bytes: u64,
    /// Messages for which the whole map was read (full sets; changes anywhere).
    pub whole_map_reads: u64,
    /// Changed regions read instead, and the voxels in them.
    pub regions_read: u64,
    /// Voxels read in the changed regions.
    pub region_voxels_read: u64,
    /// Time spent making the messages (reading the map, comparing), s.
    pub build_s: f64,
    /// From the first message to the last, s (the stream's rate is bytes over this).
    pub span_s: f64,
}

/// The octree's change tracking works in cubes of this depth (32 voxels' edge, 3.2 m at 0.1 m):
/// a voxel delta re-reads only the cubes the scans since the last message changed.
pub const VOXEL_REGION_DEPTH: u8 = 11;

/// The map's occupied voxels in wire form, each classified by `classes` (navigable, obstacle,
/// wall) or all plain occupied.
pub fn all_voxels(st: &MapperState, classes: Option<&navigable::Discovery>) -> Vec<Voxel> {
    navigable::occupied_voxels(&st.tree, &st.points, classes).into_iter().map(wire_voxel).collect()
}

/// The occupied voxels of one region of the octree ([`VOXEL_REGION_DEPTH`]), unclassified.
pub fn region_voxels(st: &MapperState, region: [u16; 3]) -> Vec<Voxel> {
    navigable::occupied_voxels_in_region(&st.tree, &st.points, VOXEL_REGION_DEPTH, region)
        .into_iter()
        .map(wire_voxel)
        .collect()
}

fn wire_voxel(v: navigable::MapVoxel) -> Voxel {
    Voxel {
        center_m: v.center_m.map(|x| x as f32),
        size_m: v.size_m as f32,
        occupancy: v.occupancy as f32,
        class: match v.class {
            navigable::MapVoxelClass::Occupied => 0,
            navigable::MapVoxelClass::Navigable => 1,
            navigable::MapVoxelClass::Obstacle => 2,
            navigable::MapVoxelClass::Wall => 3,
        },
    }
}

/// The next `pipeline/map/voxels` message for the mapper's map: `classified` is the end of the
/// run's full set (with classes); otherwise the octree's changes since the last message decide
/// what is read (everything when the tree does not track changes yet, as after a restored
/// checkpoint or a rebuild: it starts to).
pub fn next_message(
    stream: &mut VoxelStream,
    st: &mut MapperState,
    classified: Option<Vec<Voxel>>,
    now: Instant,
) -> Result<(u32, Vec<Voxel>), MapperError> {
    let force_full = classified.is_some();
    let changes = st.tree.take_changes();
    if changes.is_none() {
        st.tree.track_changes(VOXEL_REGION_DEPTH)?;
        st.tree.take_changes(); // "everything changed": this message reads everything anyway
    }
    let changed = changes.as_ref().filter(|c| !c.all).map(|c| c.regions.as_slice());
    let st = &*st;
    Ok(stream.next(
        now,
        force_full,
        changed,
        || classified.unwrap_or_else(|| all_voxels(st, None)),
        |r| region_voxels(st, r),
    ))
}

/// How the map is cut into regions: the octree's cubes at `depth` (edge `2^(16 - depth)` voxels
/// of `resolution_m`), the unit in which [`octree::OcTree::take_changes`] reports changes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegionGrid {
    /// Voxel edge, m.
    pub resolution_m: f64,
    /// Tree depth of a region (1..=16).
    pub depth: u8,
}

/// A region's index per axis (`octree key >> (16 - depth)`); `None`: a voxel larger than a region.
type Region = Option<[u16; 3]>;

impl RegionGrid {
    /// The region holding voxel `v` (`None` for one larger than a region).
    pub fn region_of(&self, v: &Voxel) -> Region {
        let shift = 16 - self.depth as u32;
        if f64::from(v.size_m) > self.resolution_m * (1u32 << shift) as f64 * 1.001 {
            return None;
        }
        let key = |c: f32| ((f64::from(c) / self.resolution_m).floor() as i64 + 32768).clamp(0, 65535) as u16;
        Some(v.center_m.map(|c| key(c) >> shift))
    }
}

/// The sender's side: what subscribers were last told (by region), and when the last full set
/// went out.
#[derive(Debug)]
pub struct VoxelStream {
    grid: RegionGrid,
    sent: HashMap<Region, HashMap<VoxelKey, (u32, u32)>>,
    sent_voxels: usize,
    /// A full set at least this often; `None`: every message is a full set.
    full_every: Option<Duration>,
    last_full: Option<Instant>,
    snapshot_requested: bool,
    first: Option<Instant>,
    /// What was sent.
    pub counters: VoxelStreamCounters,
}

impl VoxelStream {
    /// A stream over `grid`'s regions sending a full set at least every `full_every` (`None`:
    /// always full sets).
    pub fn new(grid: RegionGrid, full_every: Option<Duration>) -> Self {
        Self {
            grid,
            sent: HashMap::new(),
            sent_voxels: 0,
            full_every,
            last_full: None,
            snapshot_requested: false,
            first: None,
            counters: VoxelStreamCounters::default(),
        }
    }

    /// The next message sends a full set (a [`shared_types::COMMAND_VOXEL_SNAPSHOT`]).
    pub fn request_snapshot(&mut self) {
        self.snapshot_requested = true;
    }

    /// Voxels subscribers hold now.
    pub fn held(&self) -> usize {
        self.sent_voxels
    }

    /// The next message: `(kind, payload)`. `changed`: the regions whose occupied voxels may have
    /// changed since the previous message (`None`: anywhere); `everything` gives the map's
    /// occupied voxels, `region` those of one region (none larger than it). Only the changed
    /// regions are read unless a full set is due (`force_full`, the interval, a snapshot asked
    /// for, the first message) or `changed` is `None`; a delta then carries the voxels that
    /// differ from what was sent, and those gone as [`VOXEL_CLASS_REMOVED`].
    pub fn next(
        &mut self,
        now: Instant,
        force_full: bool,
        changed: Option<&[[u16; 3]]>,
        everything: impl FnOnce() -> Vec<Voxel>,
        mut region: impl FnMut([u16; 3]) -> Vec<Voxel>,
    ) -> (u32, Vec<Voxel>) {
        let started = Instant::now();
        let first = *self.first.get_or_insert(now);
        self.counters.span_s = now.duration_since(first).as_secs_f64();
        let r = self.make(now, force_full, changed, everything, &mut region);
        self.counters.build_s += started.elapsed().as_secs_f64();
        r
    }

    fn make(
        &mut self,
        now: Instant,
        force_full: bool,
        changed: Option<&[[u16; 3]]>,
        everything: impl FnOnce() -> Vec<Voxel>,
        region: &mut impl FnMut([u16; 3]) -> Vec<Voxel>,
    ) -> (u32, Vec<Voxel>) {
        let due = match (self.full_every, self.last_full) {
            (None, _) | (_, None) => true,
            (Some(every), Some(last)) => now.duration_since(last) >= every,
        };
        let full = force_full || due || self.snapshot_requested;
        let bytes = |n: usize| (n * std::mem::size_of::<Voxel>()) as u64;
        let (delta, total) = match changed {
            Some(regions) if !full => {
                let mut delta = vec![];
                for &r in regions {
                    let now_in = region(r);
                    self.counters.regions_read += 1;
                    self.counters.region_voxels_read += now_in.len() as u64;
                    let current: HashMap<VoxelKey, (u32, u32)> =
                        now_in.iter().map(|v| (key(v), (v.occupancy.to_bits(), v.class))).collect();
                    let before = self.sent.remove(&Some(r)).unwrap_or_default();
                    self.diff(&before, &current, &now_in, &mut delta);
                    self.sent_voxels = self.sent_voxels + current.len() - before.len();
                    if !current.is_empty() {
                        self.sent.insert(Some(r), current);
                    }
                }
                (delta, self.sent_voxels)
            }
            _ => {
                let voxels = everything();
                self.counters.whole_map_reads += 1;
                let mut current: HashMap<Region, HashMap<VoxelKey, (u32, u32)>> = HashMap::new();
                for v in &voxels {
                    current.entry(self.grid.region_of(v)).or_default().insert(key(v), (v.occupancy.to_bits(), v.class));
                }
                let previous = std::mem::replace(&mut self.sent, current);
                self.sent_voxels = voxels.len();
                if full {
                    if self.snapshot_requested && !force_full && !due {
                        self.counters.snapshots_requested += 1;
                    }
                    self.snapshot_requested = false;
                    self.last_full = Some(now);
                    self.counters.full_messages += 1;
                    self.counters.full_bytes += bytes(voxels.len());
                    self.counters.full_only_bytes += bytes(voxels.len());
                    return (VOXELS_FULL, voxels);
                }
                let empty = HashMap::new();
                let mut delta = vec![];
                let mut by_region: HashMap<Region, Vec<Voxel>> = HashMap::new();
                for v in voxels {
                    by_region.entry(self.grid.region_of(&v)).or_default().push(v);
                }
                for (r, now_in) in &by_region {
                    self.diff(previous.get(r).unwrap_or(&empty), &self.sent[r], now_in, &mut delta);
                }
                for (r, before) in previous.iter().filter(|(r, _)| !by_region.contains_key(*r)) {
                    let _ = r;
                    self.diff(before, &empty, &[], &mut delta);
                }
                (delta, self.sent_voxels)
            }
        };
        self.counters.removed += delta.iter().filter(|v| v.class == VOXEL_CLASS_REMOVED).count() as u64;
        self.counters.full_only_bytes += bytes(total);
        self.counters.delta_messages += 1;
        self.counters.delta_bytes += bytes(delta.len());
        (VOXELS_DELTA, delta)
    }

    /// Appends to `delta` the voxels of `now_in` (the region's voxels now, `current` their keys)
    /// that differ from `before`, and those of `before` that are gone, as removed.
    fn diff(
        &self,
        before: &HashMap<VoxelKey, (u32, u32)>,
        current: &HashMap<VoxelKey, (u32, u32)>,
        now_in: &[Voxel],
        delta: &mut Vec<Voxel>,
    ) {
        delta.extend(now_in.iter().filter(|v| before.get(&key(v)) != Some(&(v.occupancy.to_bits(), v.class))));
        for k in before.keys().filter(|k| !current.contains_key(*k)) {
            let size = f32::from_bits(k.3);
            let centre = |c: i32| (c as f32 + 0.5) * size;
            delta.push(Voxel {
                center_m: [centre(k.0), centre(k.1), centre(k.2)],
                size_m: size,
                occupancy: 0.0,
                class: VOXEL_CLASS_REMOVED,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn voxel(x: i32, y: i32, z: i32, occupancy: f32, class: u32) -> Voxel {
        let s = 0.1f32;
        Voxel {
            center_m: [(x as f32 + 0.5) * s, (y as f32 + 0.5) * s, (z as f32 + 0.5) * s],
            size_m: s,
            occupancy,
            class,
        }
    }

    const GRID: RegionGrid = RegionGrid { resolution_m: 0.1, depth: 14 }; // regions of 4^3 voxels

    /// The regions in which `a` and `b` differ (what the octree's change tracking reports).
    fn changed_regions(a: &[Voxel], b: &[Voxel]) -> Vec<[u16; 3]> {
        let index = |m: &[Voxel]| -> HashMap<VoxelKey, Voxel> { m.iter().map(|v| (key(v), *v)).collect() };
        let (ia, ib) = (index(a), index(b));
        let mut out: Vec<[u16; 3]> = ia
            .iter()
            .filter(|(k, v)| ib.get(*k) != Some(*v))
            .chain(ib.iter().filter(|(k, v)| ia.get(*k) != Some(*v)))
            .filter_map(|(_, v)| GRID.region_of(v))
            .collect();
        out.sort();
        out.dedup();
        out
    }

    fn in_region(map: &[Voxel], r: [u16; 3]) -> Vec<Voxel> {
        map.iter().filter(|v| GRID.region_of(v) == Some(r)).copied().collect()
    }

    /// A map that grows, changes and loses voxels: a consumer applying the stream holds the
    /// sender's map after every message, whether the sender re-reads only the changed regions
    /// or everything, and the deltas are much smaller than the map.
    #[test]
    fn a_consumer_applying_the_deltas_holds_the_map_after_every_message() {
        let mut stream = VoxelStream::new(GRID, Some(Duration::from_secs(10)));
        let t0 = Instant::now();
        let (mut held, mut have_full) = (HashMap::new(), false);
        let mut map: Vec<Voxel> = vec![];
        let (mut full_bytes, mut delta_bytes) = (0u64, 0u64);
        for step in 0..40i32 {
            let before = map.clone();
            // Grow by a row, change one voxel's occupancy, drop one every fifth step; negative
            // coordinates too.
            for x in -10..10 {
                map.push(voxel(x, step, -step, 0.7, 0));
            }
            if let Some(v) = map.get_mut((step as usize * 7) % 20) {
                v.occupancy = 0.9;
                v.class = 2;
            }
            if step % 5 == 4 {
                map.remove(3);
            }
            let now = t0 + Duration::from_secs(step as u64);
            let changed = changed_regions(&before, &map);
            let read_all = step % 7 == 3; // as after an octree change anywhere
            let (kind, payload) = stream.next(
                now,
                false,
                (!read_all).then_some(changed.as_slice()),
                || map.clone(),
                |r| in_region(&map, r),
            );
            match kind {
                VOXELS_FULL => full_bytes += payload.len() as u64,
                _ => delta_bytes += payload.len() as u64,
            }
            assert!(apply(&mut held, &mut have_full, kind, &payload), "step {step}");
            let expect: HashMap<VoxelKey, Voxel> = map.iter().map(|v| (key(v), *v)).collect();
            assert_eq!(held, expect, "step {step}");
            assert_eq!(stream.held(), map.len(), "step {step}");
        }
        // Full sets at 0, 10, 20, 30 s; the deltas carry a row and a changed voxel or two.
        assert_eq!(stream.counters.full_messages, 4);
        assert_eq!(stream.counters.delta_messages, 36);
        // Each delta: the new row (20), a changed voxel, a removed one; the map reaches 800.
        assert!(delta_bytes <= 36 * 22, "deltas {delta_bytes} voxels");
        let sent = stream.counters.full_bytes + stream.counters.delta_bytes;
        assert!(sent * 5 < stream.counters.full_only_bytes, "{:?}", stream.counters);
        assert_eq!(full_bytes + delta_bytes, sent / std::mem::size_of::<Voxel>() as u64);
        assert!(stream.counters.removed >= 7);
    }

    /// A voxel larger than a region (a pruned leaf) is kept apart and followed when the
    /// sender re-reads everything; a region is re-read alone without touching it.
    #[test]
    fn voxels_larger_than_a_region_are_followed() {
        let big = Voxel { center_m: [0.8, 0.8, 0.8], size_m: 1.6, occupancy: 0.97, class: 0 };
        assert_eq!(GRID.region_of(&big), None);
        let small = voxel(20, 0, 0, 0.7, 0);
        let mut stream = VoxelStream::new(GRID, Some(Duration::from_secs(100)));
        let t0 = Instant::now();
        let (mut held, mut have_full) = (HashMap::new(), false);
        let mut map = vec![big, small];
        let (k, p) = stream.next(t0, false, Some(&[]), || map.clone(), |r| in_region(&map, r));
        assert!(k == VOXELS_FULL && apply(&mut held, &mut have_full, k, &p));
        map[1].occupancy = 0.8;
        let r = GRID.region_of(&map[1]).unwrap();
        let (k, p) = stream.next(t0, false, Some(&[r]), || unreachable!(), |r| in_region(&map, r));
        assert_eq!((k, p.len()), (VOXELS_DELTA, 1));
        apply(&mut held, &mut have_full, k, &p);
        // The big voxel splits into eight (the octree says: everything).
        map.remove(0);
        for i in 0..8 {
            let c = |b: usize| 0.4 + 0.8 * ((i >> b) & 1) as f32;
            map.push(Voxel { center_m: [c(0), c(1), c(2)], size_m: 0.8, occupancy: 0.97, class: 0 });
        }
        let (k, p) = stream.next(t0, false, None, || map.clone(), |r| in_region(&map, r));
        assert_eq!(k, VOXELS_DELTA);
        apply(&mut held, &mut have_full, k, &p);
        let expect: HashMap<VoxelKey, Voxel> = map.iter().map(|v| (key(v), *v)).collect();
        assert_eq!(held, expect);
    }

    #[test]
    fn a_delta_before_any_full_set_is_refused_and_a_snapshot_comes_on_request() {
        let (mut held, mut have_full) = (HashMap::new(), false);
        assert!(!apply(&mut held, &mut have_full, VOXELS_DELTA, &[voxel(0, 0, 0, 0.7, 0)]));
        assert!(held.is_empty());
        let mut stream = VoxelStream::new(GRID, Some(Duration::from_secs(10)));
        let t0 = Instant::now();
        let one = || vec![voxel(0, 0, 0, 0.7, 0)];
        let none = |_: [u16; 3]| vec![];
        assert_eq!(stream.next(t0, false, Some(&[]), one, none).0, VOXELS_FULL);
        assert_eq!(stream.next(t0 + Duration::from_secs(1), false, Some(&[]), one, none).0, VOXELS_DELTA);
        stream.request_snapshot();
        let (kind, payload) = stream.next(t0 + Duration::from_secs(2), false, Some(&[]), one, none);
        assert_eq!((kind, payload.len()), (VOXELS_FULL, 1));
        assert_eq!(stream.counters.snapshots_requested, 1);
        // Without a full interval every message is a full set (the old stream).
        let mut always = VoxelStream::new(GRID, None);
        for k in 0..3 {
            assert_eq!(always.next(t0 + Duration::from_secs(k), false, Some(&[]), Vec::new, none).0, VOXELS_FULL);
        }
    }

    /// The mapper's own octree, scans of a room with a box that moves away (occupied voxels
    /// cleared, pruned blocks split) from a sensor that moves across region boundaries: after
    /// every message, a consumer applying the stream holds exactly the map's occupied voxels,
    /// while the mapper re-read only the changed regions (fewer voxels than the map).
    #[test]
    fn following_the_mappers_octree_through_the_changed_regions() {
        let mut st = MapperState::new(crate::MapperSettings::default()).expect("state");
        let grid = RegionGrid { resolution_m: st.tree.resolution(), depth: VOXEL_REGION_DEPTH };
        let mut stream = VoxelStream::new(grid, Some(Duration::from_secs(1000)));
        let t0 = Instant::now();
        let (mut held, mut have_full) = (HashMap::new(), false);
        let mut seed = 7u64;
        let mut rnd = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut deltas, mut delta_voxels) = (0, 0usize);
        for step in 0..24 {
            // A room [-4, 5] x [-4, 5] x [-1, 2.5] m; a 1 m box at x = 2 for the first half.
            let origin = [-2.0 + 0.15 * step as f64, -1.0 + 0.1 * step as f64, 0.5];
            let box_here = step < 12;
            let mut pts = vec![];
            for _ in 0..3000 {
                let (az, el) = (rnd() * std::f64::consts::TAU, (rnd() - 0.5) * 1.6);
                let d = [az.cos() * el.cos(), az.sin() * el.cos(), el.sin()];
                let mut t = f64::INFINITY;
                for (a, lo, hi) in [(0, -4.0, 5.0), (1, -4.0, 5.0), (2, -1.0, 2.5)] {
                    if d[a] > 1e-9 {
                        t = t.min((hi - origin[a]) / d[a]);
                    } else if d[a] < -1e-9 {
                        t = t.min((lo - origin[a]) / d[a]);
                    }
                }
                if box_here {
                    // Slab test against the box [1.5, 2.5] x [-0.5, 0.5] x [-1, 0].
                    let (mut tn, mut tf) = (0.0f64, f64::INFINITY);
                    for (a, lo, hi) in [(0, 1.5, 2.5), (1, -0.5, 0.5), (2, -1.0, 0.0)] {
                        if d[a].abs() < 1e-12 {
                            if origin[a] < lo || origin[a] > hi {
                                tf = -1.0;
                            }
                        } else {
                            let (t1, t2) = ((lo - origin[a]) / d[a], (hi - origin[a]) / d[a]);
                            tn = tn.max(t1.min(t2));
                            tf = tf.min(t1.max(t2));
                        }
                    }
                    if tn <= tf && tn > 0.0 {
                        t = t.min(tn);
                    }
                }
                pts.push([0, 1, 2].map(|a| (origin[a] + d[a] * t) as f32));
            }
            let o = origin.map(|c| c as f32);
            st.tree.insert_point_cloud(&pts, o, 14.0, false).expect("insert");
            let (kind, payload) =
                next_message(&mut stream, &mut st, None, t0 + Duration::from_secs(step)).expect("message");
            if kind == VOXELS_DELTA {
                deltas += 1;
                delta_voxels += payload.len();
            }
            assert!(apply(&mut held, &mut have_full, kind, &payload), "step {step}");
            let expect: HashMap<VoxelKey, Voxel> = all_voxels(&st, None).iter().map(|v| (key(v), *v)).collect();
            assert_eq!(held.len(), expect.len(), "step {step}");
            assert!(held == expect, "step {step}: the followed map differs");
        }
        assert_eq!(deltas, 23);
        let c = stream.counters;
        assert_eq!(c.whole_map_reads, 1, "only the first message read the whole map: {c:?}");
        assert!(c.regions_read >= 23 && c.region_voxels_read < 23 * stream.held() as u64, "{c:?}");
        assert!(stream.counters.removed > 0, "the box's voxels were cleared: {:?}", stream.counters);
        let map = stream.held();
        assert!(delta_voxels < 23 * map, "deltas {delta_voxels} voxels, map {map}");
    }
}

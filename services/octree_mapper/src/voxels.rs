//! Voxel deltas on `pipeline/map/voxels`: after a full set, each message carries only the voxels
//! that changed since the previous one (new, or a changed occupancy or class; one no longer
//! occupied with class [`VOXEL_CLASS_REMOVED`]), with a full set again every
//! `voxels_full_interval_s` and when a [`shared_types::COMMAND_VOXEL_SNAPSHOT`] asks for one. A
//! viewer then follows the map at the voxel rate with a stream that grows with what changes, not
//! with the map. [`apply`] (in `shared_types::voxel_stream`) is what a consumer does with a message.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use shared_types::{VOXEL_CLASS_REMOVED, VOXELS_DELTA, VOXELS_FULL, Voxel};

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
}

/// The sender's side: what subscribers were last told, and when the last full set went out.
#[derive(Debug, Default)]
pub struct VoxelStream {
    sent: HashMap<VoxelKey, (u32, u32)>,
    /// A full set at least this often; `None`: every message is a full set.
    full_every: Option<Duration>,
    last_full: Option<Instant>,
    snapshot_requested: bool,
    /// What was sent.
    pub counters: VoxelStreamCounters,
}

impl VoxelStream {
    /// A stream sending a full set at least every `full_every` (`None`: always full sets).
    pub fn new(full_every: Option<Duration>) -> Self {
        Self { full_every, ..Self::default() }
    }

    /// The next message sends a full set (a [`shared_types::COMMAND_VOXEL_SNAPSHOT`]).
    pub fn request_snapshot(&mut self) {
        self.snapshot_requested = true;
    }

    /// The message for the map's occupied `voxels` now: `(kind, payload)`. `force_full` sends a
    /// full set whatever is due (the end of the run).
    pub fn next(&mut self, voxels: Vec<Voxel>, now: Instant, force_full: bool) -> (u32, Vec<Voxel>) {
        let due = match (self.full_every, self.last_full) {
            (None, _) | (_, None) => true,
            (Some(every), Some(last)) => now.duration_since(last) >= every,
        };
        let full = force_full || due || self.snapshot_requested;
        let mut current: HashMap<VoxelKey, (u32, u32)> = HashMap::with_capacity(voxels.len());
        for v in &voxels {
            current.insert(key(v), (v.occupancy.to_bits(), v.class));
        }
        let bytes = |n: usize| (n * std::mem::size_of::<Voxel>()) as u64;
        self.counters.full_only_bytes += bytes(voxels.len());
        if full {
            if self.snapshot_requested && !force_full && !due {
                self.counters.snapshots_requested += 1;
            }
            self.snapshot_requested = false;
            self.last_full = Some(now);
            self.sent = current;
            self.counters.full_messages += 1;
            self.counters.full_bytes += bytes(voxels.len());
            return (VOXELS_FULL, voxels);
        }
        let mut delta: Vec<Voxel> =
            voxels.into_iter().filter(|v| self.sent.get(&key(v)) != Some(&(v.occupancy.to_bits(), v.class))).collect();
        for (k, _) in self.sent.iter().filter(|(k, _)| !current.contains_key(*k)) {
            let size = f32::from_bits(k.3);
            let centre = |c: i32| (c as f32 + 0.5) * size;
            delta.push(Voxel {
                center_m: [centre(k.0), centre(k.1), centre(k.2)],
                size_m: size,
                occupancy: 0.0,
                class: VOXEL_CLASS_REMOVED,
            });
            self.counters.removed += 1;
        }
        self.sent = current;
        self.counters.delta_messages += 1;
        self.counters.delta_bytes += bytes(delta.len());
        (VOXELS_DELTA, delta)
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

    /// A map that grows, changes and loses voxels: a consumer applying the stream holds the
    /// sender's map after every message, and the deltas are much smaller than the map.
    #[test]
    fn a_consumer_applying_the_deltas_holds_the_map_after_every_message() {
        let mut stream = VoxelStream::new(Some(Duration::from_secs(10)));
        let t0 = Instant::now();
        let (mut held, mut have_full) = (HashMap::new(), false);
        let mut map: Vec<Voxel> = vec![];
        let (mut full_bytes, mut delta_bytes) = (0u64, 0u64);
        for step in 0..40i32 {
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
            let (kind, payload) = stream.next(map.clone(), now, false);
            match kind {
                VOXELS_FULL => full_bytes += payload.len() as u64,
                _ => delta_bytes += payload.len() as u64,
            }
            assert!(apply(&mut held, &mut have_full, kind, &payload), "step {step}");
            let expect: HashMap<VoxelKey, Voxel> = map.iter().map(|v| (key(v), *v)).collect();
            assert_eq!(held, expect, "step {step}");
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

    #[test]
    fn a_delta_before_any_full_set_is_refused_and_a_snapshot_comes_on_request() {
        let (mut held, mut have_full) = (HashMap::new(), false);
        assert!(!apply(&mut held, &mut have_full, VOXELS_DELTA, &[voxel(0, 0, 0, 0.7, 0)]));
        assert!(held.is_empty());
        let mut stream = VoxelStream::new(Some(Duration::from_secs(10)));
        let t0 = Instant::now();
        assert_eq!(stream.next(vec![voxel(0, 0, 0, 0.7, 0)], t0, false).0, VOXELS_FULL);
        assert_eq!(stream.next(vec![voxel(0, 0, 0, 0.7, 0)], t0 + Duration::from_secs(1), false).0, VOXELS_DELTA);
        stream.request_snapshot();
        let (kind, payload) = stream.next(vec![voxel(0, 0, 0, 0.7, 0)], t0 + Duration::from_secs(2), false);
        assert_eq!((kind, payload.len()), (VOXELS_FULL, 1));
        assert_eq!(stream.counters.snapshots_requested, 1);
        // Without a full interval every message is a full set (the old stream).
        let mut always = VoxelStream::new(None);
        for k in 0..3 {
            assert_eq!(always.next(vec![], t0 + Duration::from_secs(k), false).0, VOXELS_FULL);
        }
    }
}

//! What a restarted `fastslam` keeps: the stage records every trajectory sample and every local
//! map's origin in the runtime's journal as it goes ([`pipeline_runtime::Runtime::state`]; one
//! line each, flushed before the pose is published). A restarted instance (the supervisor sets `SLAM_PIPELINE_RESTARTS` > 0)
//! reads it back, so `slam_local.tum`, the segment list and the accuracy at the end cover the whole
//! run, and starts a *new* local map numbered after the last one: the landmark maps of the killed
//! instance are lost, and fusion places the new local map in the world like any other.
//!
//! Lines are `s <t_s> <segment> <x y z> <qx qy qz qw> <36 covariance values>` and
//! `o <segment> <t_s>`; numbers in Rust's shortest round-trip form.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use pipeline_runtime::StateStore;

use fastslam::eval::TrajectorySample;
use nalgebra::{Isometry3, Matrix6, Quaternion, Translation3, UnitQuaternion};

/// What a killed instance had done.
#[derive(Debug, Clone, Default)]
pub struct Restored {
    /// Its trajectory.
    pub trajectory: Vec<TrajectorySample>,
    /// Its local maps' origins, s.
    pub segment_origins_s: BTreeMap<u32, f64>,
}

impl Restored {
    /// The id the restarted instance's first local map gets: one after every id used so far.
    pub fn next_segment(&self) -> u32 {
        let used = self.trajectory.iter().map(|s| s.segment).chain(self.segment_origins_s.keys().copied()).max();
        used.map_or(0, |s| s + 1)
    }
}

fn parse_sample(fields: &[&str]) -> Option<TrajectorySample> {
    if fields.len() != 2 + 7 + 36 {
        return None;
    }
    let t_s: f64 = fields[0].parse().ok()?;
    let segment: u32 = fields[1].parse().ok()?;
    let v: Vec<f64> = fields[2..].iter().map(|x| x.parse()).collect::<Result<_, _>>().ok()?;
    if !v.iter().all(|x| x.is_finite()) || !t_s.is_finite() {
        return None;
    }
    let q = UnitQuaternion::from_quaternion(Quaternion::new(v[6], v[3], v[4], v[5]));
    Some(TrajectorySample {
        t_s,
        segment,
        map_from_body: Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), q),
        covariance: Matrix6::from_row_slice(&v[7..]),
    })
}

/// Reads journal lines in order up to the first that does not parse; returns what they hold
/// and how many were read.
pub fn parse(lines: &[String]) -> (Restored, usize) {
    let mut r = Restored::default();
    let mut n = 0;
    for line in lines {
        let fields: Vec<&str> = line.split_whitespace().collect();
        let ok = match fields.split_first() {
            Some((&"s", rest)) => parse_sample(rest).map(|s| r.trajectory.push(s)).is_some(),
            Some((&"o", [seg, t])) => match (seg.parse::<u32>(), t.parse::<f64>()) {
                (Ok(seg), Ok(t)) if t.is_finite() => {
                    r.segment_origins_s.insert(seg, t);
                    true
                }
                _ => false,
            },
            _ => false,
        };
        if !ok {
            break;
        }
        n += 1;
    }
    (r, n)
}

/// Records a local map's origin.
pub fn record_origin(state: &mut StateStore, segment: u32, t_s: f64) {
    state.record(&format!("o {segment} {t_s}"));
}

/// Records a trajectory sample.
pub fn record_sample(state: &mut StateStore, s: &TrajectorySample) {
    let mut out = String::with_capacity(1024);
    let p = s.map_from_body.translation.vector;
    let q = s.map_from_body.rotation.coords; // x, y, z, w
    let _ = write!(out, "s {} {} {} {} {} {} {} {} {}", s.t_s, s.segment, p.x, p.y, p.z, q[0], q[1], q[2], q[3]);
    for r in 0..6 {
        for c in 0..6 {
            let _ = write!(out, " {}", s.covariance[(r, c)]);
        }
    }
    state.record(&out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn sample(t_s: f64, segment: u32) -> TrajectorySample {
        TrajectorySample {
            t_s,
            segment,
            map_from_body: Isometry3::new(Vector3::new(1.5, -2.25, t_s), Vector3::new(0.1, -0.2, 0.3)),
            covariance: Matrix6::from_fn(|r, c| (r * 6 + c) as f64 * 1e-3 + 1.0 / 3.0),
        }
    }

    #[test]
    fn journal_lines_read_back_exactly_up_to_one_that_does_not_parse() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (mut store, _) = StateStore::open(dir.path(), "slam", false).expect("store");
        record_origin(&mut store, 0, 0.1);
        record_sample(&mut store, &sample(1.0, 0));
        record_origin(&mut store, 1, 2.0);
        record_sample(&mut store, &sample(2.0, 1));
        store.flush().expect("flush");
        drop(store);
        let (_, restart) = StateStore::open(dir.path(), "slam", true).expect("reopen");
        let mut lines = restart.expect("a restart").journal;
        lines.push("s 3.0 1 0.5 0.25".into());
        let (r, n) = parse(&lines);
        assert_eq!(n, 4);
        assert_eq!(r.trajectory.len(), 2);
        assert_eq!(r.trajectory[1].t_s, 2.0);
        assert_eq!(r.trajectory[1].map_from_body, sample(2.0, 1).map_from_body);
        assert_eq!(r.trajectory[1].covariance, sample(2.0, 1).covariance);
        assert_eq!(r.segment_origins_s, BTreeMap::from([(0, 0.1), (1, 2.0)]));
        assert_eq!(r.next_segment(), 2);
    }
}

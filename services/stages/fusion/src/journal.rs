//! What a restarted `fusion` keeps: the stage records every input the engine took (buoy fixes,
//! compass headings, synced pairs, in the order taken) in the runtime's journal, and keeps the
//! newest landmark map of each SLAM local map as the snapshot `landmarks.<segment>`
//! ([`pipeline_runtime::Runtime::state`]).
//! A restarted instance (the supervisor sets `SLAM_PIPELINE_RESTARTS` > 0) replays them into a new
//! engine: the engine is deterministic, so it is back in the state the killed one had (segments,
//! transforms, the live path so far) and the globally consistent path and map at the end cover the
//! whole run. Nothing is published during the replay (those poses went out already); what arrived
//! while no instance ran is lost.
//!
//! Journal lines: `f <t> <x y z> <cov 9>`, `h <t> <yaw> <σ>`, `p <t> <segment> <x y z> <qx qy qz qw>
//! <cov 36> <buoy x y z> <buoy cov 9>`; landmark snapshots: `<id> <segment> <x y z> <cov 9>
//! <descriptor hex or -> <observations>` per line. Numbers in Rust's shortest round-trip form.

use std::fmt::Write as _;

use pipeline_runtime::StateStore;
use pipeline_runtime::restart::{Restart, StateError};

use fusion::engine::{FixInput, HeadingInput, PairInput};
use fusion::global_map::MapLandmark;
use nalgebra::{Isometry3, Matrix3, Matrix6, Quaternion, Translation3, UnitQuaternion, Vector3};

/// One input of the engine, in the order it was taken.
#[derive(Debug, Clone, PartialEq)]
pub enum Entry {
    /// A buoy fix.
    Fix(FixInput),
    /// A compass heading.
    Heading(HeadingInput),
    /// A synced pair (boxed: it is four times the size of the others).
    Pair(Box<PairInput>),
}

/// What a killed instance had taken.
#[derive(Debug, Clone, Default)]
pub struct Restored {
    /// The journalled inputs, in order.
    pub entries: Vec<Entry>,
    /// The newest landmark map of each local map.
    pub landmarks: Vec<(u32, Vec<MapLandmark>)>,
    /// Journal lines read (the runtime keeps those).
    pub lines: usize,
}

fn nums(fields: &[&str]) -> Option<Vec<f64>> {
    let v: Vec<f64> = fields.iter().map(|x| x.parse().ok()).collect::<Option<_>>()?;
    v.iter().all(|x| x.is_finite()).then_some(v)
}

fn write_nums(out: &mut String, values: impl IntoIterator<Item = f64>) {
    for v in values {
        let _ = write!(out, " {v}");
    }
}

fn row_major3(m: &Matrix3<f64>) -> impl Iterator<Item = f64> + '_ {
    (0..9).map(|i| m[(i / 3, i % 3)])
}

fn parse_entry(line: &str) -> Option<Entry> {
    let fields: Vec<&str> = line.split_whitespace().collect();
    let (kind, rest) = fields.split_first()?;
    match *kind {
        "f" if rest.len() == 13 => {
            let v = nums(rest)?;
            Some(Entry::Fix(FixInput {
                t_s: v[0],
                position_m: Vector3::new(v[1], v[2], v[3]),
                covariance_m2: Matrix3::from_row_slice(&v[4..13]),
            }))
        }
        "h" if rest.len() == 3 => {
            let v = nums(rest)?;
            Some(Entry::Heading(HeadingInput { t_s: v[0], yaw_rad: v[1], sigma_rad: v[2] }))
        }
        "p" if rest.len() == 57 => {
            let segment: u32 = rest[1].parse().ok()?;
            let t_s: f64 = rest[0].parse().ok()?;
            let v = nums(&rest[2..])?;
            let q = UnitQuaternion::from_quaternion(Quaternion::new(v[6], v[3], v[4], v[5]));
            Some(Entry::Pair(Box::new(PairInput {
                t_s,
                segment,
                local_from_body: Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), q),
                local_covariance: Matrix6::from_row_slice(&v[7..43]),
                buoy_m: Vector3::new(v[43], v[44], v[45]),
                buoy_cov_m2: Matrix3::from_row_slice(&v[46..55]),
            })))
        }
        _ => None,
    }
}

fn parse_landmark(line: &str) -> Option<MapLandmark> {
    let f: Vec<&str> = line.split_whitespace().collect();
    if f.len() != 16 {
        return None;
    }
    let v = nums(&f[2..14])?;
    let descriptor = match f[14] {
        "-" => None,
        hex if hex.len() == 64 => {
            let mut d = [0u8; 32];
            for (i, b) in d.iter_mut().enumerate() {
                *b = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).ok()?;
            }
            Some(d)
        }
        _ => return None,
    };
    Some(MapLandmark {
        id: f[0].parse().ok()?,
        segment: f[1].parse().ok()?,
        mean_m: Vector3::new(v[0], v[1], v[2]),
        cov_m2: Matrix3::from_row_slice(&v[3..12]),
        descriptor,
        observations: f[15].parse().ok()?,
    })
}

/// Snapshot key of the landmark map of `segment`.
fn landmarks_key(segment: u32) -> String {
    format!("landmarks.{segment}")
}

/// Reads what a killed instance kept: its journal lines in order up to the first that does not
/// parse, and its landmark snapshots (a malformed one is an error naming the file).
pub fn read(restart: &Restart) -> Result<Restored, StateError> {
    let mut r = Restored::default();
    for line in &restart.journal {
        let Some(e) = parse_entry(line) else { break };
        r.entries.push(e);
        r.lines += 1;
    }
    for (key, path) in &restart.snapshots {
        let Some(segment) = key.strip_prefix("landmarks.").and_then(|s| s.parse::<u32>().ok()) else { continue };
        let text = std::fs::read_to_string(path).map_err(StateError::io("reading", path))?;
        let ls: Option<Vec<MapLandmark>> = text.lines().map(parse_landmark).collect();
        let ls =
            ls.ok_or_else(|| StateError::Malformed { path: path.clone(), what: "a malformed landmark line".into() })?;
        r.landmarks.push((segment, ls));
    }
    r.landmarks.sort_by_key(|(s, _)| *s);
    Ok(r)
}

/// Records an entry in the journal (written at the next flush).
pub fn record(state: &mut StateStore, e: &Entry) {
    let mut out = String::with_capacity(1024);
    match e {
        Entry::Fix(f) => {
            let _ = write!(out, "f {}", f.t_s);
            write_nums(&mut out, f.position_m.iter().copied().chain(row_major3(&f.covariance_m2)));
        }
        Entry::Heading(h) => {
            let _ = write!(out, "h {} {} {}", h.t_s, h.yaw_rad, h.sigma_rad);
        }
        Entry::Pair(p) => {
            let _ = write!(out, "p {} {}", p.t_s, p.segment);
            let t = p.local_from_body.translation.vector;
            let q = p.local_from_body.rotation.coords; // x, y, z, w
            write_nums(&mut out, t.iter().copied().chain(q.iter().copied()));
            write_nums(&mut out, (0..36).map(|i| p.local_covariance[(i / 6, i % 6)]));
            write_nums(&mut out, p.buoy_m.iter().copied().chain(row_major3(&p.buoy_cov_m2)));
        }
    }
    state.record(&out);
}

/// Replaces the kept landmark map of `segment` (a snapshot).
pub fn landmarks(state: &StateStore, segment: u32, landmarks: &[MapLandmark]) -> Result<(), StateError> {
    let mut text = String::with_capacity(landmarks.len() * 300);
    for l in landmarks {
        let _ = write!(text, "{} {}", l.id, l.segment);
        write_nums(&mut text, l.mean_m.iter().copied().chain(row_major3(&l.cov_m2)));
        match l.descriptor {
            Some(d) => {
                text.push(' ');
                for b in d {
                    let _ = write!(text, "{b:02x}");
                }
            }
            None => text.push_str(" -"),
        }
        let _ = writeln!(text, " {}", l.observations);
    }
    state.snapshot(&landmarks_key(segment), text.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair(t_s: f64) -> PairInput {
        PairInput {
            t_s,
            segment: 3,
            local_from_body: Isometry3::new(Vector3::new(1.0, 2.0, t_s), Vector3::new(0.1, 0.2, -0.3)),
            local_covariance: Matrix6::from_fn(|r, c| (r + 7 * c) as f64 / 3.0),
            buoy_m: Vector3::new(-1.0, 0.5, 1.0 / 7.0),
            buoy_cov_m2: Matrix3::from_fn(|r, c| (r * 3 + c) as f64 * 0.01),
        }
    }

    #[test]
    fn journal_and_landmarks_read_back_exactly() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (mut store, _) = StateStore::open(dir.path(), "fusion", false).expect("store");
        let entries = vec![
            Entry::Fix(FixInput {
                t_s: 1.0,
                position_m: Vector3::new(1.0, 2.0, 3.0),
                covariance_m2: Matrix3::identity(),
            }),
            Entry::Heading(HeadingInput { t_s: 1.5, yaw_rad: -0.25, sigma_rad: 0.01 }),
            Entry::Pair(Box::new(pair(2.0))),
        ];
        for e in &entries {
            record(&mut store, e);
        }
        store.flush().expect("flush");
        let lm = MapLandmark {
            id: 9,
            segment: 3,
            mean_m: Vector3::new(0.5, 0.25, -2.0),
            cov_m2: Matrix3::identity() * 0.01,
            descriptor: Some([0xab; 32]),
            observations: 4,
        };
        landmarks(&store, 3, &[lm.clone(), MapLandmark { descriptor: None, id: 10, ..lm.clone() }]).expect("landmarks");
        drop(store);
        let (_, restart) = StateStore::open(dir.path(), "fusion", true).expect("reopen");
        let mut restart = restart.expect("a restart");
        restart.journal.push("p 3.0 3 1.0".into());
        let r = read(&restart).expect("read");
        assert_eq!(r.lines, 3, "the line that does not parse ends the journal");
        assert_eq!(r.entries[..2], entries[..2]);
        let (Entry::Pair(a), Entry::Pair(b)) = (&r.entries[2], &entries[2]) else { panic!("a pair") };
        assert_eq!(
            (a.t_s, a.segment, a.local_covariance, a.buoy_m, a.buoy_cov_m2),
            (b.t_s, b.segment, b.local_covariance, b.buoy_m, b.buoy_cov_m2)
        );
        assert!((a.local_from_body.rotation.coords - b.local_from_body.rotation.coords).norm() < 1e-12);
        assert_eq!(r.landmarks.len(), 1);
        assert_eq!(r.landmarks[0].1, vec![lm.clone(), MapLandmark { descriptor: None, id: 10, ..lm }]);
    }
}

//! What a restarted `fusion` keeps: the process appends every input the engine took (buoy fixes,
//! compass headings, synced pairs, in the order taken) to `<out>/state/<process>.journal`, and keeps
//! the newest landmark map of each SLAM local map in `<out>/state/<process>.landmarks/<segment>`.
//! A restarted instance (the supervisor sets `SLAM_PIPELINE_RESTARTS` > 0) replays them into a new
//! engine: the engine is deterministic, so it is back in the state the killed one had (segments,
//! transforms, the live path so far) and the globally consistent path and map at the end cover the
//! whole run. Nothing is published during the replay (those poses went out already); what arrived
//! while no instance ran is lost.
//!
//! Journal lines: `f <t> <x y z> <cov 9>`, `h <t> <yaw> <σ>`, `p <t> <segment> <x y z> <qx qy qz qw>
//! <cov 36> <buoy x y z> <buoy cov 9>`; landmark files: `<id> <segment> <x y z> <cov 9>
//! <descriptor hex or -> <observations>` per line, replaced atomically (rename). Numbers in Rust's
//! shortest round-trip form; a journal line cut short by the kill is ignored with all after it.

use pipeline_runtime::restart::StateError;
use std::fmt::Write as _;
use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};

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
    /// Journal lines that did not parse (the one cut by the kill, at most).
    pub ignored_lines: usize,
}

/// The journal of one `fusion` process.
#[derive(Debug)]
pub struct Journal {
    path: PathBuf,
    landmarks_dir: PathBuf,
    file: File,
    buffer: String,
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

impl Journal {
    /// `<out_dir>/state/<process>.journal`.
    pub fn path(out_dir: &Path, process: &str) -> PathBuf {
        pipeline_runtime::restart::state_path(out_dir, process, "journal")
    }

    fn landmarks_dir(path: &Path) -> PathBuf {
        path.with_extension("landmarks")
    }

    /// Reads what a killed instance journalled (`Ok(None)` without a journal).
    pub fn read(path: &Path) -> Result<Option<Restored>, StateError> {
        let Some(text) = pipeline_runtime::restart::read_state_text(path)? else { return Ok(None) };
        let mut r = Restored::default();
        r.ignored_lines = pipeline_runtime::restart::parse_lines(&text, |line| {
            parse_entry(line).map(|e| r.entries.push(e)).is_some()
        });
        let dir = Self::landmarks_dir(path);
        if let Ok(rd) = std::fs::read_dir(&dir) {
            for entry in rd.flatten() {
                let Some(segment) = entry.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else { continue };
                let file = entry.path();
                let text = std::fs::read_to_string(&file).map_err(StateError::io("reading", &file))?;
                let ls: Option<Vec<MapLandmark>> = text.lines().map(parse_landmark).collect();
                let ls = ls.ok_or_else(|| StateError::Malformed {
                    path: file.clone(),
                    what: "a malformed landmark line".into(),
                })?;
                r.landmarks.push((segment, ls));
            }
        }
        r.landmarks.sort_by_key(|(s, _)| *s);
        Ok(Some(r))
    }

    /// Opens the journal: rewritten with what `restored` holds (a restart), or empty (and the
    /// landmark files of an earlier run removed).
    pub fn open(path: &Path, restored: Option<&Restored>) -> Result<Self, StateError> {
        let landmarks_dir = Self::landmarks_dir(path);
        if restored.is_none() && landmarks_dir.exists() {
            std::fs::remove_dir_all(&landmarks_dir).map_err(StateError::io("removing", &landmarks_dir))?;
        }
        std::fs::create_dir_all(&landmarks_dir).map_err(StateError::io("creating", &landmarks_dir))?;
        let file = File::create(path).map_err(StateError::io("creating", path))?;
        let mut j = Self { path: path.into(), landmarks_dir, file, buffer: String::new() };
        if let Some(r) = restored {
            for e in &r.entries {
                j.push(e);
            }
            j.flush()?;
        }
        Ok(j)
    }

    /// Queues an entry (written by [`Journal::flush`]).
    pub fn push(&mut self, e: &Entry) {
        let out = &mut self.buffer;
        match e {
            Entry::Fix(f) => {
                let _ = write!(out, "f {}", f.t_s);
                write_nums(out, f.position_m.iter().copied().chain(row_major3(&f.covariance_m2)));
            }
            Entry::Heading(h) => {
                let _ = write!(out, "h {} {} {}", h.t_s, h.yaw_rad, h.sigma_rad);
            }
            Entry::Pair(p) => {
                let _ = write!(out, "p {} {}", p.t_s, p.segment);
                let t = p.local_from_body.translation.vector;
                let q = p.local_from_body.rotation.coords; // x, y, z, w
                write_nums(out, t.iter().copied().chain(q.iter().copied()));
                write_nums(out, (0..36).map(|i| p.local_covariance[(i / 6, i % 6)]));
                write_nums(out, p.buoy_m.iter().copied().chain(row_major3(&p.buoy_cov_m2)));
            }
        }
        out.push('\n');
    }

    /// Writes the queued entries (one write).
    pub fn flush(&mut self) -> Result<(), StateError> {
        if !self.buffer.is_empty() {
            self.file.write_all(self.buffer.as_bytes()).map_err(StateError::io("writing", &self.path))?;
            self.buffer.clear();
        }
        Ok(())
    }

    /// Replaces the kept landmark map of `segment` (a temporary file renamed over it).
    pub fn landmarks(&self, segment: u32, landmarks: &[MapLandmark]) -> Result<(), StateError> {
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
        let tmp = self.landmarks_dir.join(format!(".{segment}.tmp"));
        let dest = self.landmarks_dir.join(segment.to_string());
        std::fs::write(&tmp, text).and_then(|_| std::fs::rename(&tmp, &dest)).map_err(StateError::io("writing", &dest))
    }
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
        let path = Journal::path(dir.path(), "fusion");
        assert!(Journal::read(&path).expect("read").is_none());
        let entries = vec![
            Entry::Fix(FixInput {
                t_s: 1.0,
                position_m: Vector3::new(1.0, 2.0, 3.0),
                covariance_m2: Matrix3::identity(),
            }),
            Entry::Heading(HeadingInput { t_s: 1.5, yaw_rad: -0.25, sigma_rad: 0.01 }),
            Entry::Pair(Box::new(pair(2.0))),
        ];
        let mut j = Journal::open(&path, None).expect("open");
        for e in &entries {
            j.push(e);
        }
        j.flush().expect("flush");
        let lm = MapLandmark {
            id: 9,
            segment: 3,
            mean_m: Vector3::new(0.5, 0.25, -2.0),
            cov_m2: Matrix3::identity() * 0.01,
            descriptor: Some([0xab; 32]),
            observations: 4,
        };
        j.landmarks(3, &[lm.clone(), MapLandmark { descriptor: None, id: 10, ..lm.clone() }]).expect("landmarks");
        drop(j);
        let mut text = std::fs::read_to_string(&path).expect("journal");
        text.push_str("p 3.0 3 1.0");
        std::fs::write(&path, text).expect("write");
        let r = Journal::read(&path).expect("read").expect("journal");
        assert_eq!(r.ignored_lines, 1);
        assert_eq!(r.entries.len(), 3);
        assert_eq!(r.entries[..2], entries[..2]);
        let (Entry::Pair(a), Entry::Pair(b)) = (&r.entries[2], &entries[2]) else { panic!("a pair") };
        assert_eq!(
            (a.t_s, a.segment, a.local_covariance, a.buoy_m, a.buoy_cov_m2),
            (b.t_s, b.segment, b.local_covariance, b.buoy_m, b.buoy_cov_m2)
        );
        assert!((a.local_from_body.rotation.coords - b.local_from_body.rotation.coords).norm() < 1e-12);
        assert_eq!(r.landmarks.len(), 1);
        assert_eq!(r.landmarks[0].1, vec![lm.clone(), MapLandmark { descriptor: None, id: 10, ..lm }]);
        // A first instance of a new run starts empty.
        Journal::open(&path, None).expect("open");
        let fresh = Journal::read(&path).expect("read").expect("journal");
        assert!(fresh.entries.is_empty() && fresh.landmarks.is_empty());
    }
}

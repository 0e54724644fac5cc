//! What a restarted `fastslam` keeps: the process appends every trajectory sample and every local
//! map's origin to `<out>/state/<process>.journal` as it goes (one line each, written before the
//! pose is published). A restarted instance (the supervisor sets `SLAM_PIPELINE_RESTARTS` > 0)
//! reads it back, so `slam_local.tum`, the segment list and the accuracy at the end cover the whole
//! run, and starts a *new* local map numbered after the last one: the landmark maps of the killed
//! instance are lost, and fusion places the new local map in the world like any other.
//!
//! Lines are `s <t_s> <segment> <x y z> <qx qy qz qw> <36 covariance values>` and
//! `o <segment> <t_s>`; numbers in Rust's shortest round-trip form. A line cut short by the kill
//! does not parse and is ignored, as is everything after it.

use pipeline_runtime::restart::StateError;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use fastslam::eval::TrajectorySample;
use nalgebra::{Isometry3, Matrix6, Quaternion, Translation3, UnitQuaternion};

/// What a killed instance had done.
#[derive(Debug, Clone, Default)]
pub struct Restored {
    /// Its trajectory.
    pub trajectory: Vec<TrajectorySample>,
    /// Its local maps' origins, s.
    pub segment_origins_s: BTreeMap<u32, f64>,
    /// Lines that did not parse (the last one, cut by the kill, at most).
    pub ignored_lines: usize,
}

impl Restored {
    /// The id the restarted instance's first local map gets: one after every id used so far.
    pub fn next_segment(&self) -> u32 {
        let used = self.trajectory.iter().map(|s| s.segment).chain(self.segment_origins_s.keys().copied()).max();
        used.map_or(0, |s| s + 1)
    }
}

/// The journal file of one `fastslam` process.
#[derive(Debug)]
pub struct Journal {
    path: PathBuf,
    file: File,
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

impl Journal {
    /// `<out_dir>/state/<process>.journal`.
    pub fn path(out_dir: &Path, process: &str) -> PathBuf {
        pipeline_runtime::restart::state_path(out_dir, process, "journal")
    }

    /// Reads what a killed instance journalled (`Ok(None)` without a journal).
    pub fn read(path: &Path) -> Result<Option<Restored>, StateError> {
        let Some(text) = pipeline_runtime::restart::read_state_text(path)? else { return Ok(None) };
        let mut r = Restored::default();
        r.ignored_lines = pipeline_runtime::restart::parse_lines(&text, |line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            match fields.split_first() {
                Some((&"s", rest)) => parse_sample(rest).map(|s| r.trajectory.push(s)).is_some(),
                Some((&"o", [seg, t])) => match (seg.parse::<u32>(), t.parse::<f64>()) {
                    (Ok(seg), Ok(t)) if t.is_finite() => {
                        r.segment_origins_s.insert(seg, t);
                        true
                    }
                    _ => false,
                },
                _ => false,
            }
        });
        // A kill mid-line leaves no newline at the end: the cut line was counted above.
        Ok(Some(r))
    }

    /// Opens the journal: appending after what `restored` holds (a restart), or empty.
    pub fn open(path: &Path, restored: Option<&Restored>) -> Result<Self, StateError> {
        let file = pipeline_runtime::restart::create_state_file(path)?;
        let mut j = Self { path: path.into(), file };
        // Rewritten from what was read, so a line cut by the kill is gone.
        if let Some(r) = restored {
            let mut text = String::new();
            for (seg, t) in &r.segment_origins_s {
                Self::origin_line(&mut text, *seg, *t);
            }
            for s in &r.trajectory {
                Self::sample_line(&mut text, s);
            }
            j.append(&text)?;
        }
        Ok(j)
    }

    fn origin_line(out: &mut String, segment: u32, t_s: f64) {
        let _ = writeln!(out, "o {segment} {t_s}");
    }

    fn sample_line(out: &mut String, s: &TrajectorySample) {
        let p = s.map_from_body.translation.vector;
        let q = s.map_from_body.rotation.coords; // x, y, z, w
        let _ = write!(out, "s {} {} {} {} {} {} {} {} {}", s.t_s, s.segment, p.x, p.y, p.z, q[0], q[1], q[2], q[3]);
        for r in 0..6 {
            for c in 0..6 {
                let _ = write!(out, " {}", s.covariance[(r, c)]);
            }
        }
        out.push('\n');
    }

    fn append(&mut self, text: &str) -> Result<(), StateError> {
        self.file.write_all(text.as_bytes()).map_err(StateError::io("writing", &self.path))
    }

    /// Appends a trajectory sample.
    pub fn sample(&mut self, s: &TrajectorySample) -> Result<(), StateError> {
        let mut text = String::with_capacity(1024);
        Self::sample_line(&mut text, s);
        self.append(&text)
    }

    /// Appends a local map's origin.
    pub fn origin(&mut self, segment: u32, t_s: f64) -> Result<(), StateError> {
        let mut text = String::new();
        Self::origin_line(&mut text, segment, t_s);
        self.append(&text)
    }
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
    fn a_journal_reads_back_exactly_and_a_cut_line_is_dropped() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = Journal::path(dir.path(), "slam");
        assert!(Journal::read(&path).expect("read").is_none());
        let mut j = Journal::open(&path, None).expect("open");
        j.origin(0, 0.1).expect("origin");
        j.sample(&sample(1.0, 0)).expect("sample");
        j.origin(1, 2.0).expect("origin");
        j.sample(&sample(2.0, 1)).expect("sample");
        drop(j);
        // A kill in the middle of the next line.
        let mut text = std::fs::read_to_string(&path).expect("journal");
        text.push_str("s 3.0 1 0.5 0.25");
        std::fs::write(&path, &text).expect("write");
        let r = Journal::read(&path).expect("read").expect("a journal");
        assert_eq!(r.ignored_lines, 1);
        assert_eq!(r.trajectory.len(), 2);
        assert_eq!(r.trajectory[1].t_s, 2.0);
        assert_eq!(r.trajectory[1].map_from_body, sample(2.0, 1).map_from_body);
        assert_eq!(r.trajectory[1].covariance, sample(2.0, 1).covariance);
        assert_eq!(r.segment_origins_s, BTreeMap::from([(0, 0.1), (1, 2.0)]));
        assert_eq!(r.next_segment(), 2);
        // Reopened for the restart: the cut line is gone, new lines follow.
        let mut j = Journal::open(&path, Some(&r)).expect("reopen");
        j.sample(&sample(4.0, 2)).expect("sample");
        let again = Journal::read(&path).expect("read").expect("a journal");
        assert_eq!((again.ignored_lines, again.trajectory.len(), again.next_segment()), (0, 3, 3));
    }
}

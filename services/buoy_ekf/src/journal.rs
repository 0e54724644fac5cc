//! What a restarted `buoy_ekf` keeps: the process appends its trajectory (the estimate after every
//! input) and the odometry inputs it applied to `<out>/state/<process>.journal` as it goes. A
//! restarted instance (the supervisor sets `SLAM_PIPELINE_RESTARTS` > 0) reads them back, so
//! `buoy_ekf.tum`, `dead_reckoning.tum` and the accuracy at the end cover the whole run; the filter
//! itself starts over (trilateration of the next ranges, heading hypotheses), so its estimate is
//! unavailable for the first ranges after the restart.
//!
//! Lines are `t <t_s> <x> <y> <z> <heading or NaN>` and `u <t_s> <v> <δθx> <δθy> <δθz> <δt>`, numbers
//! in Rust's shortest round-trip form. A line cut short by the kill is ignored with all after it.

use pipeline_runtime::restart::StateError;
use std::fmt::Write as _;
use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use geometry::ProcessInput;
use nalgebra::Vector3;

/// What a killed instance had done.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Restored {
    /// Its trajectory: (t, position, heading if known).
    pub trajectory: Vec<(f64, Vector3<f64>, Option<f64>)>,
    /// The odometry inputs it applied, with their stamps.
    pub inputs: Vec<(f64, ProcessInput)>,
    /// Lines that did not parse (the one cut by the kill, at most).
    pub ignored_lines: usize,
}

/// The journal file of one `buoy_ekf` process.
#[derive(Debug)]
pub struct Journal {
    path: PathBuf,
    file: File,
}

fn numbers(fields: &[&str], n: usize) -> Option<Vec<f64>> {
    if fields.len() != n {
        return None;
    }
    fields.iter().map(|x| x.parse().ok()).collect()
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
                Some((&"t", rest)) => numbers(rest, 5)
                    .filter(|v| v[..4].iter().all(|x| x.is_finite()))
                    .map(|v| {
                        r.trajectory.push((v[0], Vector3::new(v[1], v[2], v[3]), v[4].is_finite().then_some(v[4])))
                    })
                    .is_some(),
                Some((&"u", rest)) => numbers(rest, 6)
                    .filter(|v| v.iter().all(|x| x.is_finite()))
                    .map(|v| {
                        let u =
                            ProcessInput { v_mps: v[1], delta_theta_rad: Vector3::new(v[2], v[3], v[4]), dt_s: v[5] };
                        r.inputs.push((v[0], u))
                    })
                    .is_some(),
                _ => false,
            }
        });
        Ok(Some(r))
    }

    /// Opens the journal: rewritten with what `restored` holds (a restart), or empty.
    pub fn open(path: &Path, restored: Option<&Restored>) -> Result<Self, StateError> {
        let file = pipeline_runtime::restart::create_state_file(path)?;
        let mut j = Self { path: path.into(), file };
        if let Some(r) = restored {
            j.append(&r.trajectory, &r.inputs)?;
        }
        Ok(j)
    }

    /// Appends trajectory samples and inputs (one write).
    pub fn append(
        &mut self,
        trajectory: &[(f64, Vector3<f64>, Option<f64>)],
        inputs: &[(f64, ProcessInput)],
    ) -> Result<(), StateError> {
        if trajectory.is_empty() && inputs.is_empty() {
            return Ok(());
        }
        let mut text = String::new();
        for (t, p, h) in trajectory {
            let _ = writeln!(text, "t {t} {} {} {} {}", p.x, p.y, p.z, h.unwrap_or(f64::NAN));
        }
        for (t, u) in inputs {
            let d = u.delta_theta_rad;
            let _ = writeln!(text, "u {t} {} {} {} {} {}", u.v_mps, d.x, d.y, d.z, u.dt_s);
        }
        self.file.write_all(text.as_bytes()).map_err(StateError::io("writing", &self.path))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_journal_reads_back_exactly_and_a_cut_line_is_dropped() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = Journal::path(dir.path(), "buoy");
        assert!(Journal::read(&path).expect("read").is_none());
        let traj = vec![(1.0, Vector3::new(0.1, 0.2, -1.0 / 3.0), None), (1.1, Vector3::new(1.0, 2.0, 3.0), Some(0.5))];
        let u = ProcessInput { v_mps: 1.5, delta_theta_rad: Vector3::new(0.0, 0.01, -0.02), dt_s: 0.1 };
        let mut j = Journal::open(&path, None).expect("open");
        j.append(&traj, &[(1.0, u)]).expect("append");
        drop(j);
        let mut text = std::fs::read_to_string(&path).expect("journal");
        text.push_str("t 1.2 0.5");
        std::fs::write(&path, &text).expect("write");
        let r = Journal::read(&path).expect("read").expect("a journal");
        assert_eq!(r.trajectory, traj);
        assert_eq!(r.inputs.len(), 1);
        assert_eq!(r.inputs[0].1.delta_theta_rad, u.delta_theta_rad);
        assert_eq!(r.ignored_lines, 1);
        let mut j = Journal::open(&path, Some(&r)).expect("reopen");
        j.append(&traj[..1], &[]).expect("append");
        let again = Journal::read(&path).expect("read").expect("a journal");
        assert_eq!((again.trajectory.len(), again.inputs.len(), again.ignored_lines), (3, 1, 0));
    }
}

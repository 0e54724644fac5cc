//! What a restarted `buoy_ekf` keeps: the stage records its trajectory (the estimate after every
//! input) and the odometry inputs it applied in the runtime's journal as it goes
//! ([`pipeline_runtime::Runtime::state`]). A restarted instance (the supervisor sets
//! `SLAM_PIPELINE_RESTARTS` > 0) reads them back ([`parse`]), so `buoy_ekf.tum`,
//! `dead_reckoning.tum` and the accuracy at the end cover the whole run; the filter itself starts
//! over (trilateration of the next ranges, heading hypotheses), so its estimate is unavailable for
//! the first ranges after the restart.
//!
//! Lines are `t <t_s> <x> <y> <z> <heading or NaN>` and `u <t_s> <v> <δθx> <δθy> <δθz> <δt>`, numbers
//! in Rust's shortest round-trip form.

use std::fmt::Write as _;

use geometry::ProcessInput;
use nalgebra::Vector3;
use pipeline_runtime::StateStore;

/// What a killed instance had done.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Restored {
    /// Its trajectory: (t, position, heading if known).
    pub trajectory: Vec<(f64, Vector3<f64>, Option<f64>)>,
    /// The odometry inputs it applied, with their stamps.
    pub inputs: Vec<(f64, ProcessInput)>,
}

fn numbers(fields: &[&str], n: usize) -> Option<Vec<f64>> {
    if fields.len() != n {
        return None;
    }
    fields.iter().map(|x| x.parse().ok()).collect()
}

/// Reads journal lines in order up to the first that does not parse; returns what they hold
/// and how many were read.
pub fn parse(lines: &[String]) -> (Restored, usize) {
    let mut r = Restored::default();
    let mut n = 0;
    for line in lines {
        let fields: Vec<&str> = line.split_whitespace().collect();
        let ok = match fields.split_first() {
            Some((&"t", rest)) => numbers(rest, 5)
                .filter(|v| v[..4].iter().all(|x| x.is_finite()))
                .map(|v| r.trajectory.push((v[0], Vector3::new(v[1], v[2], v[3]), v[4].is_finite().then_some(v[4]))))
                .is_some(),
            Some((&"u", rest)) => numbers(rest, 6)
                .filter(|v| v.iter().all(|x| x.is_finite()))
                .map(|v| {
                    let u = ProcessInput { v_mps: v[1], delta_theta_rad: Vector3::new(v[2], v[3], v[4]), dt_s: v[5] };
                    r.inputs.push((v[0], u))
                })
                .is_some(),
            _ => false,
        };
        if !ok {
            break;
        }
        n += 1;
    }
    (r, n)
}

/// Records trajectory samples and inputs as journal lines.
pub fn record(state: &mut StateStore, trajectory: &[(f64, Vector3<f64>, Option<f64>)], inputs: &[(f64, ProcessInput)]) {
    let mut line = String::with_capacity(128);
    for (t, p, h) in trajectory {
        line.clear();
        let _ = write!(line, "t {t} {} {} {} {}", p.x, p.y, p.z, h.unwrap_or(f64::NAN));
        state.record(&line);
    }
    for (t, u) in inputs {
        line.clear();
        let d = u.delta_theta_rad;
        let _ = write!(line, "u {t} {} {} {} {} {}", u.v_mps, d.x, d.y, d.z, u.dt_s);
        state.record(&line);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn journal_lines_read_back_exactly_up_to_one_that_does_not_parse() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (mut store, _) = StateStore::open(dir.path(), "buoy", false).expect("store");
        let traj = vec![(1.0, Vector3::new(0.1, 0.2, -1.0 / 3.0), None), (1.1, Vector3::new(1.0, 2.0, 3.0), Some(0.5))];
        let u = ProcessInput { v_mps: 1.5, delta_theta_rad: Vector3::new(0.0, 0.01, -0.02), dt_s: 0.1 };
        record(&mut store, &traj, &[(1.0, u)]);
        store.flush().expect("flush");
        drop(store);
        let (_, restart) = StateStore::open(dir.path(), "buoy", true).expect("reopen");
        let mut lines = restart.expect("a restart").journal;
        lines.push("t 1.2 0.5".into());
        lines.push("t 1.3 0 0 0 NaN".into());
        let (r, n) = parse(&lines);
        assert_eq!(n, 3, "the line that does not parse ends the journal");
        assert_eq!(r.trajectory, traj);
        assert_eq!(r.inputs.len(), 1);
        assert_eq!(r.inputs[0].1.delta_theta_rad, u.delta_theta_rad);
    }
}

//! What a restarted `buoy_ekf` keeps: the stage records every input its filter takes, in the
//! order it takes them ([`crate::Applied`]), in the runtime's journal as it goes
//! ([`pipeline_runtime::Runtime::state`]). A restarted instance (the supervisor sets
//! `SLAM_PIPELINE_RESTARTS` > 0) reads them back ([`parse`]) and replays them
//! ([`crate::BuoyState::replay`]): its filter, trajectory and counters are the killed instance's,
//! so it goes on from the killed instance's estimate (instead of starting over from the next
//! ranges, whose first fixes are metres off until the filter has settled again), and
//! `buoy_ekf.tum`, `dead_reckoning.tum` and the accuracy at the end cover the whole run.
//!
//! Lines, numbers in Rust's shortest round-trip form (`NaN` and `inf` as Rust writes them: an
//! invalid input is replayed, and counted, as it was the first time):
//! - `o <stamp_ns> <v> <δθx> <δθy> <δθz> <δt> <16 covariance entries, row-major>`: odometry;
//! - `r <stamp_ns> <origin_ns> <n> (<buoy_id> <range_m> <sigma_m>)×n`: a ranges message;
//! - `d <stamp_ns> <depth_m> <sigma_m>`: a depth reading.

use std::fmt::Write as _;

use pipeline_runtime::StateStore;
use shared_types::{BuoyRange, DepthReading, OdometryInput};

use crate::Applied;

fn floats(fields: &[&str]) -> Option<Vec<f64>> {
    fields.iter().map(|x| x.parse().ok()).collect()
}

fn parse_line(line: &str) -> Option<Applied> {
    let fields: Vec<&str> = line.split_whitespace().collect();
    let (&kind, rest) = fields.split_first()?;
    let stamp_ns: u64 = rest.first()?.parse().ok()?;
    match kind {
        "o" if rest.len() == 22 => {
            let v = floats(&rest[1..])?;
            let mut input_covariance = [0.0; 16];
            input_covariance.copy_from_slice(&v[5..]);
            let input =
                OdometryInput { v_mps: v[0], delta_theta_rad: [v[1], v[2], v[3]], dt_s: v[4], input_covariance };
            Some(Applied::Odometry { stamp_ns, input })
        }
        "r" if rest.len() >= 3 => {
            let origin_ns: u64 = rest[1].parse().ok()?;
            let n: usize = rest[2].parse().ok()?;
            if rest.len() != 3 + 3 * n {
                return None;
            }
            let ranges = rest[3..]
                .chunks(3)
                .map(|c| {
                    Some(BuoyRange {
                        buoy_id: c[0].parse().ok()?,
                        _reserved: 0,
                        range_m: c[1].parse().ok()?,
                        sigma_m: c[2].parse().ok()?,
                    })
                })
                .collect::<Option<Vec<_>>>()?;
            Some(Applied::Ranges { stamp_ns, origin_ns, ranges })
        }
        "d" if rest.len() == 3 => {
            let v = floats(&rest[1..])?;
            Some(Applied::Depth { stamp_ns, reading: DepthReading { depth_m: v[0], sigma_m: v[1] } })
        }
        _ => None,
    }
}

/// Reads journal lines in order up to the first that does not parse; returns the inputs they
/// hold and how many lines were read.
pub fn parse(lines: &[String]) -> (Vec<Applied>, usize) {
    let inputs: Vec<Applied> = lines.iter().map_while(|l| parse_line(l)).collect();
    let n = inputs.len();
    (inputs, n)
}

/// Records inputs as journal lines.
pub fn record(state: &mut StateStore, inputs: &[Applied]) {
    let mut line = String::with_capacity(256);
    for a in inputs {
        line.clear();
        let _ = match a {
            Applied::Odometry { stamp_ns, input: u } => {
                let d = u.delta_theta_rad;
                let _ = write!(line, "o {stamp_ns} {} {} {} {} {}", u.v_mps, d[0], d[1], d[2], u.dt_s);
                u.input_covariance.iter().try_for_each(|c| write!(line, " {c}"))
            }
            Applied::Ranges { stamp_ns, origin_ns, ranges } => {
                let _ = write!(line, "r {stamp_ns} {origin_ns} {}", ranges.len());
                ranges.iter().try_for_each(|b| write!(line, " {} {} {}", b.buoy_id, b.range_m, b.sigma_m))
            }
            Applied::Depth { stamp_ns, reading: d } => write!(line, "d {stamp_ns} {} {}", d.depth_m, d.sigma_m),
        };
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
        let mut input_covariance = [0.0; 16];
        input_covariance[0] = 0.01;
        input_covariance[15] = f64::NAN; // invalid inputs are replayed as they came
        let inputs = vec![
            Applied::Odometry {
                stamp_ns: 1_000_000_000,
                input: OdometryInput {
                    v_mps: 1.5,
                    delta_theta_rad: [0.0, 0.01, -1.0 / 3.0],
                    dt_s: 0.1,
                    input_covariance,
                },
            },
            Applied::Ranges {
                stamp_ns: 1_050_000_000,
                origin_ns: 77,
                ranges: vec![
                    BuoyRange { buoy_id: 3, _reserved: 0, range_m: 20.125, sigma_m: 0.3 },
                    BuoyRange { buoy_id: 0, _reserved: 0, range_m: f64::INFINITY, sigma_m: 0.3 },
                ],
            },
            Applied::Ranges { stamp_ns: 1_060_000_000, origin_ns: 0, ranges: vec![] },
            Applied::Depth { stamp_ns: 1_100_000_000, reading: DepthReading { depth_m: 5.5, sigma_m: 0.05 } },
        ];
        record(&mut store, &inputs);
        store.flush().expect("flush");
        drop(store);
        let (_, restart) = StateStore::open(dir.path(), "buoy", true).expect("reopen");
        let mut lines = restart.expect("a restart").journal;
        lines.push("r 1200000000 0 2 1 20.0 0.3".into()); // fewer ranges than it says
        lines.push("d 1300000000 5.0 0.05".into());
        let (back, n) = parse(&lines);
        assert_eq!(n, 4, "the line that does not parse ends the journal");
        assert_eq!(back.len(), inputs.len());
        assert_eq!(back[1], inputs[1]);
        assert_eq!(back[2], inputs[2]);
        assert_eq!(back[3], inputs[3]);
        // (NaN is not equal to itself: the odometry field by field.)
        let (Applied::Odometry { input: x, .. }, Applied::Odometry { input: y, .. }) = (&back[0], &inputs[0]) else {
            panic!("{back:?}")
        };
        assert_eq!((x.v_mps, x.delta_theta_rad, x.dt_s), (y.v_mps, y.delta_theta_rad, y.dt_s));
        assert!(x.input_covariance[15].is_nan() && x.input_covariance[..15] == y.input_covariance[..15]);
    }
}

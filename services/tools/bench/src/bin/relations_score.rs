//! Scores a trajectory against a relations file (Kümmerle et al. 2009, "On measuring the accuracy
//! of SLAM algorithms"): for each relation (t1, t2, δ) the error e = (x_t1⁻¹ ⊕ x_t2) ⊖ δ, with the
//! poses interpolated at t1 and t2; prints mean ± std (and max) of the translational (m) and
//! rotational (deg) errors over the relations the trajectory covers, and how many it does not.
//!
//! ```text
//! cargo run --release -p pipeline_bench --bin relations_score -- \
//!     --trajectory out/grid_slam.tum --relations ../shared/data/carmen/fr079.relations --offset 1211.38
//! ```
//!
//! `--offset` is added to the trajectory's stamps to reach the relations' clock (the CARMEN
//! logs' offsets are in ../shared/data/carmen/ATTRIBUTION.md). `--scan-offset` also prints the
//! errors over a range of offsets, to show how sensitive the score is to the clock alignment.
//! `--by-rotation` splits the translational error by how far each relation turns, and
//! `--point-ahead` scores a point that far ahead of the pose along the body's x axis: together they
//! show whether a relation's reference point differs from the trajectory's (then the error grows
//! with the turn, as (R(δθ) − I)·lever).
//! Exit status 0; 2 on bad input (the message names the file and line).

use anyhow::{Context, Result};
use clap::Parser;
use grid_slam::Pose2;
use grid_slam::relations::{read_relations, score};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(about = "Score a trajectory (TUM) against relations (Kümmerle et al. 2009)")]
struct Args {
    /// Trajectory, TUM format (`t x y z qx qy qz qw`; yaw is taken from the quaternion).
    #[arg(long)]
    trajectory: PathBuf,
    /// Relations file (`t1 t2 dx dy dz droll dpitch dyaw`).
    #[arg(long)]
    relations: PathBuf,
    /// Seconds added to the trajectory's stamps to reach the relations' clock.
    #[arg(long, default_value_t = 0.0)]
    offset: f64,
    /// Poses further apart than this are not interpolated across, s.
    #[arg(long, default_value_t = 2.0)]
    max_gap: f64,
    /// Also score at offset ± this many seconds (in steps of 0.01 s).
    #[arg(long)]
    scan_offset: Option<f64>,
    /// Print the result as JSON.
    #[arg(long)]
    json: bool,
    /// Also print the translational error over the relations whose turn |δθ| falls in each of
    /// the bins [0, 0.1), [0.1, 0.5), [0.5, 1.6), [1.6, π] rad.
    #[arg(long)]
    by_rotation: bool,
    /// Score the point this far ahead of each pose along the body's x axis, m (0: the pose).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    point_ahead: f64,
}

fn main() {
    match run() {
        Ok(()) => {}
        Err(e) => {
            eprintln!("relations_score: {e:#}");
            std::process::exit(2);
        }
    }
}

fn run() -> Result<()> {
    let a = Args::parse();
    let traj: Vec<(f64, Pose2)> = geometry::tum::read_tum(&a.trajectory)
        .with_context(|| format!("reading {}", a.trajectory.display()))?
        .into_iter()
        .map(|(t, iso)| {
            let (_, _, yaw) = iso.rotation.euler_angles();
            (t, Pose2 { x_m: iso.translation.x, y_m: iso.translation.y, theta_rad: yaw })
        })
        .map(|(t, p): (f64, Pose2)| (t, p.compose(&Pose2 { x_m: a.point_ahead, y_m: 0.0, theta_rad: 0.0 })))
        .collect();
    let rel = read_relations(&a.relations)?;
    let s = score(&traj, &rel, a.offset, a.max_gap);
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        println!(
            "{} relations scored, {} not covered: translation {:.4} ± {:.4} m (max {:.3}), rotation {:.3} ± {:.3} deg (max {:.2})",
            s.scored,
            s.uncovered,
            s.trans_mean_m,
            s.trans_std_m,
            s.trans_max_m,
            s.rot_mean_deg,
            s.rot_std_deg,
            s.rot_max_deg
        );
        println!(
            "{} relations over {:.0} s (global consistency): translation {:.4} m; {:.1} % of all over {} m",
            s.long_scored,
            grid_slam::relations::LONG_SPAN_S,
            s.long_trans_mean_m,
            100.0 * s.over_far_share,
            grid_slam::relations::FAR_OFF_M
        );
    }
    if a.by_rotation {
        println!("{:>14} {:>10} {:>10}", "|turn| rad", "relations", "trans m");
        for (lo, hi) in [(0.0, 0.1), (0.1, 0.5), (0.5, 1.6), (1.6, 4.0)] {
            let bin: Vec<_> = rel.iter().filter(|r| (lo..hi).contains(&r.delta.theta_rad.abs())).copied().collect();
            let s = score(&traj, &bin, a.offset, a.max_gap);
            println!("{:>14} {:>10} {:>10.4}", format!("{lo:.1}-{hi:.1}"), s.scored, s.trans_mean_m);
        }
    }
    if let Some(w) = a.scan_offset {
        let steps = (w / 0.01).round() as i64;
        println!("{:>10} {:>10} {:>10}", "offset s", "trans m", "rot deg");
        for k in -steps..=steps {
            let o = a.offset + k as f64 * 0.01;
            let s = score(&traj, &rel, o, a.max_gap);
            println!("{o:>10.2} {:>10.4} {:>10.3}", s.trans_mean_m, s.rot_mean_deg);
        }
    }
    Ok(())
}

//! Not a test: runs CARMEN logs through the `grid_slam` filter (in one process, no IPC) and prints
//! a table of relation errors (Kümmerle et al. 2009), wall time and map memory next to the
//! published numbers of the data sets (../shared/data/carmen/ATTRIBUTION.md).
//!
//! The Radish "corrected" logs carry SLAM-corrected poses, so the odometry fed to the filter is
//! those poses with seeded synthetic drift (`grid_slam::drift::DriftModel`, defaults stated in its
//! docs); the drifted odometry alone is scored as well, as the baseline.
//!
//! ```text
//! cargo run --release -p pipeline_bench --bin grid_slam_bench   # fr079, intel, aces; drift seeds 7, 8, 9; 30 particles
//! cargo run --release -p pipeline_bench --bin grid_slam_bench -- --sets fr079 --seeds 7 --particles 1,30 --max-scans 1500
//! ```

use anyhow::{Context, Result, bail};
use clap::Parser;
use datasets::carmen::{OdometrySource, read_carmen};
use grid_slam::backend::{BackEnd, BackEndConfig};
use grid_slam::densify::{densify, interleave};
use grid_slam::drift::DriftModel;
use grid_slam::export::{Occupancy, write_tum2};
use grid_slam::relations::{read_relations, score};
use grid_slam::{GridSlam, GridSlamConfig, Pose2, ScanGeometry};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser, Debug)]
#[command(about = "2-D grid SLAM on CARMEN logs: relation errors, wall time, memory")]
struct Args {
    /// Data directory holding the logs and relations.
    #[arg(long, default_value = "../shared/data/carmen")]
    data: PathBuf,
    /// Data sets: fr079, intel, aces (comma-separated).
    #[arg(long, default_value = "fr079,intel,aces", value_delimiter = ',')]
    sets: Vec<String>,
    /// Particle counts to run (comma-separated).
    #[arg(long, default_value = "30", value_delimiter = ',')]
    particles: Vec<usize>,
    /// Grid resolution, m.
    #[arg(long, default_value_t = 0.05)]
    resolution: f64,
    /// Worker threads (0: all cores).
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Stop after this many scans (0: all).
    #[arg(long, default_value_t = 0)]
    max_scans: usize,
    /// Drift seeds (comma-separated): each set runs once per seed, and the means over the
    /// seeds close the table.
    #[arg(long, default_value = "7,8,9", value_delimiter = ',')]
    seeds: Vec<u64>,
    /// Filter settings as TOML (the `[grid_slam]` keys of a pipeline config), applied over the defaults.
    #[arg(long)]
    settings: Option<PathBuf>,
    /// Override the beam spacing: the scan spans this many degrees from its first to its last
    /// beam (CARMEN's FLASER lines do not say; 0: the reader's rule).
    #[arg(long, default_value_t = 0.0)]
    span_deg: f64,
    /// Print the particles' map memory after every filter update (stderr) and its distribution.
    #[arg(long)]
    mem_trace: bool,
    /// The filter alone: no pose-graph back end (`back_end = "none"`).
    #[arg(long)]
    front_end_only: bool,
    /// Back-end settings as TOML (the `[back_end]` keys of a pipeline config's `pose_graph`), over the defaults.
    #[arg(long)]
    back_end_settings: Option<PathBuf>,
    /// Score the poses at the scans only, as before the trajectories held poses between scans
    /// shaped by the odometry (the ODOM lines).
    #[arg(long)]
    scan_poses_only: bool,
    /// The laser's position ahead of the pose the filter estimates, m (negative: behind it).
    /// The corrected logs' poses are the laser's own (fr079 states `PARAM
    /// robot_frontlaser_offset -0.04` for its robot, and scores worse with it: docs/grid_slam.md),
    /// so the default is 0.
    #[arg(long, allow_hyphen_values = true, default_value_t = 0.0)]
    laser_offset: f64,
    /// Where the maps and trajectories go.
    #[arg(long, default_value = "target/grid_slam_bench")]
    out: PathBuf,
}

/// One run's scores, for the means over the seeds.
struct Row {
    set: &'static str,
    particles: usize,
    trans_m: f64,
    long_m: f64,
    far_share: f64,
    wall_s: f64,
}

struct Set {
    name: &'static str,
    log: &'static str,
    relations: &'static str,
    offset_s: f64,
    published: &'static str,
}

const SETS: [Set; 3] = [
    Set {
        name: "fr079",
        log: "freiburg-079-corrected.log.gz",
        relations: "fr079.relations",
        offset_s: 1211.38,
        published: "gmapping 0.061±0.044 m; Cartographer 0.045±0.035 m / 0.54±0.72°, 62 s",
    },
    Set {
        name: "intel",
        log: "intel-corrected.log.gz",
        relations: "intel.relations",
        offset_s: 976052857.34,
        published: "gmapping 0.070±0.083 m; Cartographer 0.023±0.024 m / 0.45±1.34°",
    },
    Set {
        name: "aces",
        log: "aces-corrected.log.gz",
        relations: "aces.relations",
        offset_s: 70.14,
        published: "gmapping 0.060±0.049 m; Cartographer 0.038±0.043 m / 0.37±0.47°",
    },
];

fn main() -> Result<()> {
    let args = Args::parse();
    let mut base = GridSlamConfig::default();
    if let Some(p) = &args.settings {
        let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
        base = toml::from_str(&text).with_context(|| format!("{}: not valid grid_slam settings", p.display()))?;
    }
    let mut be_cfg = BackEndConfig::default();
    if let Some(p) = &args.back_end_settings {
        let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
        be_cfg = toml::from_str(&text).with_context(|| format!("{}: not valid back-end settings", p.display()))?;
    }
    std::fs::create_dir_all(&args.out)?;
    print_header();
    let mut rows: Vec<Row> = vec![];
    for name in &args.sets {
        let Some(set) = SETS.iter().find(|s| s.name == name) else {
            bail!("unknown data set {name} (fr079, intel, aces)")
        };
        run_set(&args, set, &base, be_cfg, &mut rows)?;
    }
    println!(
        "mem x: peak MB of all particles' maps over one map (the one-particle run's when --particles starts with 1, else the best particle's at the end)"
    );
    println!("maps and trajectories: {}", args.out.display());
    Ok(())
}

fn print_header() {
    println!(
        "{:<6} {:>4} {:>4} {:>6} {:>6} {:>5} {:>8} {:>8} {:>20} {:>18} {:>9} {:>7} {:>16} {:>7} {:>8} {:>7}",
        "set",
        "seed",
        "N",
        "scans",
        "upd",
        "resmp",
        "wall s",
        "data s",
        "trans m (mean±std)",
        "rot deg",
        ">60 s m",
        ">0.5 m",
        "odometry m/deg",
        "peak MB",
        "map MB",
        "mem x"
    );
}

/// One data set: every drift seed and particle count, then the means over the seeds, the
/// published numbers and the log's own corrected poses' score.
fn run_set(args: &Args, set: &Set, base: &GridSlamConfig, be_cfg: BackEndConfig, rows: &mut Vec<Row>) -> Result<()> {
    let log_path = args.data.join(set.log);
    if !log_path.exists() {
        println!("{:<6} skipped: {} is absent", set.name, log_path.display());
        return Ok(());
    }
    let log = read_carmen(&log_path)?;
    let relations = read_relations(&args.data.join(set.relations))?;
    let odo = log.scan_odometry(OdometrySource::LaserLines);
    let mut scans: Vec<(usize, Pose2)> = log
        .scans
        .iter()
        .zip(&odo)
        .enumerate()
        .filter_map(|(i, (_, o))| o.map(|o| (i, Pose2 { x_m: o[0], y_m: o[1], theta_rad: o[2] })))
        .collect();
    if args.max_scans > 0 {
        scans.truncate(args.max_scans);
    }
    // The log's own corrected poses scored alike: the floor the scans' spacing leaves (the
    // relations' stamps fall between scans and the poses are interpolated there).
    let truth_traj: Vec<(f64, Pose2)> = scans.iter().map(|(i, p)| (log.scans[*i].stamp_s, *p)).collect();
    // The ODOM lines (the subsampled logs keep them at full rate): poses between scans.
    let track: Vec<(f64, Pose2)> = if args.scan_poses_only {
        Vec::new()
    } else {
        log.odometry_in_order()
            .0
            .into_iter()
            .map(|(t, o)| (t, Pose2 { x_m: o[0], y_m: o[1], theta_rad: o[2] }))
            .collect()
    };
    // The log's poses between scans: the ODOM lines where no scan is.
    let mut merged = truth_traj.clone();
    merged.extend(&track);
    merged.sort_by(|a, b| a.0.total_cmp(&b.0));
    merged.dedup_by(|later, earlier| later.0 == earlier.0);
    let truth_score = score(&densify(&truth_traj, &merged), &relations, set.offset_s, 2.0);
    let first = &log.scans[scans[0].0];
    let laser_offset_m = args.laser_offset;
    let stated = log.front_laser_offset_m().map_err(|e| anyhow::anyhow!(e))?;
    println!(
        "{:<6} the laser {laser_offset_m:+.3} m ahead of the pose (--laser-offset); the log's robot_frontlaser_offset: {}",
        set.name,
        stated.map_or("not stated".to_string(), |x| format!("{x:+.3} m"))
    );
    let geom = ScanGeometry {
        angle_min_rad: first.angle_min_rad,
        angle_increment_rad: if args.span_deg > 0.0 {
            args.span_deg.to_radians() / (first.ranges.len() - 1) as f64
        } else {
            first.angle_increment_rad
        },
        beams: first.ranges.len(),
        range_min_m: 0.01,
        range_max_m: first.range_max_m.unwrap_or(81.8),
        body_from_laser: Pose2 { x_m: laser_offset_m, y_m: 0.0, theta_rad: 0.0 },
    };
    for &seed in &args.seeds {
        let (drifted, between) = DriftModel { seed, ..Default::default() }.apply_between(&truth_traj, &track);
        let at_scans: Vec<(f64, Pose2)> = truth_traj.iter().zip(&drifted).map(|(t, p)| (t.0, *p)).collect();
        let odo_traj = interleave(&at_scans, &between);
        let run = Run {
            args,
            set,
            log: &log,
            scans: &scans,
            drifted: &drifted,
            odo_traj: &odo_traj,
            relations: &relations,
            geom,
            seed,
            odo_score: score(&odo_traj, &relations, set.offset_s, 2.0),
        };
        let mut one_particle_map_mb: Option<f64> = None;
        for &n in &args.particles {
            let cfg =
                GridSlamConfig { particles: n, resolution_m: args.resolution, threads: args.threads, ..base.clone() };
            rows.push(run.one(cfg, be_cfg, &mut one_particle_map_mb)?);
        }
    }
    for &n in &args.particles {
        let runs: Vec<&Row> = rows.iter().filter(|r| r.set == set.name && r.particles == n).collect();
        if runs.len() > 1 {
            let mean = |f: fn(&Row) -> f64| runs.iter().map(|r| f(r)).sum::<f64>() / runs.len() as f64;
            println!(
                "       N={n}, mean over {} seeds: translation {:.4} m, over 60 s {:.4} m, over 0.5 m {:.1} %, wall {:.1} s",
                runs.len(),
                mean(|r| r.trans_m),
                mean(|r| r.long_m),
                100.0 * mean(|r| r.far_share),
                mean(|r| r.wall_s)
            );
        }
    }
    println!("       published: {}", set.published);
    println!(
        "       the log's own corrected poses: {:.4}±{:.4} m, {:.3}°, >0.5 m {:.1} % ({} relations; scans {:.2} s apart on median)",
        truth_score.trans_mean_m,
        truth_score.trans_std_m,
        truth_score.rot_mean_deg,
        100.0 * truth_score.over_far_share,
        truth_score.scored,
        {
            let mut d: Vec<f64> = truth_traj.windows(2).map(|w| w[1].0 - w[0].0).collect();
            d.sort_by(f64::total_cmp);
            d.get(d.len() / 2).copied().unwrap_or(f64::NAN)
        }
    );
    Ok(())
}

/// One drift seed of one data set: what every particle count runs on.
struct Run<'a> {
    args: &'a Args,
    set: &'a Set,
    log: &'a datasets::carmen::CarmenLog,
    scans: &'a [(usize, Pose2)],
    drifted: &'a [Pose2],
    /// The drifted odometry at the scans and between them (the ODOM lines').
    odo_traj: &'a [(f64, Pose2)],
    relations: &'a [grid_slam::relations::Relation],
    geom: ScanGeometry,
    seed: u64,
    odo_score: grid_slam::relations::RelationScore,
}

impl Run<'_> {
    /// The filter (and the back end unless `--front-end-only`) with `cfg`: scored, printed,
    /// written (`<set>_s<seed>_<N>.tum` and the grid).
    fn one(&self, cfg: GridSlamConfig, be_cfg: BackEndConfig, one_particle_map_mb: &mut Option<f64>) -> Result<Row> {
        let (args, set, n) = (self.args, self.set, cfg.particles);
        let mut f = GridSlam::new(cfg, self.geom)?;
        let t0 = Instant::now();
        let (back_end, refused, mem_trace) = self.front_end(&mut f, be_cfg)?;
        let front_wall = t0.elapsed().as_secs_f64();
        let front_traj = densify(&f.trajectory(), self.odo_traj);
        let mut back_grid = None;
        let traj = if args.front_end_only {
            front_traj
        } else {
            let front_sc = score(&front_traj, self.relations, set.offset_s, 2.0);
            let r = back_end.run(&f)?;
            print_back_end(&front_sc, front_wall, &r.report, t0.elapsed().as_secs_f64() - front_wall);
            let t = densify(&f.trajectory_with(&r.nodes), self.odo_traj);
            back_grid = Some(r.grid);
            t
        };
        let wall = t0.elapsed().as_secs_f64();
        let sc = score(&traj, self.relations, set.offset_s, 2.0);
        // Peak bytes of all particles' distinct tiles against one map: the one-particle run's
        // map when it ran first (`--particles 1,...`), else this run's best particle's.
        let one_map_mb = f.memory().best_bytes as f64 / 1e6;
        if n == 1 {
            *one_particle_map_mb = Some(one_map_mb);
        }
        self.print_row(&f, &traj, &sc, wall, one_particle_map_mb.unwrap_or(one_map_mb));
        print_details(&f, refused, &mem_trace);
        let stem = format!("{}_s{}_{}", set.name, self.seed, n);
        write_tum2(&args.out.join(format!("{stem}.tum")), &traj)?;
        if let Some(g) = back_grid.as_ref().or(f.best_grid()) {
            let occ = Occupancy::from_grid(g, 5);
            occ.write_map_server(&args.out, &stem)?;
            let path: Vec<Pose2> = traj.iter().map(|p| p.1).collect();
            occ.write_png(&args.out.join(format!("{stem}.png")), &path)?;
        }
        Ok(Row {
            set: set.name,
            particles: n,
            trans_m: sc.trans_mean_m,
            long_m: sc.long_trans_mean_m,
            far_share: sc.over_far_share,
            wall_s: wall,
        })
    }

    /// Feeds every scan with its drifted odometry to the filter (and the updates' scans to the
    /// back end). Returns the back end, the scans refused and the maps' memory at each update
    /// (`--mem-trace`).
    fn front_end(&self, f: &mut GridSlam, be_cfg: BackEndConfig) -> Result<(BackEnd, usize, Vec<f64>)> {
        let mut back_end = BackEnd::new(be_cfg)?;
        let mut refused = 0;
        let mut mem_trace: Vec<f64> = Vec::new();
        for ((i, _), odom) in self.scans.iter().zip(self.drifted) {
            let s = &self.log.scans[*i];
            match f.process(s.stamp_s, *odom, &s.ranges) {
                Ok(o) => {
                    if o.updated && !self.args.front_end_only {
                        back_end.add_node(o.update, &s.ranges);
                    }
                    if o.updated && self.args.mem_trace {
                        let m = f.memory();
                        mem_trace.push(m.bytes as f64 / 1e6);
                        eprintln!("mem update={} bytes={} resampled={}", f.stats().updates, m.bytes, o.resampled);
                    }
                }
                Err(_) => refused += 1,
            }
        }
        Ok((back_end, refused, mem_trace))
    }

    /// The table's row of one run.
    fn print_row(
        &self,
        f: &GridSlam,
        traj: &[(f64, Pose2)],
        sc: &grid_slam::relations::RelationScore,
        wall: f64,
        one_map_mb: f64,
    ) {
        let st = f.stats();
        let peak_mb = f.peak_memory().map_or(f64::NAN, |m| m.bytes as f64 / 1e6);
        let span = traj.last().map_or(0.0, |l| l.0) - traj.first().map_or(0.0, |f| f.0);
        let o = &self.odo_score;
        println!(
            "{:<6} {:>4} {:>4} {:>6} {:>6} {:>5} {:>8.1} {:>8.0} {:>9.4}±{:<6.4} ({:>4}) {:>8.3}±{:<7.3} {:>9.4} {:>6.1}% {:>7.3}/{:<7.2} {:>8.1} {:>7.1} {:>7.2}",
            self.set.name,
            self.seed,
            f.config().particles,
            st.scans,
            st.updates,
            st.resamples,
            wall,
            span,
            sc.trans_mean_m,
            sc.trans_std_m,
            sc.scored,
            sc.rot_mean_deg,
            sc.rot_std_deg,
            sc.long_trans_mean_m,
            100.0 * sc.over_far_share,
            o.trans_mean_m,
            o.rot_mean_deg,
            peak_mb,
            f.memory().best_bytes as f64 / 1e6,
            peak_mb / one_map_mb
        );
    }
}

/// The front end's score and the back end's report, on one line.
fn print_back_end(
    front_sc: &grid_slam::relations::RelationScore,
    front_wall: f64,
    b: &grid_slam::backend::BackEndReport,
    back_wall: f64,
) {
    println!(
        "       front end: {:.4}±{:.4} m, {:.3}°, >60 s {:.4} m, >0.5 m {:.1}% in {:.1} s; back end: {} nodes, {} submaps, {} searched, {} matches, {} loop constraints ({} rejected), correction mean {:.3} max {:.3} m, {} iterations, {:.1} s (submaps {:.1}, search {:.1}, optimise {:.1})",
        front_sc.trans_mean_m,
        front_sc.trans_std_m,
        front_sc.rot_mean_deg,
        front_sc.long_trans_mean_m,
        100.0 * front_sc.over_far_share,
        front_wall,
        b.nodes,
        b.submaps,
        b.searched,
        b.matches,
        b.loop_constraints,
        b.rejected,
        b.mean_correction_m,
        b.max_correction_m,
        b.iterations,
        back_wall,
        b.submaps_s,
        b.search_s,
        b.optimise_s
    );
}

/// N_eff and lineages, what was refused, and the maps' memory over the updates.
fn print_details(f: &GridSlam, refused: usize, mem_trace: &[f64]) {
    let (st, n) = (f.stats(), f.config().particles);
    if let Some(ne) = f.n_eff_summary() {
        println!(
            "       N_eff/N over the updates: mean {:.2}, median {:.2}, p10 {:.2}; lineages that survive {} updates: {:.1} of {n} on average; of the first set at the end: {}",
            ne.mean_share,
            ne.median_share,
            ne.p10_share,
            grid_slam::filter::LINEAGE_WINDOW,
            ne.lineages_mean.unwrap_or(f64::NAN),
            ne.distinct_ancestors
        );
    }
    if st.updates > 0 {
        println!(
            "       scan matches per update: {:.1} of {n} particles (copies of one particle after a resampling share theirs)",
            st.matches as f64 / st.updates as f64
        );
    }
    if refused > 0 || st.tracking_failures > 0 || st.proposal_fallbacks > 0 {
        println!(
            "       refused scans {refused}, tracking failures {}, proposal fallbacks {}, invalid beams {}",
            st.tracking_failures, st.proposal_fallbacks, st.invalid_beams
        );
    }
    if !mem_trace.is_empty() {
        let mut v = mem_trace.to_vec();
        v.sort_by(f64::total_cmp);
        println!(
            "       maps' memory over the {} updates: mean {:.1} MB, median {:.1}, p90 {:.1}, max {:.1}",
            v.len(),
            v.iter().sum::<f64>() / v.len() as f64,
            v[v.len() / 2],
            v[v.len() * 9 / 10],
            v[v.len() - 1]
        );
    }
}

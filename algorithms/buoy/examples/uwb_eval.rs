//! Evaluates the buoy EKF on the libRSF "Labyrinth" indoor UWB data set (Pfeifer & Protzel,
//! TU Chemnitz, CC BY-SA 4.0: read from `../shared/data/indoor_uwb`, never copied into the
//! project) with the SAME default parameters as `plaza2_eval`; only the sensor-provided σ differ
//! (each range carries its variance, the odometry its wheel-speed variances).
//!
//! ```sh
//! cargo run --release -p buoy --example uwb_eval [-- [DIR] [--config FILE.toml] [--dump FILE]
//!     [--beacons 105,107,108] [--outliers 0.15] [--outlier-seed 1]]
//! ```
//! `--beacons` keeps only the ranges to those modules (the buoy table shrinks with them and
//! `init.min_buoys` is lowered to their number); `--outliers` turns that share of the ranges
//! into gross errors of 1-4 m of either sign (seeded, `--outlier-seed`): the real data under
//! the heavy-outlier conditions of issue 18, for comparison with the same run without them.
//! DIR defaults to `../shared/data/indoor_uwb` relative to the workspace root; it holds
//! `Indoor_UWB_Input.txt` and `Indoor_UWB_GT.txt`. `--config` and `--dump` as in `plaza2_eval`.
//! Lines (whitespace separated):
//! - `range2 t range_m variance_m2 module_x_m module_y_m module_id snr`;
//! - `odom2diff t wheel_1_mps wheel_2_mps v_y_mps wheel_base_m var_1 var_2 var_y` (the readme
//!   names the wheels right and left and numbers the variances 9-11; the files have them in
//!   columns 7-9);
//! - `point2 t x_m y_m c_xx c_xy c_yx c_yy` (ground truth, in the GT file).
//!
//! Differential drive as libRSF defines it (its 2-D differential odometry factor): the two wheel
//! columns are v − b·ω and v + b·ω (the readme's "right" column is the first), b the column named
//! wheel base (half the track in this convention). So v = (w₁ + w₂)/2, ω = (w₂ − w₁)/(2b) over the
//! interval since the previous odometry line (Δt = the first range period for the first line);
//! var_v = (var₁ + var₂)/4, var_δθ = (var₁ + var₂)·Δt²/(4b²). (Checked against the ground truth:
//! the other sign turns the path the wrong way.) The beacons (modules) are at the positions their
//! ranges carry, at the robot's height (planar ranges).
//!
//! Metric as in `plaza2_eval`: RMSE of the 2-D position against every ground-truth row, nearest
//! stamp, no alignment; rows before the first estimate use that first estimate. Dead reckoning
//! starts at the first ground-truth position with the heading of the ground truth's first 0.2 m
//! of travel (the ground truth has no heading).

#[path = "common/mod.rs"]
mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use buoy::{BuoyEntry, Mode, OdometryInput};
use common::RangeEvent;

/// A `range2` line.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Range {
    t_s: f64,
    range_m: f64,
    variance_m2: f64,
    module_xy_m: [f64; 2],
    id: u32,
}

/// An `odom2diff` line: wheel speeds v − b·ω and v + b·ω, b, their variances.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Odom {
    t_s: f64,
    wheel_1_mps: f64,
    wheel_2_mps: f64,
    wheel_base_m: f64,
    var_1: f64,
    var_2: f64,
}

/// One parsed line.
enum Line {
    Range(Range),
    Odom(Odom),
    Point(f64, f64, f64),
}

/// Parses one line; `None` for blank lines and `#` comments. Errors name the column.
fn parse_line(text: &str) -> Result<Option<Line>> {
    let fields: Vec<&str> = text.split_whitespace().collect();
    let Some((&kind, rest)) = fields.split_first() else { return Ok(None) };
    if kind.starts_with('#') {
        return Ok(None);
    }
    let expected = match kind {
        "range2" | "point2" => 7,
        "odom2diff" => 8,
        other => bail!("unknown line type `{other}`"),
    };
    if rest.len() < expected {
        bail!("`{kind}` needs {expected} numbers, got {}", rest.len());
    }
    let mut v = Vec::with_capacity(expected);
    for (i, f) in rest.iter().take(expected).enumerate() {
        let x: f64 = f.parse().with_context(|| format!("column {}: `{f}` is not a number", i + 2))?;
        if !x.is_finite() {
            bail!("column {}: `{f}` is not a finite number", i + 2);
        }
        v.push(x);
    }
    Ok(Some(match kind {
        "range2" => {
            if v[1] < 0.0 || v[2] <= 0.0 {
                bail!("range must be >= 0 and its variance > 0");
            }
            if v[5] < 0.0 || v[5].fract() != 0.0 || v[5] > f64::from(u32::MAX) {
                bail!("column 7: module id `{}` is not a non-negative integer", rest[5]);
            }
            Line::Range(Range {
                t_s: v[0],
                range_m: v[1],
                variance_m2: v[2],
                module_xy_m: [v[3], v[4]],
                id: v[5] as u32,
            })
        }
        "odom2diff" => {
            if v[4] <= 0.0 || v[5] < 0.0 || v[6] < 0.0 {
                bail!("wheel base must be > 0 and variances >= 0");
            }
            Line::Odom(Odom {
                t_s: v[0],
                wheel_1_mps: v[1],
                wheel_2_mps: v[2],
                wheel_base_m: v[4],
                var_1: v[5],
                var_2: v[6],
            })
        }
        _ => Line::Point(v[0], v[1], v[2]),
    }))
}

/// All lines of a file, with `path:line:` on errors.
fn parse_file(path: &Path) -> Result<Vec<Line>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut out = Vec::new();
    for (no, line) in text.lines().enumerate() {
        if let Some(l) = parse_line(line).with_context(|| format!("{}:{}", path.display(), no + 1))? {
            out.push(l);
        }
    }
    Ok(out)
}

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// What to evaluate: the data set's directory and the options of the command line.
pub struct Options {
    /// The directory with `Indoor_UWB_Input.txt` and `Indoor_UWB_GT.txt`.
    pub dir: PathBuf,
    /// EKF settings (TOML) over the defaults.
    pub config: Option<PathBuf>,
    /// Keep only the ranges to these modules.
    pub keep: Option<Vec<u32>>,
    /// Share of the ranges made gross errors.
    pub outliers: f64,
    /// Seed of the gross errors.
    pub outlier_seed: u64,
}

impl Options {
    /// The defaults: the shared data set, every beacon, no added errors.
    pub fn shared() -> Self {
        let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
        Self { dir: root.join("../shared/data/indoor_uwb"), config: None, keep: None, outliers: 0.0, outlier_seed: 1 }
    }
}

/// A finished evaluation: the ground truth, the EKF's run, dead reckoning and the counts.
pub struct Evaluation {
    /// Ground truth `(t, x, y)`.
    pub gt: Vec<(f64, f64, f64)>,
    /// The EKF's run.
    pub run: common::Run,
    /// Dead reckoning `(t, x, y)`.
    pub dr: Vec<(f64, f64, f64)>,
    /// The replay's start, s.
    pub t0_s: f64,
    /// Odometry rows, ranges, ranges made gross errors, beacons.
    pub counts: (usize, usize, usize, usize),
}

impl Evaluation {
    /// The EKF's ATE (RMSE against every ground-truth row, m) and dead reckoning's.
    pub fn ate_m(&self) -> (f64, f64) {
        (common::ate(&self.gt, &self.run.estimates).0, common::ate(&self.gt, &self.dr).0)
    }
}

fn run() -> Result<()> {
    let mut o = Options::shared();
    let mut dump = None;
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        match a.as_str() {
            "--config" => o.config = Some(PathBuf::from(it.next().context("--config needs a file")?)),
            "--dump" => dump = Some(PathBuf::from(it.next().context("--dump needs a file")?)),
            "--beacons" => {
                let list = it.next().context("--beacons needs ids, e.g. 105,107,108")?;
                o.keep = Some(
                    list.split(',')
                        .map(|x| x.parse().with_context(|| format!("--beacons: `{x}`")))
                        .collect::<Result<_>>()?,
                );
            }
            "--outliers" => {
                o.outliers = it.next().context("--outliers needs a share")?.parse().context("--outliers")?;
                if !(0.0..=0.5).contains(&o.outliers) {
                    bail!("--outliers must be in [0, 0.5]");
                }
            }
            "--outlier-seed" => {
                o.outlier_seed =
                    it.next().context("--outlier-seed needs a number")?.parse().context("--outlier-seed")?
            }
            s if s.starts_with("--") => bail!("unknown option {s}"),
            _ => o.dir = a.into(),
        }
    }
    let e = evaluate(&o)?;
    let (odometry, ranges, injected, beacons) = e.counts;
    println!(
        "Indoor UWB ({}): {} ground-truth rows, {odometry} odometry rows, {ranges} ranges ({injected} made gross \
         errors), {beacons} beacons",
        common::tidy(&o.dir).display(),
        e.gt.len(),
    );
    common::report(&e.gt, &e.run, &e.dr, e.t0_s)?;
    if let Some(path) = dump {
        common::dump(&path, &e.gt, &e.run.estimates)?;
    }
    Ok(())
}

/// Replays the data set through the EKF with the options `o`.
pub fn evaluate(o: &Options) -> Result<Evaluation> {
    let (dir, config, keep, outliers, outlier_seed) =
        (&o.dir, o.config.as_deref(), &o.keep, o.outliers, o.outlier_seed);
    let mut ranges = Vec::new();
    let mut odom = Vec::new();
    for line in parse_file(&dir.join("Indoor_UWB_Input.txt"))? {
        match line {
            Line::Range(r) => ranges.push(r),
            Line::Odom(o) => odom.push(o),
            Line::Point(..) => bail!("ground truth in the input file"),
        }
    }
    let mut gt = Vec::new();
    for line in parse_file(&dir.join("Indoor_UWB_GT.txt"))? {
        match line {
            Line::Point(t, x, y) => gt.push((t, x, y)),
            _ => bail!("sensor data in the ground-truth file"),
        }
    }
    for (name, sorted) in [
        ("ranges", ranges.windows(2).all(|w| w[0].t_s <= w[1].t_s)),
        ("odometry", odom.windows(2).all(|w| w[0].t_s < w[1].t_s)),
        ("ground truth", gt.windows(2).all(|w| w[0].0 <= w[1].0)),
    ] {
        if !sorted {
            bail!("{name} are not in time order");
        }
    }
    if ranges.is_empty() || odom.is_empty() || gt.is_empty() {
        bail!("no ranges, odometry or ground truth in {}", dir.display());
    }

    // Beacons: the module positions the ranges carry (must not move).
    let mut modules: BTreeMap<u32, [f64; 2]> = BTreeMap::new();
    for r in &ranges {
        let p = modules.entry(r.id).or_insert(r.module_xy_m);
        if *p != r.module_xy_m {
            bail!("module {} moves from {:?} to {:?}", r.id, p, r.module_xy_m);
        }
    }
    if let Some(k) = &keep {
        if let Some(id) = k.iter().find(|id| !modules.contains_key(id)) {
            bail!("--beacons: module {id} is not in the data set (it has {:?})", modules.keys().collect::<Vec<_>>());
        }
        modules.retain(|id, _| k.contains(id));
        ranges.retain(|r| k.contains(&r.id));
    }
    let mut injected = 0;
    if outliers > 0.0 {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(outlier_seed);
        for r in &mut ranges {
            let (hit, magnitude, negative) =
                (rng.random_bool(outliers), rng.random_range(1.0..=4.0), rng.random_bool(0.5));
            if hit {
                injected += 1;
                r.range_m = if negative && r.range_m - magnitude >= 0.05 {
                    r.range_m - magnitude
                } else {
                    r.range_m + magnitude
                };
            }
        }
    }
    let mut cfg = common::load_config(config)?;
    cfg.mode = Mode::Planar;
    cfg.buoys = modules.iter().map(|(&id, p)| BuoyEntry { id, position_m: [p[0], p[1], 0.0] }).collect();
    cfg.init.min_buoys = cfg.init.min_buoys.min(cfg.buoys.len());

    let first_dt = ranges.get(1).map_or(0.1, |r| r.t_s - ranges[0].t_s);
    let inputs: Vec<(f64, OdometryInput)> = odom
        .iter()
        .enumerate()
        .map(|(i, o)| {
            let dt = if i == 0 { first_dt } else { o.t_s - odom[i - 1].t_s };
            let b = o.wheel_base_m;
            let input = OdometryInput {
                dt_s: dt,
                v_mps: (o.wheel_1_mps + o.wheel_2_mps) / 2.0,
                dtheta_rad: (o.wheel_2_mps - o.wheel_1_mps) / (2.0 * b) * dt,
                var_v: (o.var_1 + o.var_2) / 4.0,
                var_dtheta: (o.var_1 + o.var_2) * dt * dt / (4.0 * b * b),
            };
            (o.t_s, input)
        })
        .collect();

    // Dead reckoning from the first ground-truth position, heading of its first 0.2 m.
    let (t0g, x0, y0) = gt[0];
    let h0 = gt.iter().find(|g| (g.1 - x0).hypot(g.2 - y0) >= 0.2).map_or(0.0, |g| (g.2 - y0).atan2(g.1 - x0));
    let dr = common::dead_reckoning((t0g, x0, y0, h0), &inputs);

    let events: Vec<RangeEvent> = ranges
        .iter()
        .map(|r| RangeEvent { t_s: r.t_s, id: r.id, range_m: r.range_m, sigma_m: r.variance_m2.sqrt() })
        .collect();
    let t0 = (inputs[0].0 - inputs[0].1.dt_s).min(ranges[0].t_s);
    let run = common::replay(cfg, t0, &inputs, &events)?;
    Ok(Evaluation { gt, run, dr, t0_s: t0, counts: (inputs.len(), ranges.len(), injected, modules.len()) })
}

//! `octree_bench`: the `octree` crate's map insertion next to the OctoMap 1.9.7 C++ reference
//! (`shared/bench/octomap`), on the same 20 depth-camera scans (1.22 M points), in the same run.
//!
//! ```sh
//! cargo run --release -p pipeline_bench --bin octree_bench -- [--quick] [--res 0.10,0.05]
//!     [--threads 2] [--reps 3] [--octomap-bench DIR] [--work-dir DIR] [--track-changes]
//! ```
//!
//! Steps: copy the bench folder to the work dir (default `target/octree_bench/`), generate the
//! scans there with `/usr/bin/python3 gen_scene.py --out data` if missing and check their sha256
//! against the folder's README, build `bench_octomap` with the folder's `build.sh` (g++ and
//! liboctomap-dev), then for each repetition (outer loop) and resolution run `bench_octomap
//! --mode eager` (a fresh process; its JSON is read) and our eager insertion in-process (max range
//! 6.0, `--threads` ray-casting threads), alternating which goes first. Reported: best wall and CPU
//! time of insertion, tree memory (plus our insertion scratch buffers, separately), the 1,000,000
//! point queries of `bench_octomap.cpp` (same splitmix64 points; median of passes 2..6 as there,
//! best over repetitions), the leaf hashes, and the voxel agreement with the maps the first C++ run
//! writes (`--write`). Missing prerequisites end the run with exit code 2 and the command to fix
//! them. Not run by `cargo test`: speed is read from the table, the box is shared and noisy.

use std::collections::HashMap;
use std::fmt;
use std::os::unix::fs::PermissionsExt as _;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::Instant;

use anyhow::{Context as _, bail, ensure};
use clap::Parser;
use octree::{OcTree, OcTreeKey, bench_data};
use serde_json::Value;

/// Maximum range of the insertion (the data set's points are all within it).
const MAX_RANGE: f64 = 6.0;
/// Files copied from the bench folder into the work dir.
const BENCH_FILES: [&str; 6] =
    ["README.txt", "bench_octomap.cpp", "build.sh", "check_data.py", "gen_scene.py", "run_bench.py"];
/// Leaf hashes of OctoMap's map of this data set (README / results/summary.md), by resolution.
const EXPECTED_HASHES: [(f64, &str); 2] = [(0.10, "26a7811c8069136f"), (0.05, "23da93c3d38d4aaf")];
/// Number of point queries and the seed of their generator (bench_octomap.cpp).
const QUERIES: usize = 1_000_000;
const QUERY_SEED: u64 = 20240601;
/// Timed query passes; the figure is the median of passes 2..=6 (bench_octomap.cpp).
const QUERY_PASSES: usize = 6;
/// The system Python with numpy from python3-numpy (gen_scene.py needs numpy).
const SYSTEM_PYTHON: &str = "/usr/bin/python3";

#[derive(Parser, Debug)]
#[command(
    name = "octree_bench",
    about = "Insertion speed, memory and point queries of the octree crate next to OctoMap's C++ (same scans, same run)"
)]
struct Args {
    /// OctoMap benchmark folder [default: ../shared/bench/octomap from the workspace root].
    #[arg(long, value_name = "DIR")]
    octomap_bench: Option<PathBuf>,
    /// Work dir (bench copy, data, C++ binaries, maps) [default: target/octree_bench].
    #[arg(long, value_name = "DIR")]
    work_dir: Option<PathBuf>,
    /// Resolutions (m), comma-separated; passed to bench_octomap as written.
    #[arg(long, value_delimiter = ',', default_values_t = ["0.10".to_string(), "0.05".to_string()])]
    res: Vec<String>,
    /// Our ray-casting threads (bench_octomap is single-threaded).
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Repetitions of each run (interleaved); the best is reported.
    #[arg(long, default_value_t = 3)]
    reps: usize,
    /// Smoke run: 1 repetition, 0.10 m only.
    #[arg(long)]
    quick: bool,
    /// Our tree records the changed regions as the octree mapper's does (for its voxel deltas,
    /// `OcTree::track_changes` at depth 11), taken after every scan.
    #[arg(long)]
    track_changes: bool,
}

/// A prerequisite is missing (exit code 2); the message says what and how to install it.
#[derive(Debug)]
struct Missing(String);

impl fmt::Display for Missing {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Missing {}

fn missing(msg: impl Into<String>) -> anyhow::Error {
    anyhow::Error::new(Missing(msg.into()))
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("octree_bench: error: {e:#}");
            if e.downcast_ref::<Missing>().is_some() { ExitCode::from(2) } else { ExitCode::FAILURE }
        }
    }
}

/// One resolution: the string given to bench_octomap and its value.
struct Res {
    text: String,
    value: f64,
}

impl Res {
    /// `%.2f`, as in the C++ bench's file names.
    fn file_tag(&self) -> String {
        format!("{:.2}", self.value)
    }
    fn expected_hash(&self) -> Option<&'static str> {
        EXPECTED_HASHES.iter().find(|(r, _)| (r - self.value).abs() < 1e-12).map(|(_, h)| *h)
    }
}

fn run(mut args: Args) -> anyhow::Result<()> {
    if args.quick {
        args.reps = 1;
        args.res = vec!["0.10".into()];
    }
    ensure!(args.reps >= 1, "--reps must be at least 1");
    ensure!(args.threads >= 1, "--threads must be at least 1");
    let resolutions = args
        .res
        .iter()
        .map(|t| {
            let value: f64 = t.trim().parse().with_context(|| format!("--res: `{t}` is not a number"))?;
            ensure!(value.is_finite() && value > 0.0, "--res: {t} must be > 0");
            Ok(Res { text: t.trim().to_string(), value })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    ensure!(!resolutions.is_empty(), "--res names no resolution");

    let root = workspace_root();
    let bench_dir = args.octomap_bench.clone().unwrap_or_else(|| root.join("../shared/bench/octomap"));
    let work = args.work_dir.clone().unwrap_or_else(|| root.join("target/octree_bench"));
    let load_before = load_average();
    eprintln!("octree_bench: OctoMap bench folder {}", bench_dir.display());
    eprintln!("octree_bench: work dir {}", work.display());

    let cpp_changed = prepare_work_dir(&bench_dir, &work)?;
    let scans_path = ensure_scans(&work)?;
    let cpp_bin = build_cpp(&work, cpp_changed)?;
    let scene_path = work.join("data/scene.txt");
    let maps_dir = work.join("maps");
    std::fs::create_dir_all(&maps_dir).with_context(|| format!("creating {}", maps_dir.display()))?;

    eprintln!("octree_bench: loading {}", scans_path.display());
    let scans = bench_data::read_scans(&scans_path).with_context(|| format!("reading {}", scans_path.display()))?;
    let points = scans.num_points();
    let queries = query_points();

    let runs =
        Interleaved { args: &args, scans: &scans, scans_path: &scans_path, scene_path: &scene_path, cpp_bin: &cpp_bin };
    let (cpp_runs, our_runs, first_trees) = runs.run(&resolutions, &maps_dir, &queries)?;
    let load_after = load_average();

    let cpus = std::thread::available_parallelism().map_or(0, |n| n.get());
    println!();
    println!(
        "octree_bench: {} frames, {points} points, max range {MAX_RANGE} m, eager insertion; best of {} interleaved \
         run(s) each; {cpus} CPUs",
        scans.frames.len(),
        args.reps
    );
    let version = cpp_runs.iter().flatten().next().map_or("?", |c| c.version.as_str());
    println!(
        "ours: octree crate, {} ray-casting thread(s), in-process; OctoMap: bench_octomap (liboctomap-dev {version}, \
         -O3, single-threaded), one process per run",
        args.threads
    );
    let mut all_agree = true;
    for (i, res) in resolutions.iter().enumerate() {
        let tree = first_trees[i].as_ref().context("no run of ours")?;
        let agreement = compare_maps(tree, &maps_dir, res);
        all_agree &= print_table(res, points, &cpp_runs[i], &our_runs[i], &agreement);
    }
    println!();
    println!(
        "load average (1/5/15 min) before: {load_before}, after: {load_after} on {cpus} CPUs; the box is shared: \
         compare CPU seconds if it was busy"
    );
    if !all_agree {
        println!("WARNING: the maps do not agree (see above)");
    }
    Ok(())
}

/// The timed runs: per repetition and resolution, OctoMap's C++ bench and ours, the order
/// alternating between repetitions (a machine that slows down does not favour one side).
struct Interleaved<'a> {
    args: &'a Args,
    scans: &'a bench_data::ScanFile,
    scans_path: &'a Path,
    scene_path: &'a Path,
    cpp_bin: &'a Path,
}

/// The C++ runs, our runs, and our first tree, per resolution.
type Runs = (Vec<Vec<CppRun>>, Vec<Vec<OurRun>>, Vec<Option<OcTree>>);

impl Interleaved<'_> {
    fn run(&self, resolutions: &[Res], maps_dir: &Path, queries: &[[f32; 3]]) -> anyhow::Result<Runs> {
        let mut cpp_runs: Vec<Vec<CppRun>> = resolutions.iter().map(|_| Vec::new()).collect();
        let mut our_runs: Vec<Vec<OurRun>> = resolutions.iter().map(|_| Vec::new()).collect();
        let mut first_trees: Vec<Option<OcTree>> = resolutions.iter().map(|_| None).collect();
        for rep in 0..self.args.reps {
            for (i, res) in resolutions.iter().enumerate() {
                let tag = format!("[rep {}/{}] res {} m", rep + 1, self.args.reps, res.text);
                // The first C++ run of a resolution also writes its maps (after everything timed).
                let write = if rep == 0 { Some(maps_dir) } else { None };
                let cpp_first = rep % 2 == 0;
                for side in if cpp_first { [true, false] } else { [false, true] } {
                    if side {
                        eprintln!("{tag}: OctoMap bench_octomap ...");
                        let c = run_cpp(self.cpp_bin, self.scans_path, self.scene_path, res, write)?;
                        eprintln!(
                            "{tag}: OctoMap insert {:.3} s (CPU {:.3} s), {:.0} k points/s, query {:.1} ns",
                            c.insert_s,
                            c.insert_cpu_s,
                            self.scans.num_points() as f64 / c.insert_s / 1e3,
                            c.query_point_ns
                        );
                        cpp_runs[i].push(c);
                    } else {
                        eprintln!("{tag}: ours ({} ray threads) ...", self.args.threads);
                        let (o, tree) =
                            run_ours(self.scans, res.value, self.args.threads, self.args.track_changes, queries)?;
                        eprintln!(
                            "{tag}: ours insert {:.3} s (CPU {:.3} s), {:.0} k points/s, query {:.1} ns",
                            o.insert_s,
                            o.insert_cpu_s,
                            self.scans.num_points() as f64 / o.insert_s / 1e3,
                            o.query_point_ns
                        );
                        if first_trees[i].is_none() {
                            first_trees[i] = Some(tree);
                        }
                        our_runs[i].push(o);
                    }
                }
            }
        }
        Ok((cpp_runs, our_runs, first_trees))
    }
}

// ---------------------------------------------------------------------------------------- setup

/// The workspace root: from the compile-time manifest dir, else the nearest ancestor of the
/// current dir holding a `[workspace]` Cargo.toml, else the current dir.
fn workspace_root() -> PathBuf {
    let compiled = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../..");
    if compiled.join("Cargo.toml").is_file() {
        return compiled.canonicalize().unwrap_or(compiled);
    }
    let cwd = std::env::current_dir().unwrap_or_else(|_| PathBuf::from("."));
    for dir in cwd.ancestors() {
        if let Ok(text) = std::fs::read_to_string(dir.join("Cargo.toml"))
            && text.contains("[workspace]")
        {
            return dir.to_path_buf();
        }
    }
    cwd
}

/// Copies the bench folder's files into `work` (writable copies; the folder is read-only).
/// Returns whether a C++ build input changed (or the binary is missing).
fn prepare_work_dir(bench: &Path, work: &Path) -> anyhow::Result<bool> {
    if !bench.is_dir() {
        return Err(missing(format!(
            "OctoMap bench folder {} not found: pass --octomap-bench DIR (the project's shared/bench/octomap)",
            bench.display()
        )));
    }
    std::fs::create_dir_all(work).with_context(|| format!("creating {}", work.display()))?;
    let mut changed = !work.join("bench_octomap").is_file();
    for name in BENCH_FILES {
        let src = bench.join(name);
        let dst = work.join(name);
        let bytes = std::fs::read(&src).map_err(|e| {
            missing(format!(
                "{} is missing from the OctoMap bench folder ({e}); pass --octomap-bench DIR",
                src.display()
            ))
        })?;
        if std::fs::read(&dst).ok().as_deref() == Some(bytes.as_slice()) {
            continue;
        }
        if name == "bench_octomap.cpp" || name == "build.sh" {
            changed = true;
        }
        let _ = std::fs::remove_file(&dst);
        std::fs::write(&dst, &bytes).with_context(|| format!("writing {}", dst.display()))?;
        let exec = std::fs::metadata(&src)?.permissions().mode() & 0o111 != 0;
        std::fs::set_permissions(&dst, std::fs::Permissions::from_mode(if exec { 0o755 } else { 0o644 }))?;
    }
    eprintln!("octree_bench: bench files copied to {}", work.display());
    Ok(changed)
}

/// The expected sha256 of `scans.bin` from the README (`sha256 <64 hex digits>`).
fn expected_sha256(readme: &str) -> Option<String> {
    readme.split_whitespace().collect::<Vec<_>>().windows(2).find_map(|w| {
        (w[0] == "sha256" && w[1].len() == 64 && w[1].chars().all(|c| c.is_ascii_hexdigit()))
            .then(|| w[1].to_ascii_lowercase())
    })
}

/// Generates `data/scans.bin` in `work` if missing and checks its sha256 against the README.
fn ensure_scans(work: &Path) -> anyhow::Result<PathBuf> {
    let scans = work.join("data/scans.bin");
    if !scans.is_file() || !work.join("data/scene.txt").is_file() {
        if !Path::new(SYSTEM_PYTHON).is_file() {
            return Err(missing(format!(
                "{SYSTEM_PYTHON} not found (needed to generate the scans): apt-get install -y python3 python3-numpy"
            )));
        }
        let numpy = Command::new(SYSTEM_PYTHON).args(["-c", "import numpy"]).output()?;
        if !numpy.status.success() {
            return Err(missing(format!(
                "{SYSTEM_PYTHON} cannot import numpy (needed by gen_scene.py): apt-get install -y python3-numpy"
            )));
        }
        eprintln!(
            "octree_bench: generating the scans: {SYSTEM_PYTHON} gen_scene.py --out data (in {})",
            work.display()
        );
        let out = Command::new(SYSTEM_PYTHON)
            .args(["gen_scene.py", "--out", "data"])
            .current_dir(work)
            .output()
            .context("running gen_scene.py")?;
        if !out.status.success() {
            bail!(
                "gen_scene.py failed ({}):\n{}{}",
                out.status,
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
    }
    let readme = std::fs::read_to_string(work.join("README.txt"))?;
    let want = expected_sha256(&readme).context("README.txt names no sha256 of scans.bin")?;
    let out = Command::new("sha256sum")
        .arg(&scans)
        .output()
        .map_err(|e| missing(format!("sha256sum not runnable ({e}): apt-get install -y coreutils")))?;
    ensure!(out.status.success(), "sha256sum {} failed: {}", scans.display(), String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    let got = text.split_whitespace().next().unwrap_or("");
    ensure!(
        got == want,
        "{} has sha256 {got}, the README says {want}: delete {} and rerun to regenerate it",
        scans.display(),
        work.join("data").display()
    );
    eprintln!("octree_bench: {} sha256 {got} (matches the README)", scans.display());
    Ok(scans)
}

/// Builds the C++ bench with the folder's build.sh (if a source changed or it is missing).
fn build_cpp(work: &Path, changed: bool) -> anyhow::Result<PathBuf> {
    let bin = work.join("bench_octomap");
    if !changed && bin.is_file() {
        eprintln!("octree_bench: using the built {}", bin.display());
        return Ok(bin);
    }
    if Command::new("g++").arg("--version").output().map(|o| !o.status.success()).unwrap_or(true) {
        return Err(missing("g++ not found (needed to build bench_octomap): apt-get install -y g++ liboctomap-dev"));
    }
    let dev = Command::new("dpkg-query").args(["-W", "-f=${Status}", "liboctomap-dev"]).output();
    let installed = dev.map(|o| String::from_utf8_lossy(&o.stdout).contains("install ok installed")).unwrap_or(false);
    if !installed || !Path::new("/usr/include/octomap/octomap.h").is_file() {
        return Err(missing(
            "liboctomap-dev is not installed (OctoMap 1.9.7 headers and library): apt-get install -y liboctomap-dev",
        ));
    }
    eprintln!("octree_bench: building the C++ bench: sh build.sh (in {}; about a minute) ...", work.display());
    let out = Command::new("sh").arg("build.sh").current_dir(work).output().context("running build.sh")?;
    if !out.status.success() {
        bail!(
            "build.sh failed ({}):\n{}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        eprintln!("  {line}");
    }
    ensure!(bin.is_file(), "build.sh succeeded but {} does not exist", bin.display());
    Ok(bin)
}

/// `/proc/loadavg`'s 1, 5 and 15 minute load averages.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

/// CPU time of the whole process (all threads), s.
fn process_cpu_s() -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: ts is a valid, writable timespec; CLOCK_PROCESS_CPUTIME_ID always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 + 1e-9 * ts.tv_nsec as f64
}

// ------------------------------------------------------------------------------------------ C++

/// What one `bench_octomap --mode eager` process reported.
struct CppRun {
    version: String,
    insert_s: f64,
    insert_cpu_s: f64,
    post_s: f64,
    nodes: u64,
    leaves: u64,
    occupied_leaves: u64,
    free_leaves: u64,
    memory: u64,
    leaf_hash: String,
    query_point_ns: f64,
    query_point_cpu_ns: f64,
    query_key_ns: f64,
    query_found: u64,
    query_occupied: u64,
}

fn run_cpp(bin: &Path, scans: &Path, scene: &Path, res: &Res, write: Option<&Path>) -> anyhow::Result<CppRun> {
    let mut cmd = Command::new(bin);
    cmd.arg("--data").arg(scans).arg("--scene").arg(scene);
    cmd.args(["--res", &res.text, "--mode", "eager", "--maxrange", &MAX_RANGE.to_string()]);
    if let Some(dir) = write {
        cmd.arg("--write").arg("--out").arg(dir);
    }
    let out = cmd.output().with_context(|| format!("starting {}", bin.display()))?;
    if !out.status.success() {
        bail!("{} failed ({}): {}", bin.display(), out.status, String::from_utf8_lossy(&out.stderr));
    }
    let v: Value = serde_json::from_slice(&out.stdout)
        .with_context(|| format!("bench_octomap printed no JSON: {}", String::from_utf8_lossy(&out.stdout)))?;
    let num = |k: &str| v.get(k).and_then(Value::as_f64).with_context(|| format!("bench_octomap JSON lacks `{k}`"));
    let int = |k: &str| v.get(k).and_then(Value::as_u64).with_context(|| format!("bench_octomap JSON lacks `{k}`"));
    let text = |k: &str| {
        v.get(k).and_then(Value::as_str).map(str::to_string).with_context(|| format!("bench_octomap JSON lacks `{k}`"))
    };
    Ok(CppRun {
        version: text("octomap_version")?,
        insert_s: num("insert_s")?,
        insert_cpu_s: num("insert_cpu_s")?,
        post_s: num("updateInner_s")? + num("prune_s")?,
        nodes: int("nodes")?,
        leaves: int("leaf_nodes")?,
        occupied_leaves: int("occupied_leafs")?,
        free_leaves: int("free_leafs")?,
        memory: int("memoryUsage_bytes")?,
        leaf_hash: text("leaf_hash")?,
        query_point_ns: num("query_point_ns")?,
        query_point_cpu_ns: num("query_point_cpu_ns")?,
        query_key_ns: num("query_key_ns")?,
        query_found: int("query_found")?,
        query_occupied: int("query_occupied")?,
    })
}

// ----------------------------------------------------------------------------------------- ours

/// One run of ours.
struct OurRun {
    insert_s: f64,
    insert_cpu_s: f64,
    post_s: f64,
    nodes: u64,
    leaves: u64,
    occupied_leaves: u64,
    free_leaves: u64,
    /// Tree memory as built (arena capacity).
    memory: u64,
    /// Tree memory after `shrink_to_fit`.
    memory_shrunk: u64,
    /// Insertion scratch buffers (hash sets, code lists) before `shrink_to_fit`.
    scratch: u64,
    leaf_hash: String,
    query_point_ns: f64,
    query_point_cpu_ns: f64,
    query_key_ns: f64,
    query_found: u64,
    query_occupied: u64,
}

/// bench_octomap.cpp's query points: splitmix64 (seed 20240601) uniform in the room's bounding box
/// grown by 0.5 m, computed in `f64` and converted to `f32`.
fn query_points() -> Vec<[f32; 3]> {
    let mut s = QUERY_SEED;
    let mut u01 = || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    };
    let lo = [0.021 - 0.5, 0.013 - 0.5, 0.017 - 0.5];
    let hi = [10.021 + 0.5, 6.013 + 0.5, 3.017 + 0.5];
    (0..QUERIES)
        .map(|_| {
            let x = lo[0] + (hi[0] - lo[0]) * u01();
            let y = lo[1] + (hi[1] - lo[1]) * u01();
            let z = lo[2] + (hi[2] - lo[2]) * u01();
            [x as f32, y as f32, z as f32]
        })
        .collect()
}

/// Median of passes 2..=n (bench_octomap.cpp's `median_tail`).
fn median_tail(v: &[f64]) -> f64 {
    let mut w = v[1..].to_vec();
    w.sort_by(f64::total_cmp);
    w[w.len() / 2]
}

fn run_ours(
    scans: &bench_data::ScanFile,
    res: f64,
    threads: usize,
    track_changes: bool,
    queries: &[[f32; 3]],
) -> anyhow::Result<(OurRun, OcTree)> {
    let mut tree = OcTree::new(res)?;
    tree.set_ray_threads(threads);
    if track_changes {
        tree.track_changes(11)?;
    }
    let cpu0 = process_cpu_s();
    let t0 = Instant::now();
    for f in &scans.frames {
        tree.insert_point_cloud(&f.points, f.origin, MAX_RANGE, false)?;
        if track_changes {
            std::hint::black_box(tree.take_changes());
        }
    }
    let insert_s = t0.elapsed().as_secs_f64();
    let insert_cpu_s = process_cpu_s() - cpu0;
    let t1 = Instant::now();
    tree.update_inner_occupancy();
    tree.prune();
    let post_s = t1.elapsed().as_secs_f64();
    let memory = tree.memory_usage_bytes() as u64;
    let scratch = tree.scratch_bytes() as u64;
    tree.shrink_to_fit();
    let memory_shrunk = tree.memory_usage_bytes() as u64;
    let (occupied_leaves, free_leaves) = tree.num_occupied_free_leaves();

    let keys: Vec<OcTreeKey> = queries
        .iter()
        .map(|q| tree.coord_to_key(*q))
        .collect::<Option<_>>()
        .context("a query point is outside the tree")?;
    let (mut tp, mut tpc, mut tk) = (Vec::new(), Vec::new(), Vec::new());
    let (mut found, mut occupied) = (0u64, 0u64);
    for _ in 0..QUERY_PASSES {
        (found, occupied) = (0, 0);
        let c0 = process_cpu_s();
        let a = Instant::now();
        for q in queries {
            if let Some(l) = tree.search(*q) {
                found += 1;
                occupied += tree.is_occupied_log_odds(l) as u64;
            }
        }
        let b = Instant::now();
        let c1 = process_cpu_s();
        let (mut found2, mut occupied2) = (0u64, 0u64);
        for k in &keys {
            if let Some(l) = tree.search_key(*k) {
                found2 += 1;
                occupied2 += tree.is_occupied_log_odds(l) as u64;
            }
        }
        let c = Instant::now();
        ensure!((found, occupied) == (found2, occupied2), "key and point queries disagree");
        let per = |d: f64| d * 1e9 / queries.len() as f64;
        tp.push(per((b - a).as_secs_f64()));
        tpc.push(per(c1 - c0));
        tk.push(per((c - b).as_secs_f64()));
    }
    let run = OurRun {
        insert_s,
        insert_cpu_s,
        post_s,
        nodes: tree.num_nodes() as u64,
        leaves: tree.num_leaves() as u64,
        occupied_leaves: occupied_leaves as u64,
        free_leaves: free_leaves as u64,
        memory,
        memory_shrunk,
        scratch,
        leaf_hash: format!("{:016x}", tree.leaf_hash()),
        query_point_ns: median_tail(&tp),
        query_point_cpu_ns: median_tail(&tpc),
        query_key_ns: median_tail(&tk),
        query_found: found,
        query_occupied: occupied,
    };
    Ok((run, tree))
}

// ------------------------------------------------------------------------------------ agreement

/// Finest-level voxel agreement of our map with the maps OctoMap's first run wrote.
struct Agreement {
    /// Occupied voxels: ours, OctoMap's (voxel dump, log-odds), in both, in both with equal log-odds.
    occupied: Option<(u64, u64, u64, u64)>,
    /// Free voxels: ours, OctoMap's (.bt, max-likelihood), in both.
    free: Option<(u64, u64, u64)>,
    /// Whether our `.bt` bytes equal OctoMap's `writeBinary` output.
    bt_identical: Option<bool>,
    /// Problems reading OctoMap's files.
    errors: Vec<String>,
}

/// Finest-level voxels of a tree (pruned leaves expanded): packed key → log-odds.
fn expand(tree: &OcTree) -> HashMap<u64, f32> {
    let mut m = HashMap::new();
    for l in tree.leaves() {
        let k0 = l.min_key();
        let n = l.edge_voxels() as u16;
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    m.insert(OcTreeKey([k0.0[0] + i, k0.0[1] + j, k0.0[2] + k]).pack(), l.log_odds);
                }
            }
        }
    }
    m
}

fn compare_maps(ours: &OcTree, maps: &Path, res: &Res) -> Agreement {
    let mut a = Agreement { occupied: None, free: None, bt_identical: None, errors: Vec::new() };
    let vox = expand(ours);
    let ours_occ = vox.values().filter(|l| ours.is_occupied_log_odds(**l)).count() as u64;
    let ours_free = vox.len() as u64 - ours_occ;

    let dump = maps.join(format!("occupied_voxels_res{}.bin", res.file_tag()));
    match bench_data::read_occupied_voxels(&dump) {
        Ok(theirs) => {
            let (mut both, mut same) = (0, 0);
            for v in &theirs {
                if let Some(l) = vox.get(&v.key.pack())
                    && ours.is_occupied_log_odds(*l)
                {
                    both += 1;
                    same += (l.to_bits() == v.log_odds.to_bits()) as u64;
                }
            }
            a.occupied = Some((ours_occ, theirs.len() as u64, both, same));
        }
        Err(e) => a.errors.push(format!("{}: {e}", dump.display())),
    }
    let bt = maps.join(format!("octomap_res{}.bt", res.file_tag()));
    match (OcTree::read_binary_file(&bt), std::fs::read(&bt)) {
        (Ok(theirs), Ok(bytes)) => {
            let tv = expand(&theirs);
            let theirs_free = tv.values().filter(|l| !theirs.is_occupied_log_odds(**l)).count() as u64;
            let both = tv
                .iter()
                .filter(|(k, l)| {
                    !theirs.is_occupied_log_odds(**l) && vox.get(k).is_some_and(|o| !ours.is_occupied_log_odds(*o))
                })
                .count() as u64;
            a.free = Some((ours_free, theirs_free, both));
            let mut mine = Vec::new();
            a.bt_identical = Some(ours.write_binary(&mut mine).is_ok() && mine == bytes);
        }
        (Err(e), _) => a.errors.push(format!("{}: {e}", bt.display())),
        (_, Err(e)) => a.errors.push(format!("{}: {e}", bt.display())),
    }
    a
}

// ---------------------------------------------------------------------------------------- table

fn best(v: impl Iterator<Item = f64>) -> f64 {
    v.fold(f64::INFINITY, f64::min)
}

fn goal(met: bool) -> &'static str {
    if met { "met" } else { "MISSED" }
}

fn pct(part: u64, whole: u64) -> f64 {
    if whole == 0 { 100.0 } else { 100.0 * part as f64 / whole as f64 }
}

/// Prints one resolution's table; returns whether hashes and voxels agree.
fn print_table(res: &Res, points: usize, cpp: &[CppRun], ours: &[OurRun], agr: &Agreement) -> bool {
    let (c0, o0) = (&cpp[0], &ours[0]);
    let c_ins = best(cpp.iter().map(|r| r.insert_s));
    let o_ins = best(ours.iter().map(|r| r.insert_s));
    let c_cpu = best(cpp.iter().map(|r| r.insert_cpu_s));
    let o_cpu = best(ours.iter().map(|r| r.insert_cpu_s));
    let c_post = best(cpp.iter().map(|r| r.post_s));
    let o_post = best(ours.iter().map(|r| r.post_s));
    let c_q = best(cpp.iter().map(|r| r.query_point_ns));
    let o_q = best(ours.iter().map(|r| r.query_point_ns));
    let c_qc = best(cpp.iter().map(|r| r.query_point_cpu_ns));
    let o_qc = best(ours.iter().map(|r| r.query_point_cpu_ns));
    let c_k = best(cpp.iter().map(|r| r.query_key_ns));
    let o_k = best(ours.iter().map(|r| r.query_key_ns));
    let (c_rate, o_rate) = (points as f64 / c_ins, points as f64 / o_ins);
    let (c_cpu_rate, o_cpu_rate) = (points as f64 / c_cpu, points as f64 / o_cpu);

    println!();
    println!("== resolution {} m ({} run(s) each)", res.text, cpp.len().min(ours.len()));
    println!("{:<40} {:>18} {:>18} {:>12}  goal", "metric", "ours", "OctoMap", "ours/OctoMap");
    let row = |name: &str, o: String, c: String, ratio: Option<f64>, g: &str| {
        let r = ratio.map_or(String::new(), |r| format!("{r:.2}x"));
        println!("{name:<40} {o:>18} {c:>18} {r:>12}  {g}");
    };
    let rate_goal = format!(">= 2x  {}", goal(o_rate / c_rate >= 2.0));
    row("insert points/s (wall, best)", mpts(o_rate), mpts(c_rate), Some(o_rate / c_rate), &rate_goal);
    row("insert wall s (best)", format!("{o_ins:.3}"), format!("{c_ins:.3}"), Some(o_ins / c_ins), "");
    row("insert CPU s (best; all threads)", format!("{o_cpu:.3}"), format!("{c_cpu:.3}"), Some(o_cpu / c_cpu), "");
    row("insert points per CPU-s", mpts(o_cpu_rate), mpts(c_cpu_rate), Some(o_cpu_rate / c_cpu_rate), "");
    row("update_inner + prune after, ms", format!("{:.2}", o_post * 1e3), format!("{:.2}", c_post * 1e3), None, "");
    let mem_goal = format!("<= 1x  {}", goal(o0.memory <= c0.memory));
    row(
        "tree memory, bytes (as built)",
        o0.memory.to_string(),
        c0.memory.to_string(),
        Some(o0.memory as f64 / c0.memory as f64),
        &mem_goal,
    );
    row(
        "  tree after shrink_to_fit",
        o0.memory_shrunk.to_string(),
        "".into(),
        Some(o0.memory_shrunk as f64 / c0.memory as f64),
        "",
    );
    row("  + insertion scratch buffers", o0.scratch.to_string(), "not counted".into(), None, "");
    let q_goal = format!("<= 1x  {}", goal(o_q <= c_q));
    row("point query ns (1M, median pass, best)", format!("{o_q:.1}"), format!("{c_q:.1}"), Some(o_q / c_q), &q_goal);
    row("  CPU ns per point query", format!("{o_qc:.1}"), format!("{c_qc:.1}"), Some(o_qc / c_qc), "");
    row("  key query ns (keys precomputed)", format!("{o_k:.1}"), format!("{c_k:.1}"), Some(o_k / c_k), "");
    row(
        "  queries found / occupied",
        format!("{} / {}", o0.query_found, o0.query_occupied),
        format!("{} / {}", c0.query_found, c0.query_occupied),
        None,
        if (o0.query_found, o0.query_occupied) == (c0.query_found, c0.query_occupied) { "equal" } else { "DIFFER" },
    );
    row("nodes / leaves", format!("{} / {}", o0.nodes, o0.leaves), format!("{} / {}", c0.nodes, c0.leaves), None, "");
    row(
        "occupied / free leaves",
        format!("{} / {}", o0.occupied_leaves, o0.free_leaves),
        format!("{} / {}", c0.occupied_leaves, c0.free_leaves),
        None,
        "",
    );
    let hashes_stable =
        ours.iter().all(|r| r.leaf_hash == o0.leaf_hash) && cpp.iter().all(|r| r.leaf_hash == c0.leaf_hash);
    let expected = res.expected_hash();
    let hash_ok = o0.leaf_hash == c0.leaf_hash && hashes_stable && expected.is_none_or(|h| h == c0.leaf_hash);
    let hash_note = format!(
        "{}{}",
        if hash_ok { "agree" } else { "DIFFER" },
        expected.map_or(String::new(), |h| format!(" (expected {h})"))
    );
    row("leaf hash", o0.leaf_hash.clone(), c0.leaf_hash.clone(), None, &hash_note);

    hash_ok && print_agreement(agr)
}

/// The maps' voxel agreement (ours against OctoMap's); true when they agree in every voxel.
fn print_agreement(agr: &Agreement) -> bool {
    let mut voxels_ok = true;
    if let Some((o, c, both, same)) = agr.occupied {
        let union = o + c - both;
        voxels_ok &= both == union && same == both;
        println!(
            "{:<40} {:.4} % ({both} in both of {union}; ours {o}, OctoMap {c}; log-odds bit-identical in {same})",
            "occupied voxels agreement",
            pct(both, union)
        );
    }
    if let Some((o, c, both)) = agr.free {
        let union = o + c - both;
        voxels_ok &= both == union;
        println!(
            "{:<40} {:.4} % ({both} in both of {union}; ours {o}, OctoMap {c})",
            "free voxels agreement",
            pct(both, union)
        );
    }
    if let Some(same) = agr.bt_identical {
        voxels_ok &= same;
        println!("{:<40} {}", ".bt bytes identical to OctoMap's", if same { "yes" } else { "NO" });
    }
    for e in &agr.errors {
        voxels_ok = false;
        println!("voxel agreement not checked: {e}");
    }
    voxels_ok
}

/// Points per second as `x.xxx M/s`.
fn mpts(rate: f64) -> String {
    format!("{:.3} M/s", rate / 1e6)
}

//! FastSLAM throughput benchmark: frames/s and per-frame time (p50/p99) for N particles × M prior
//! landmarks × 50 observations per frame on 2 worker threads, against the goals
//! "N = 1000, M = 10k at ≥ 60 frames/s" and "time(M = 100k) ≤ 2 × time(M = 1k)" (the shared
//! copy-on-write maps should grow per-frame cost logarithmically in M, not linearly).
//!
//! Run: `cargo run --release -p fastslam --example fastslam_bench`
//! (options: `--n 100,1000 --m 1000,10000,100000 --frames 60 --warmup 10 --threads 2`).
//!
//! Set-up per (N, M): `set_prior_map` with M landmarks uniformly at random in a cube whose volume
//! gives [`LANDMARKS_PER_SEARCH_SPHERE`] landmarks on average within `association.search_radius_m`
//! of any point (the same density for every M: only the map size changes), each with a random,
//! distinct 256-bit descriptor and a small covariance. The true vehicle drives a circle in the
//! middle of the cube; each frame is an odometry `predict` (the noiseless input; the filter adds its
//! input and process noise) and an `update` with 50 observations of landmarks within
//! [`SENSOR_RANGE_M`] of the true pose: body-frame positions plus Gaussian noise, each with its
//! landmark's descriptor (a few bits flipped). Every observation should be a landmark EKF update
//! with weight (the table's `match%` column checks it). Only `predict` + `update` are timed.
//!
//! Reference floors measured in the same run: (a) one landmark EKF update with weight
//! (`ekf::innovation` + `ekf::update` + `log_likelihood`) in a tight loop, × 50·N / threads;
//! (b) deep-copying M landmarks (`Vec<LandmarkEkf>::clone`) × N: what resampling would cost if
//! every particle had its own map.
//!
//! Memory: the process's peak RSS (VmHWM of /proc/self/status, reset before each configuration
//! through /proc/self/clear_refs when the kernel allows it) and the RSS after the timed frames.

use std::hint::black_box;
use std::time::{Duration, Instant};

use fastslam::ekf::{self, LandmarkEkf};
use fastslam::{FastSlam, FastSlamConfig, Observation, PriorLandmark, Proposal};
use geometry::{ProcessInput, propagate};
use nalgebra::{Isometry3, Matrix3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;

/// Observations per frame.
const OBS_PER_FRAME: usize = 50;
/// Mean number of landmarks within the association search radius of a point.
const LANDMARKS_PER_SEARCH_SPHERE: f64 = 3.0;
/// Landmarks farther than this from the true pose are not observed, m.
const SENSOR_RANGE_M: f64 = 10.0;
/// Frame interval, s.
const DT_S: f64 = 0.1;
/// Forward speed, m/s.
const SPEED_MPS: f64 = 0.5;
/// Radius of the driven circle, m.
const CIRCLE_RADIUS_M: f64 = 5.0;
/// Centre of the landmark field and of the driven circle (which starts at the origin), m.
const CENTRE: Vector3<f64> = Vector3::new(0.0, CIRCLE_RADIUS_M, 0.0);
/// Observation noise σ per body axis, m.
const OBS_SIGMA_M: f64 = 0.05;
/// Prior landmark position σ per axis, m.
const PRIOR_SIGMA_M: f64 = 0.03;
/// Odometry input variances (v in (m/s)², δθ in rad²) handed to `predict`.
const INPUT_VARIANCES: [f64; 4] = [0.05 * 0.05, 0.001 * 0.001, 0.001 * 0.001, 0.002 * 0.002];
/// The goal: frames/s at N = 1000, M = 10k.
const GOAL_FPS: f64 = 60.0;
/// The goal: time(M = 100k) / time(M = 1k).
const GOAL_RATIO: f64 = 2.0;

struct Options {
    particles: Vec<usize>,
    landmarks: Vec<usize>,
    frames: usize,
    warmup: usize,
    threads: usize,
}

fn parse_list(s: &str) -> Vec<usize> {
    s.split(',').map(|x| x.trim().parse().unwrap_or_else(|_| panic!("not a number: {x}"))).collect()
}

fn options() -> Options {
    let mut o = Options {
        particles: vec![100, 1000],
        landmarks: vec![1000, 10_000, 100_000],
        frames: 60,
        warmup: 10,
        threads: 2,
    };
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let value = it.next().unwrap_or_else(|| panic!("{flag} needs a value"));
        match flag.as_str() {
            "--n" => o.particles = parse_list(value),
            "--m" => o.landmarks = parse_list(value),
            "--frames" => o.frames = parse_list(value)[0].max(1),
            "--warmup" => o.warmup = parse_list(value)[0],
            "--threads" => o.threads = parse_list(value)[0].max(1),
            _ => panic!("unknown option {flag} (--n, --m, --frames, --warmup, --threads)"),
        }
    }
    o
}

/// The value of a `Vm*` line of /proc/self/status, kB.
fn proc_status_kb(key: &str) -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines().find(|l| l.starts_with(key))?.split_whitespace().nth(1)?.parse().ok()
}

/// Resets the peak RSS to the current RSS (Linux ≥ 4.0); false when not allowed.
fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

fn mib(kb: Option<u64>) -> String {
    kb.map_or("?".into(), |k| format!("{:.0}", k as f64 / 1024.0))
}

fn normal3(rng: &mut Xoshiro256PlusPlus) -> Vector3<f64> {
    Vector3::new(StandardNormal.sample(rng), StandardNormal.sample(rng), StandardNormal.sample(rng))
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// One random landmark field for every configuration: uniform points at the benchmark density in a
/// cube around [`CENTRE`] large enough to hold a ball of `m_max` of them, sorted by distance from
/// the centre, each with a random 256-bit descriptor. Configuration M takes the first M: a ball
/// whose inside (where the vehicle drives and looks) is the same for every M.
fn landmark_field(m_max: usize, search_radius_m: f64) -> Vec<(Vector3<f64>, [u8; 32])> {
    let sphere = 4.0 / 3.0 * std::f64::consts::PI * search_radius_m.powi(3);
    let density = LANDMARKS_PER_SEARCH_SPHERE / sphere;
    let ball_r = (3.0 * m_max as f64 / (4.0 * std::f64::consts::PI * density)).cbrt();
    let side = 2.0 * ball_r * 1.02;
    let count = (density * side.powi(3)).ceil() as usize;
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(42);
    let mut field: Vec<(Vector3<f64>, [u8; 32])> = (0..count)
        .map(|_| {
            let u = Vector3::new(rng.random::<f64>(), rng.random::<f64>(), rng.random::<f64>()) - Vector3::repeat(0.5);
            let mut d = [0u8; 32];
            rng.fill(&mut d[..]);
            (CENTRE + u * side, d)
        })
        .collect();
    field.sort_by(|a, b| (a.0 - CENTRE).norm_squared().total_cmp(&(b.0 - CENTRE).norm_squared()));
    field.truncate(m_max);
    field
}

/// The prior map of configuration M: the M innermost points of the field in random order (so the
/// landmarks seen in one frame have ids spread over 0..M: no locality for the map's trie), and the
/// ball's radius.
fn prior_map(field: &[(Vector3<f64>, [u8; 32])], m: usize) -> (Vec<PriorLandmark>, f64) {
    let cov = Matrix3::identity() * PRIOR_SIGMA_M * PRIOR_SIGMA_M;
    let mut lms: Vec<PriorLandmark> = field[..m].iter().map(|(p, d)| (*p, cov, Some(*d))).collect();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(m as u64);
    for i in (1..lms.len()).rev() {
        lms.swap(i, rng.random_range(0..=i));
    }
    let radius = field[..m].last().map_or(0.0, |(p, _)| (p - CENTRE).norm());
    (lms, radius)
}

/// True landmarks near a point: a uniform grid of buckets over the ball's bounding cube
/// (benchmark side, untimed).
struct Buckets {
    cell: f64,
    n: i64,
    origin: Vector3<f64>,
    cells: Vec<Vec<u32>>,
}

impl Buckets {
    fn new(lms: &[PriorLandmark], ball_radius_m: f64) -> Self {
        let cell = SENSOR_RANGE_M;
        let side = 2.0 * ball_radius_m + 1e-6;
        let n = (side / cell).ceil().max(1.0) as i64;
        let origin = CENTRE - Vector3::repeat(side / 2.0);
        let mut b = Self { cell, n, origin, cells: vec![vec![]; (n * n * n) as usize] };
        for (i, (p, _, _)) in lms.iter().enumerate() {
            let k = b.index(b.coords(p));
            b.cells[k].push(i as u32);
        }
        b
    }

    fn coords(&self, p: &Vector3<f64>) -> [i64; 3] {
        let c = |x: f64, o: f64| (((x - o) / self.cell).floor() as i64).clamp(0, self.n - 1);
        [c(p.x, self.origin.x), c(p.y, self.origin.y), c(p.z, self.origin.z)]
    }

    fn index(&self, c: [i64; 3]) -> usize {
        (c[0] + self.n * (c[1] + self.n * c[2])) as usize
    }

    /// Landmark indices in the 27 buckets around `p`: every landmark within `cell` of `p`.
    fn around(&self, p: &Vector3<f64>) -> impl Iterator<Item = u32> + '_ {
        let c = self.coords(p);
        (-1..=1)
            .flat_map(move |dz| (-1..=1).flat_map(move |dy| (-1..=1).map(move |dx| [c[0] + dx, c[1] + dy, c[2] + dz])))
            .filter(|q| q.iter().all(|v| (0..self.n).contains(v)))
            .flat_map(|q| self.cells[self.index(q)].iter().copied())
    }

    /// Indices of the landmarks within `r` of `p` (r ≤ cell).
    fn near(&self, lms: &[PriorLandmark], p: &Vector3<f64>, r: f64, out: &mut Vec<u32>) {
        out.clear();
        out.extend(self.around(p).filter(|&i| (lms[i as usize].0 - p).norm() <= r));
    }

    /// How many landmarks the filter's association grid (cells of side `search_m`, the 27 cells
    /// around the point's cell) offers as candidates for a point at `p` (3·search_m ≤ cell).
    fn candidates(&self, lms: &[PriorLandmark], p: &Vector3<f64>, search_m: f64) -> usize {
        let key = |v: &Vector3<f64>| v.map(|x| (x / search_m).floor());
        let k = key(p);
        self.around(p).filter(|&i| (key(&lms[i as usize].0) - k).amax() <= 1.0).count()
    }
}

/// One configuration's measurements.
struct Row {
    n: usize,
    m: usize,
    threads: usize,
    frames: usize,
    p50_ms: f64,
    p99_ms: f64,
    fps: f64,
    predict_ms: f64,
    update_ms: f64,
    match_pct: f64,
    unmatched: usize,
    resample_pct: f64,
    candidates: f64,
    setup_s: f64,
    rss_mib: String,
    peak_mib: String,
}

fn run(n: usize, m: usize, field: &[(Vector3<f64>, [u8; 32])], opt: &Options, peak_reset: bool) -> Row {
    let cfg = FastSlamConfig {
        particles: n,
        threads: opt.threads,
        proposal: Proposal::Motion,
        seed: 7,
        ..Default::default()
    };
    let radius = cfg.association.search_radius_m;
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(42);
    let t_setup = Instant::now();
    let (lms, ball_radius) = prior_map(field, m);
    let buckets = Buckets::new(&lms, ball_radius);
    let mut f = FastSlam::new(cfg).expect("valid config");
    f.set_prior_map(&lms);
    let setup_s = t_setup.elapsed().as_secs_f64();
    // The filter's particles start at the identity, as does the true vehicle: it drives a circle
    // (left turn) around the cube's centre (0, CIRCLE_RADIUS_M, 0).
    let mut truth = Isometry3::identity();

    let input = ProcessInput {
        v_mps: SPEED_MPS,
        delta_theta_rad: Vector3::new(0.0, 0.0, SPEED_MPS / CIRCLE_RADIUS_M * DT_S),
        dt_s: DT_S,
    };
    let rz = Matrix3::identity() * OBS_SIGMA_M * OBS_SIGMA_M;
    let mut near = vec![];
    let total = opt.warmup + opt.frames;
    let (mut times, mut predict_s, mut update_s) = (Vec::with_capacity(opt.frames), 0.0, 0.0);
    let (mut matched, mut unmatched, mut resampled, mut candidates) = (0usize, 0usize, 0usize, 0usize);
    for k in 0..total {
        truth = propagate(&truth, &input);
        // 50 landmarks within sensor range of the true pose, observed with noise.
        buckets.near(&lms, &truth.translation.vector, SENSOR_RANGE_M, &mut near);
        assert!(near.len() >= OBS_PER_FRAME, "only {} landmarks in range", near.len());
        // In position order, so that every M with the same landmarks in range sees the same frames.
        near.sort_by(|a, b| lms[*a as usize].0.x.total_cmp(&lms[*b as usize].0.x));
        for i in 0..OBS_PER_FRAME {
            let j = rng.random_range(i..near.len());
            near.swap(i, j);
        }
        let obs: Vec<Observation> = near[..OBS_PER_FRAME]
            .iter()
            .map(|&i| {
                let (p, _, d) = &lms[i as usize];
                let mut d = d.expect("descriptor");
                for _ in 0..4 {
                    let bit = rng.random_range(0..256usize);
                    d[bit / 8] ^= 1 << (bit % 8);
                }
                // Noise truncated at 2.5 σ (χ²₃ 6.25, inside the 11.34 gate): every observation
                // associates, none is left out as ambiguous or becomes a new landmark.
                let noise = loop {
                    let v = normal3(&mut rng);
                    if v.norm_squared() <= 6.25 {
                        break v * OBS_SIGMA_M;
                    }
                };
                let z = ekf::predict_measurement(&truth, p) + noise;
                Observation { z_m: z, Rz: rz, descriptor: Some(d) }
            })
            .collect();
        if k >= opt.warmup {
            for o in &obs {
                candidates += buckets.candidates(&lms, &truth.transform_point(&o.z_m.into()).coords, radius);
            }
        }
        let t0 = Instant::now();
        f.predict(&input, INPUT_VARIANCES).expect("finite input");
        let t1 = Instant::now();
        let r = f.update(&obs);
        let t2 = Instant::now();
        assert!(r.new_segment.is_none(), "the benchmark must stay in one local map: {:?}", r.new_segment);
        if k >= opt.warmup {
            times.push((t2 - t0).as_secs_f64() * 1e3);
            predict_s += (t1 - t0).as_secs_f64();
            update_s += (t2 - t1).as_secs_f64();
            matched += r.matched;
            unmatched += r.new + r.ambiguous;
            resampled += usize::from(r.resampled);
        }
    }
    let total_s: f64 = times.iter().sum::<f64>() / 1e3;
    times.sort_by(f64::total_cmp);
    let frames = times.len();
    let row = Row {
        n,
        m,
        threads: opt.threads,
        frames,
        p50_ms: percentile(&times, 0.5),
        p99_ms: percentile(&times, 0.99),
        fps: frames as f64 / total_s,
        predict_ms: predict_s * 1e3 / frames as f64,
        update_ms: update_s * 1e3 / frames as f64,
        match_pct: 100.0 * matched as f64 / (frames * OBS_PER_FRAME) as f64,
        unmatched,
        resample_pct: 100.0 * resampled as f64 / frames as f64,
        candidates: candidates as f64 / (frames * OBS_PER_FRAME) as f64,
        setup_s,
        rss_mib: mib(proc_status_kb("VmRSS:")),
        peak_mib: if peak_reset { mib(proc_status_kb("VmHWM:")) } else { "-".into() },
    };
    drop(f);
    row
}

/// Which part of the landmark EKF update with weight [`ekf_ns`] times.
#[derive(Clone, Copy, PartialEq)]
enum EkfPart {
    /// `ekf::innovation` alone (what association pays per candidate).
    Innovation,
    /// Innovation + `log_likelihood`.
    WithWeight,
    /// Innovation + `log_likelihood` + `ekf::update`: one matched observation.
    Full,
}

/// (a) ns per call of `part` over 64 landmarks and poses in turn (best of 5 runs).
fn ekf_ns(part: EkfPart) -> f64 {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(5);
    let rz = Matrix3::identity() * OBS_SIGMA_M * OBS_SIGMA_M;
    let poses: Vec<Isometry3<f64>> =
        (0..64).map(|_| Isometry3::new(normal3(&mut rng), normal3(&mut rng) * 0.3)).collect();
    let fresh: Vec<LandmarkEkf> = (0..64)
        .map(|_| LandmarkEkf {
            mean_m: normal3(&mut rng) * 5.0,
            cov_m2: Matrix3::identity() * PRIOR_SIGMA_M * PRIOR_SIGMA_M,
            descriptor: None,
            hits: 2,
            last_seen_frame: 0,
        })
        .collect();
    let zs: Vec<Vector3<f64>> = fresh
        .iter()
        .zip(&poses)
        .map(|(l, p)| ekf::predict_measurement(p, &l.mean_m) + normal3(&mut rng) * OBS_SIGMA_M)
        .collect();
    let mut lms = fresh.clone();
    let mut best = f64::INFINITY;
    let iters = 200_000;
    for _ in 0..5 {
        lms.clone_from(&fresh);
        let t = Instant::now();
        let mut acc = 0.0;
        for i in 0..iters {
            let k = i & 63;
            let (pose, z) = (black_box(&poses[k]), black_box(&zs[k]));
            let lm = &mut lms[k];
            if let Ok(inn) = ekf::innovation(pose, lm, z, &rz) {
                acc += match part {
                    EkfPart::Innovation => inn.mahalanobis,
                    _ => inn.log_likelihood(),
                };
                if part == EkfPart::Full {
                    let _ = ekf::update(lm, pose, &inn, &rz);
                }
            }
        }
        black_box(acc);
        best = best.min(t.elapsed().as_secs_f64() * 1e9 / iters as f64);
    }
    best
}

/// (b) ms to deep-copy a `Vec<LandmarkEkf>` of length m (best of a few).
fn copy_map_ms(m: usize) -> f64 {
    let v: Vec<LandmarkEkf> = (0..m)
        .map(|i| LandmarkEkf {
            mean_m: Vector3::new(i as f64, 0.0, 0.0),
            cov_m2: Matrix3::identity(),
            descriptor: Some([i as u8; 32]),
            hits: 2,
            last_seen_frame: 0,
        })
        .collect();
    let reps = (2_000_000 / m).clamp(5, 200);
    let mut best = Duration::MAX;
    for _ in 0..reps {
        let t = Instant::now();
        let c = black_box(v.clone());
        drop(black_box(c));
        best = best.min(t.elapsed());
    }
    best.as_secs_f64() * 1e3
}

fn main() {
    let opt = options();
    let peak_reset = reset_peak_rss();
    let (inn_ns, weight_ns, ekf_full_ns) =
        (ekf_ns(EkfPart::Innovation), ekf_ns(EkfPart::WithWeight), ekf_ns(EkfPart::Full));
    let copy_1k = copy_map_ms(1000);
    let copy_100k = copy_map_ms(100_000);
    let cfg = FastSlamConfig::default();
    let field = landmark_field(opt.landmarks.iter().copied().max().unwrap_or(1), cfg.association.search_radius_m);

    println!(
        "FastSLAM benchmark: {OBS_PER_FRAME} observations/frame (all of prior landmarks), proposal motion, {} threads, \
         {} timed frames after {} warm-up; landmarks at {LANDMARKS_PER_SEARCH_SPHERE} per search sphere (r = {} m), \
         observed within {SENSOR_RANGE_M} m; times are predict + update.",
        opt.threads, opt.frames, opt.warmup, cfg.association.search_radius_m
    );
    println!(
        "match% = observations the best particle matched; unm = observations not matched (new or ambiguous; \
         should be 0); resmp% = frames that resampled; cand = association candidates per observation."
    );
    println!();
    println!(
        "{:>5} {:>7} {:>3} {:>6} {:>8} {:>8} {:>8} {:>7} {:>8} {:>6} {:>4} {:>6} {:>5} {:>7} {:>7} {:>8}  goal",
        "N",
        "M",
        "thr",
        "frames",
        "p50 ms",
        "p99 ms",
        "frames/s",
        "pred ms",
        "upd ms",
        "match%",
        "unm",
        "resmp%",
        "cand",
        "setup s",
        "RSS MiB",
        "peak MiB"
    );
    let mut rows = vec![];
    for &n in &opt.particles {
        for &m in &opt.landmarks {
            let peak_reset = reset_peak_rss() && peak_reset;
            let r = run(n, m, &field, &opt, peak_reset);
            let goal = if n == 1000 && m == 10_000 {
                format!("≥{GOAL_FPS:.0} frames/s: {}", if r.fps >= GOAL_FPS { "PASS" } else { "FAIL" })
            } else {
                String::new()
            };
            println!(
                "{:>5} {:>7} {:>3} {:>6} {:>8.2} {:>8.2} {:>8.1} {:>7.2} {:>8.2} {:>6.1} {:>4} {:>6.0} {:>5.1} {:>7.2} {:>7} {:>8}  {goal}",
                r.n,
                r.m,
                r.threads,
                r.frames,
                r.p50_ms,
                r.p99_ms,
                r.fps,
                r.predict_ms,
                r.update_ms,
                r.match_pct,
                r.unmatched,
                r.resample_pct,
                r.candidates,
                r.setup_s,
                r.rss_mib,
                r.peak_mib,
            );
            rows.push(r);
        }
    }
    println!();
    println!("Scaling in M (goal: p50(M = 100k) / p50(M = 1k) ≤ {GOAL_RATIO}×):");
    for &n in &opt.particles {
        let at = |m: usize| rows.iter().find(|r| r.n == n && r.m == m).map(|r| r.p50_ms);
        if let (Some(a), Some(b)) = (at(1000), at(100_000)) {
            let ratio = b / a;
            println!(
                "  N = {n:>5}: {b:.2} ms / {a:.2} ms = {ratio:.2}×  {}",
                if ratio <= GOAL_RATIO { "PASS" } else { "FAIL" }
            );
        }
    }
    println!();
    println!("Reference floors (single thread, tight loop):");
    println!(
        "  (a) one landmark EKF update with weight: {ekf_full_ns:.1} ns (innovation alone {inn_ns:.1} ns, \
         + log-likelihood {weight_ns:.1} ns, + update {ekf_full_ns:.1} ns); × {OBS_PER_FRAME}·N / {} threads:",
        opt.threads
    );
    for &n in &opt.particles {
        let floor_ms = ekf_full_ns * (OBS_PER_FRAME * n) as f64 / opt.threads as f64 / 1e6;
        let measured = rows.iter().filter(|r| r.n == n).map(|r| r.p50_ms).fold(f64::INFINITY, f64::min);
        let cand = rows.iter().filter(|r| r.n == n).map(|r| r.candidates).fold(0.0, f64::max);
        let assoc_ms = inn_ns * cand * (OBS_PER_FRAME * n) as f64 / opt.threads as f64 / 1e6;
        println!(
            "      N = {n:>5}: floor {floor_ms:.3} ms/frame ({:.0} frames/s); best measured p50 {measured:.2} ms = \
             {:.1}× the floor; one innovation per association candidate ({cand:.1}/observation) alone: {assoc_ms:.2} ms",
            1e3 / floor_ms,
            measured / floor_ms
        );
    }
    println!(
        "  (b) a map copied per particle (Vec<LandmarkEkf>::clone, {} B per landmark): {copy_1k:.4} ms for M = 1k, \
         {copy_100k:.3} ms for M = 100k ({:.0}×); one resampling that copies every map:",
        std::mem::size_of::<LandmarkEkf>(),
        copy_100k / copy_1k
    );
    for &n in &opt.particles {
        println!(
            "      N = {n:>5}: {:.2} ms at M = 1k, {:.1} ms at M = 100k",
            copy_1k * n as f64,
            copy_100k * n as f64
        );
    }
    if !peak_reset {
        println!("(peak RSS not reset per configuration: /proc/self/clear_refs not writable)");
    }
}

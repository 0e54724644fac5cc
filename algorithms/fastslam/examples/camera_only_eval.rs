//! Camera-only tracking, measured: the stereo front end alone (frame-to-frame registration, its
//! motions chained) against FastSLAM with the front end as its motion input: without source
//! track ids (associating by the front end's own feature tracks, the default, and by maximum
//! likelihood alone) and with the source's track ids, on
//! - `stereo_vo [DIR]`: real features in the stereo_vo format (default
//!   `../shared/data/stereo_vo_large`, KITTI, read in place: it may not be committed), against
//!   the data set's own VO poses or `--reference FILE.tum` (stamps `frame_id / 10`);
//! - `road`: the KITTI-like simulated drive (`sim::road`) against its ground truth, with the
//!   position NEES of the filter's covariance.
//!
//! `cargo run --release -p fastslam --example camera_only_eval -- stereo_vo [DIR] [--reference F] [--particles N] [--frames]`
//! `cargo run --release -p fastslam --example camera_only_eval -- road [--seed S] [--seeds K] [--length FRAMES] [--particles N] [--frames]`
//! (both also `--proposal motion|optimal`, FastSLAM 1.0 or 2.0; `road` also takes the drive's
//! warts: `--pixel-sigma PX`, `--wrong-matches FRACTION`, `--wrong-tracks FRACTION`,
//! `--dropped-frames PROBABILITY`, or `--clean` for none; the simulator checks the values).
//!
//! Per run: RMSE of the positions after the best rigid alignment (Horn/Umeyama), the end-point
//! difference after aligning the first poses (% of the reference path length), time per frame
//! (p50, max), frames without a registered motion, and for FastSLAM on the drive the mean
//! position NEES (consistent: ≈ 3, inside χ²₃'s 95 % interval [0.22, 9.35]) and the share of
//! poses inside that interval. `--frames` prints every frame.

use std::collections::BTreeMap;
use std::time::Instant;

use fastslam::eval::{CHI2_3_95, TrajectorySample, evaluate, weighted_mean};
use fastslam::frontend::{Frame, FrontEnd, FrontEndConfig, RegistrationError};
use fastslam::{CameraOnly, FastSlam, FastSlamConfig, Observation};
use geometry::{StereoPixels, StereoRig};
use nalgebra::{Isometry3, Vector3};

#[derive(Clone)]
struct Args {
    source: String,
    dir: String,
    particles: usize,
    reference: Option<String>,
    frames: bool,
    seed: u64,
    seeds: u64,
    length: usize,
    proposal: fastslam::Proposal,
    /// Overrides of the simulated drive's warts (`--pixel-sigma`, `--wrong-matches`,
    /// `--wrong-tracks`, `--dropped-frames`, `--clean`).
    pixel_sigma_px: Option<f64>,
    wrong_match_fraction: Option<f64>,
    wrong_track_fraction: Option<f64>,
    dropped_frame_probability: Option<f64>,
    clean: bool,
}

fn parse() -> Result<Args, String> {
    let mut a = Args {
        source: String::new(),
        dir: "../shared/data/stereo_vo_large".into(),
        particles: 100,
        reference: None,
        frames: false,
        seed: 1,
        seeds: 1,
        length: 400,
        proposal: fastslam::Proposal::default(),
        pixel_sigma_px: None,
        wrong_match_fraction: None,
        wrong_track_fraction: None,
        dropped_frame_probability: None,
        clean: false,
    };
    let mut it = std::env::args().skip(1);
    let num = |v: Option<String>, what: &str| v.and_then(|v| v.parse().ok()).ok_or(format!("{what} needs a number"));
    let real =
        |v: Option<String>, what: &str| v.and_then(|v| v.parse::<f64>().ok()).ok_or(format!("{what} needs a number"));
    while let Some(x) = it.next() {
        match x.as_str() {
            "--particles" => a.particles = num(it.next(), "--particles")?,
            "--seed" => a.seed = num(it.next(), "--seed")? as u64,
            "--seeds" => a.seeds = (num(it.next(), "--seeds")? as u64).max(1),
            "--length" => a.length = num(it.next(), "--length")?,
            "--reference" => a.reference = Some(it.next().ok_or("--reference needs a file")?),
            "--frames" => a.frames = true,
            "--pixel-sigma" => a.pixel_sigma_px = Some(real(it.next(), "--pixel-sigma")?),
            "--wrong-matches" => a.wrong_match_fraction = Some(real(it.next(), "--wrong-matches")?),
            "--wrong-tracks" => a.wrong_track_fraction = Some(real(it.next(), "--wrong-tracks")?),
            "--dropped-frames" => a.dropped_frame_probability = Some(real(it.next(), "--dropped-frames")?),
            "--clean" => a.clean = true,
            "--proposal" => {
                a.proposal = match it.next().as_deref() {
                    Some("motion") => fastslam::Proposal::Motion,
                    Some("optimal") => fastslam::Proposal::Optimal,
                    _ => return Err("--proposal motion|optimal".into()),
                }
            }
            "stereo_vo" | "road" if a.source.is_empty() => a.source = x,
            s if !s.starts_with("--") && a.source == "stereo_vo" => a.dir = s.to_string(),
            s => return Err(format!("unexpected argument `{s}` (usage: stereo_vo [DIR] ... | road ...)")),
        }
    }
    if a.source.is_empty() {
        return Err("name a source: `stereo_vo [DIR]` or `road`".into());
    }
    Ok(a)
}

/// One input: frames of observations (body frame) with and without track ids, the extrinsic,
/// the reference trajectory and whether it is ground truth.
struct Input {
    name: String,
    frames: Vec<(f64, Vec<Observation>)>,
    body_from_camera: Isometry3<f64>,
    reference: Vec<(f64, Isometry3<f64>)>,
    truth: bool,
}

fn stereo_vo(args: &Args, ids: bool) -> Result<Input, String> {
    let vo = datasets::StereoVo::load(&args.dir)
        .map_err(|e| format!("{e} (the data set may not be committed: point to it in ../shared/data)"))?;
    let c = vo.calibration;
    let rig = StereoRig {
        f_px: c.fx_px,
        cx_px: c.cx_px,
        cy_px: c.cy_px,
        baseline_m: c.baseline_m,
        width_px: (2.0 * c.cx_px).ceil() as u32,
        height_px: (2.0 * c.cy_px).ceil() as u32,
    };
    let frames = datasets::group_by_frame(&vo.factors)
        .iter()
        .map(|fr| {
            let obs = fr
                .observations
                .iter()
                .filter_map(|o| {
                    let px = StereoPixels { u_left_px: o.u_left_px, u_right_px: o.u_right_px, v_px: o.v_px };
                    let cov = rig.triangulation_covariance(&px, 0.5).ok()?;
                    let mut ob =
                        Observation::from_camera(&Vector3::from(o.point_cam_m), &cov, None, &Isometry3::identity())
                            .ok()?;
                    ob.track_id = ids.then_some(o.landmark_id);
                    Some(ob)
                })
                .collect();
            (fr.frame_id as f64 / 10.0, obs)
        })
        .collect();
    let reference = match &args.reference {
        Some(f) => fastslam::eval::read_tum(std::path::Path::new(f)).map_err(|e| format!("{f}: {e}"))?,
        None => vo
            .poses
            .iter()
            .map(|p| {
                let m = p.world_from_camera;
                let rot = nalgebra::Rotation3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned());
                (
                    p.frame_id as f64 / 10.0,
                    Isometry3::from_parts(
                        nalgebra::Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
                        nalgebra::UnitQuaternion::from_rotation_matrix(&rot),
                    ),
                )
            })
            .collect(),
    };
    Ok(Input {
        name: format!("{} ({} observations)", args.dir, vo.factors.len()),
        frames,
        body_from_camera: Isometry3::identity(),
        reference,
        truth: args.reference.is_some(),
    })
}

fn road(args: &Args, ids: bool) -> Result<Input, String> {
    let mut cfg = sim::road::RoadConfig { seed: args.seed, frames: args.length, ..Default::default() };
    if args.clean {
        cfg.wrong_match_fraction = 0.0;
        cfg.spurious_fraction = 0.0;
        cfg.wrong_track_fraction = 0.0;
        cfg.dropped_frame_probability = 0.0;
    }
    if let Some(v) = args.pixel_sigma_px {
        cfg.pixel_sigma_px = v;
    }
    if let Some(v) = args.wrong_match_fraction {
        cfg.wrong_match_fraction = v;
    }
    if let Some(v) = args.wrong_track_fraction {
        cfg.wrong_track_fraction = v;
    }
    if let Some(v) = args.dropped_frame_probability {
        cfg.dropped_frame_probability = v;
    }
    let mut sim = sim::road::RoadSim::new(cfg).map_err(|e| e.to_string())?;
    let b = sim.body_from_camera();
    let mut frames = vec![];
    for f in sim.by_ref() {
        let obs = f
            .observations
            .iter()
            .filter_map(|o| {
                let mut ob = Observation::from_camera(&o.point_cam_m, &o.covariance_cam_m2, None, &b).ok()?;
                ob.track_id = ids.then_some(o.track_id);
                Some(ob)
            })
            .collect();
        frames.push((f.t_s, obs));
    }
    Ok(Input {
        name: format!(
            "simulated drive (seed {}, {} frames, {} dropped, {:.0} m)",
            args.seed,
            args.length,
            sim.dropped(),
            sim.path_length_m()
        ),
        frames,
        body_from_camera: b,
        reference: sim.truth().iter().map(|t| (t.t_s, t.world_from_body)).collect(),
        truth: true,
    })
}

struct Score {
    rmse_m: f64,
    end_pct: f64,
    path_m: f64,
}

fn score(est: &[(f64, Isometry3<f64>)], reference: &[(f64, Isometry3<f64>)]) -> Option<Score> {
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = est
        .iter()
        .filter_map(|(t, p)| {
            fastslam::eval::nearest(reference, *t).map(|r| (p.translation.vector, r.translation.vector))
        })
        .collect();
    if pairs.len() < 3 {
        return None;
    }
    let src: Vec<_> = pairs.iter().map(|p| p.0).collect();
    let dst: Vec<_> = pairs.iter().map(|p| p.1).collect();
    let a = geometry::align_rigid(&src, &dst, &vec![1.0; src.len()])?;
    let se: f64 = src.iter().zip(&dst).map(|(s, d)| (a.transform_point(&(*s).into()).coords - d).norm_squared()).sum();
    let path_m: f64 = dst.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    let r0 = fastslam::eval::nearest(reference, est[0].0)?;
    let r1 = fastslam::eval::nearest(reference, est.last()?.0)?;
    let rel_est = est[0].1.inverse() * est.last()?.1;
    let end = (rel_est.translation.vector - (r0.inverse() * r1).translation.vector).norm();
    Some(Score { rmse_m: (se / src.len() as f64).sqrt(), end_pct: 100.0 * end / path_m.max(1e-9), path_m })
}

fn percentiles(times: &[f64]) -> (f64, f64, f64) {
    let mut t = times.to_vec();
    t.sort_by(f64::total_cmp);
    let q = |p: f64| t.get(((t.len().max(1) - 1) as f64 * p).round() as usize).copied().unwrap_or(f64::NAN);
    (q(0.5), q(0.99), q(1.0))
}

/// One line of the table.
#[derive(Clone, Default)]
struct Row {
    rmse_m: f64,
    end_pct: f64,
    path_m: f64,
    times: Vec<f64>,
    failed: usize,
    /// Mean position NEES, the share of poses inside χ²₃'s 95 % interval, and the poses scored.
    nees: Option<(f64, f64, usize)>,
}

fn main() {
    let args = match parse() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("camera_only_eval: {e}");
            std::process::exit(2);
        }
    };
    println!(
        "{:<36} {:>8} {:>8} {:>7} {:>8} {:>8} {:>8} {:>7} {:>7} {:>6} {:>5}",
        "run", "RMSE m", "end %", "path m", "p50 ms", "p99 ms", "max ms", "failed", "NEESp", "in95", "B-S"
    );
    let seeds: Vec<u64> = if args.source == "road" { (args.seed..args.seed + args.seeds).collect() } else { vec![0] };
    let mut all: Vec<(String, Vec<Row>)> = vec![];
    for &seed in &seeds {
        for ids in [false, true] {
            let a = Args { seed, ..args.clone() };
            let input = match if a.source == "road" { road(&a, ids) } else { stereo_vo(&a, ids) } {
                Ok(i) => i,
                Err(e) => {
                    eprintln!("camera_only_eval: {e}");
                    std::process::exit(2);
                }
            };
            if !ids {
                println!(
                    "# {}: {} frames; reference: {}",
                    input.name,
                    input.frames.len(),
                    if input.truth { "ground truth" } else { "the data set's VO poses" }
                );
            }
            // Without source ids FastSLAM runs twice: with the front end's own feature tracks
            // (the default) and by maximum likelihood alone (`assign_tracks = false`).
            let modes: &[(&str, bool)] =
                if ids { &[("source ids", true)] } else { &[("front-end tracks", true), ("max. likelihood", false)] };
            let mut rows = vec![];
            for (k, (mode, assign)) in modes.iter().enumerate() {
                let (fe, slam) = run(&input, &a, *assign);
                if k == 0 {
                    rows.push((format!("front end{}", if ids { ", source ids" } else { "" }), fe));
                }
                rows.push((format!("fastslam N={}, {mode}", a.particles), slam));
            }
            for (name, row) in rows {
                print_row(&name, &row);
                match all.iter_mut().find(|(n, _)| *n == name) {
                    Some((_, v)) => v.push(row),
                    None => all.push((name, vec![row])),
                }
            }
        }
    }
    if seeds.len() > 1 {
        println!("# mean over {} seeds (times pooled)", seeds.len());
        for (name, rows) in &all {
            let n = rows.len() as f64;
            let mean = |f: &dyn Fn(&Row) -> f64| rows.iter().map(f).sum::<f64>() / n;
            let row = Row {
                rmse_m: mean(&|r| r.rmse_m),
                end_pct: mean(&|r| r.end_pct),
                path_m: mean(&|r| r.path_m),
                times: rows.iter().flat_map(|r| r.times.clone()).collect(),
                failed: rows.iter().map(|r| r.failed).sum(),
                nees: rows[0].nees.map(|_| {
                    // Pooled over every pose of every seed.
                    let n: usize = rows.iter().filter_map(|r| r.nees.map(|x| x.2)).sum();
                    let pooled = |f: &dyn Fn(&(f64, f64, usize)) -> f64| {
                        rows.iter().filter_map(|r| r.nees.as_ref()).map(|x| f(x) * x.2 as f64).sum::<f64>()
                            / n.max(1) as f64
                    };
                    (pooled(&|x| x.0), pooled(&|x| x.1), n)
                }),
            };
            print_row(name, &row);
        }
    }
    println!(
        "(NEESp: mean position NEES over the poses (3 for a consistent filter); in95: share of poses inside χ²₃'s 95 % \
         interval [{:.2}, {:.2}]; B-S: the mean inside Bar-Shalom's 95 % interval for a mean of n χ²₃ samples \
         (n = poses; 390 poses: [2.76, 3.25]), or below (covariance too large) or above it (too small))",
        CHI2_3_95.0, CHI2_3_95.1
    );
}

/// The front end alone and FastSLAM on one input.
fn run(input: &Input, args: &Args, assign_tracks: bool) -> (Row, Row) {
    let b = input.body_from_camera;
    // The front end alone, its motions chained.
    let mut fe = FrontEnd::new(FrontEndConfig::default());
    let mut pose = Isometry3::identity();
    let mut traj = vec![];
    let mut times = vec![];
    let mut failed = 0;
    let mut last_t: Option<f64> = None;
    for (t, obs) in &input.frames {
        let dt = last_t.map_or(0.0, |l| t - l);
        last_t = Some(*t);
        let t0 = Instant::now();
        let r = fe.register(Frame::from_observations(obs, &b), dt);
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        match r {
            Ok(r) => {
                pose *= b * r.prev_from_cur * b.inverse();
                if args.frames {
                    println!(
                        "  front end t={t:.1}: {:?} {} inliers of {:?}, {:.1} candidates/point, χ²/dof {:.2}",
                        r.method, r.inliers, r.points, r.candidates_per_point, r.chi2_per_dof
                    );
                }
            }
            Err(RegistrationError::FirstFrame) => {}
            Err(e) => {
                failed += 1;
                println!("  front end t={t:.1}: {e}");
            }
        }
        if args.frames
            && input.truth
            && let Some(e) = truth_error(input, *t, &pose)
        {
            println!("  front end t={t:.1}: error {e}");
        }
        traj.push((*t, pose));
    }
    let fe_row = row(&traj, &input.reference, times, failed, None);
    // FastSLAM with the front end as its motion input.
    let cfg = FastSlamConfig { particles: args.particles, proposal: args.proposal, ..Default::default() };
    let mut f = FastSlam::new(cfg).expect("valid settings");
    let mut cam = CameraOnly::new(FrontEndConfig { assign_tracks, ..Default::default() }, b);
    let mut traj = vec![];
    let mut samples = vec![];
    let mut origins = BTreeMap::new();
    let mut times = vec![];
    let mut failed = 0;
    let mut last_t: Option<f64> = None;
    for (t, obs) in &input.frames {
        let dt = last_t.map_or(0.0, |l| t - l);
        if last_t.is_none() {
            origins.insert(0, *t);
        }
        last_t = Some(*t);
        let t0 = Instant::now();
        let mut obs = obs.clone();
        let m = cam.predict(&mut f, &mut obs, dt);
        let obs = &obs;
        let r = f.update(obs);
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        if let Err(e) = &m.registration
            && !matches!(e, RegistrationError::FirstFrame)
        {
            failed += 1;
            println!("  fastslam t={t:.1}: {e}");
        }
        if r.new_segment.is_some() {
            origins.insert(f.segment(), *t);
        }
        let e = f.estimate();
        if args.frames {
            println!(
                "  fastslam t={t:.1}: matched {} new {} rejected {} N_eff {:.1} candidates/obs {:.2} NIS {:.2} σp {:.3} m",
                r.matched,
                r.new,
                r.rejected,
                r.n_eff,
                r.candidates_per_observation,
                r.mean_nis,
                e.covariance.fixed_view::<3, 3>(0, 0).trace().sqrt()
            );
        }
        if args.frames
            && input.truth
            && let Some(err) = truth_error(input, *t, &e.map_from_body)
        {
            let nees = fastslam::eval::nearest(&input.reference, input.frames[0].0)
                .zip(fastslam::eval::nearest(&input.reference, *t))
                .and_then(|(r0, rt)| {
                    let d = e.map_from_body.translation.vector - (r0.inverse() * rt).translation.vector;
                    let c = e.covariance.fixed_view::<3, 3>(0, 0).into_owned();
                    c.try_inverse().map(|ci| d.dot(&(ci * d)))
                })
                .unwrap_or(f64::NAN);
            println!("  fastslam t={t:.1}: error {err}, position NEES {nees:.1}");
        }
        traj.push((*t, e.map_from_body));
        samples.push(TrajectorySample {
            t_s: *t,
            segment: f.segment(),
            map_from_body: e.map_from_body,
            covariance: e.covariance,
        });
    }
    let nees = input.truth.then(|| {
        let scores = evaluate(&samples, &input.reference, &origins);
        let n = scores.iter().map(|s| s.samples).sum();
        (weighted_mean(&scores, |s| s.nees_position), weighted_mean(&scores, |s| s.nees_position_in_95), n)
    });
    (fe_row, row(&traj, &input.reference, times, failed, nees))
}

/// The error of `est` (in the frame of the first pose) against the reference at `t`: position
/// (x, y, z, m) and rotation (deg).
fn truth_error(input: &Input, t: f64, est: &Isometry3<f64>) -> Option<String> {
    let r0 = fastslam::eval::nearest(&input.reference, input.frames.first()?.0)?;
    let rt = fastslam::eval::nearest(&input.reference, t)?;
    let rel = r0.inverse() * rt;
    let d = est.translation.vector - rel.translation.vector;
    let r = (rel.inverse() * est).rotation.angle().to_degrees();
    Some(format!("position ({:+.3}, {:+.3}, {:+.3}) m, rotation {r:.3}°", d.x, d.y, d.z))
}

fn row(
    traj: &[(f64, Isometry3<f64>)],
    reference: &[(f64, Isometry3<f64>)],
    times: Vec<f64>,
    failed: usize,
    nees: Option<(f64, f64, usize)>,
) -> Row {
    let s = score(traj, reference);
    Row {
        rmse_m: s.as_ref().map_or(f64::NAN, |s| s.rmse_m),
        end_pct: s.as_ref().map_or(f64::NAN, |s| s.end_pct),
        path_m: s.as_ref().map_or(f64::NAN, |s| s.path_m),
        times,
        failed,
        nees,
    }
}

fn print_row(name: &str, r: &Row) {
    let (p50, p99, max) = percentiles(&r.times);
    let (n, i, bs) = r.nees.map_or(("-".to_string(), "-".to_string(), "-"), |(n, i, poses)| {
        let bs = match geometry::stats::mean_chi2_interval(3, poses, 0.95) {
            Some((lo, _)) if n < lo => "below",
            Some((_, hi)) if n > hi => "above",
            Some(_) => "in",
            None => "-",
        };
        (format!("{n:.2}"), format!("{:.0}%", i * 100.0), bs)
    });
    println!(
        "{name:<36} {:>8.3} {:>7.2}% {:>7.1} {:>8.1} {:>8.1} {:>8.1} {:>7} {:>7} {:>6} {:>5}",
        r.rmse_m, r.end_pct, r.path_m, p50, p99, max, r.failed, n, i, bs
    );
}

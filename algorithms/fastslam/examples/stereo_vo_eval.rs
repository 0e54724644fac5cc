//! Camera-only tracking on real stereo features in the stereo_vo format (e.g. the KITTI
//! features of `../shared/data/stereo_vo_large`, read in place: they may not be committed):
//! the front end alone (frame-to-frame registration, its poses chained) and FastSLAM with the
//! front end as its motion input, each with and without the data set's landmark ids as feature
//! track ids, against the data set's reference poses.
//!
//! `cargo run --release -p fastslam --example stereo_vo_eval -- [DIR] [--particles N] [--reference FILE.tum] [--frames]`
//!
//! The reference is the data set's `VO_camera_poses_large.txt` (its own visual odometry), or a
//! TUM file given with `--reference` (e.g. ground truth, stamped `frame_id / 10`). Reported per
//! run: RMSE of the positions after the best rigid alignment (Horn/Umeyama), the difference of
//! the end points after aligning the first poses, as a percentage of the reference path length,
//! and the time per frame. `--frames` prints every frame.

use std::time::Instant;

use fastslam::frontend::{Frame, FrontEnd, FrontEndConfig};
use fastslam::{CameraOnly, FastSlam, FastSlamConfig, Observation};
use geometry::{StereoPixels, StereoRig};
use nalgebra::{Isometry3, Vector3};

struct Args {
    dir: String,
    particles: usize,
    reference: Option<String>,
    frames: bool,
}

fn parse() -> Result<Args, String> {
    let mut a = Args { dir: "../shared/data/stereo_vo_large".into(), particles: 100, reference: None, frames: false };
    let mut it = std::env::args().skip(1);
    while let Some(x) = it.next() {
        match x.as_str() {
            "--particles" => a.particles = it.next().and_then(|v| v.parse().ok()).ok_or("--particles N")?,
            "--reference" => a.reference = Some(it.next().ok_or("--reference FILE")?),
            "--frames" => a.frames = true,
            s if !s.starts_with("--") => a.dir = s.to_string(),
            s => return Err(format!("unknown option {s}")),
        }
    }
    Ok(a)
}

/// Frames of observations (camera frame = body frame), with the data set's ids as track ids
/// when `ids`; the stamp is `frame_id / 10` s.
fn frames(vo: &datasets::StereoVo, ids: bool) -> Vec<(f64, Vec<Observation>)> {
    let c = vo.calibration;
    let rig = StereoRig {
        f_px: c.fx_px,
        cx_px: c.cx_px,
        cy_px: c.cy_px,
        baseline_m: c.baseline_m,
        width_px: (2.0 * c.cx_px).ceil() as u32,
        height_px: (2.0 * c.cy_px).ceil() as u32,
    };
    datasets::group_by_frame(&vo.factors)
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
        .collect()
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
    // End points after aligning the first poses (how far the track has drifted at the end).
    let (e0, r0) = (est.first()?, fastslam::eval::nearest(reference, est[0].0)?);
    let (e1, r1) = (est.last()?, fastslam::eval::nearest(reference, est.last()?.0)?);
    let rel_est = e0.1.inverse() * e1.1;
    let rel_ref = r0.inverse() * r1;
    let end = (rel_est.translation.vector - rel_ref.translation.vector).norm();
    Some(Score { rmse_m: (se / src.len() as f64).sqrt(), end_pct: 100.0 * end / path_m.max(1e-9), path_m })
}

fn main() {
    let args = match parse() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("stereo_vo_eval: {e}");
            std::process::exit(2);
        }
    };
    let vo = match datasets::StereoVo::load(&args.dir) {
        Ok(v) => v,
        Err(e) => {
            eprintln!("stereo_vo_eval: {e} (the data set may not be committed: point to it in ../shared/data)");
            std::process::exit(2);
        }
    };
    let reference: Vec<(f64, Isometry3<f64>)> = match &args.reference {
        Some(f) => match fastslam::eval::read_tum(std::path::Path::new(f)) {
            Ok(r) => r,
            Err(e) => {
                eprintln!("stereo_vo_eval: {f}: {e}");
                std::process::exit(2);
            }
        },
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
    println!(
        "{}: {} frames, {} observations; reference: {}",
        args.dir,
        datasets::group_by_frame(&vo.factors).len(),
        vo.factors.len(),
        args.reference.as_deref().unwrap_or("the data set's VO poses")
    );
    println!(
        "{:<34} {:>9} {:>9} {:>8} {:>9} {:>9} {:>7}",
        "run", "RMSE m", "end %", "path m", "p50 ms", "max ms", "failed"
    );
    for ids in [false, true] {
        let frames = frames(&vo, ids);
        // The front end alone, its motions chained.
        let mut fe = FrontEnd::new(FrontEndConfig::default());
        let mut pose = Isometry3::identity();
        let mut traj = vec![];
        let mut times = vec![];
        let mut failed = 0;
        for (t, obs) in &frames {
            let t0 = Instant::now();
            let r = fe.register(Frame::from_observations(obs, &Isometry3::identity()), 0.1);
            times.push(t0.elapsed().as_secs_f64() * 1e3);
            match r {
                Ok(r) => {
                    pose *= r.prev_from_cur;
                    if args.frames {
                        println!(
                            "  front end t={t:.1}: {:?} {} inliers of {:?}, {:.1} candidates/point, χ²/dof {:.2}",
                            r.method, r.inliers, r.points, r.candidates_per_point, r.chi2_per_dof
                        );
                    }
                }
                Err(fastslam::frontend::RegistrationError::FirstFrame) => {}
                Err(e) => {
                    failed += 1;
                    println!("  front end t={t:.1}: {e}");
                }
            }
            traj.push((*t, pose));
        }
        report(&format!("front end alone{}", if ids { ", track ids" } else { "" }), &traj, &reference, &times, failed);
        // FastSLAM with the front end as its motion input.
        let cfg = FastSlamConfig { particles: args.particles, ..Default::default() };
        let mut f = FastSlam::new(cfg).expect("valid settings");
        let mut cam = CameraOnly::new(FrontEndConfig::default(), Isometry3::identity());
        let mut traj = vec![];
        let mut times = vec![];
        let mut failed = 0;
        let mut last_t = None;
        for (t, obs) in &frames {
            let t0 = Instant::now();
            let dt = last_t.map_or(0.0, |l| t - l);
            last_t = Some(*t);
            let m = cam.predict(&mut f, obs, dt);
            let r = f.update(obs);
            times.push(t0.elapsed().as_secs_f64() * 1e3);
            if let Err(e) = &m.registration
                && !matches!(e, fastslam::frontend::RegistrationError::FirstFrame)
            {
                failed += 1;
                println!("  fastslam t={t:.1}: {e}");
            }
            if args.frames {
                println!(
                    "  fastslam t={t:.1}: matched {} new {} N_eff {:.1} candidates/obs {:.2} NIS {:.2}",
                    r.matched, r.new, r.n_eff, r.candidates_per_observation, r.mean_nis
                );
            }
            traj.push((*t, f.estimate().map_from_body));
        }
        report(
            &format!("fastslam N={}{}", args.particles, if ids { ", track ids" } else { "" }),
            &traj,
            &reference,
            &times,
            failed,
        );
    }
}

fn report(
    name: &str,
    traj: &[(f64, Isometry3<f64>)],
    reference: &[(f64, Isometry3<f64>)],
    times: &[f64],
    failed: usize,
) {
    let mut t = times.to_vec();
    t.sort_by(f64::total_cmp);
    let p50 = t.get(t.len() / 2).copied().unwrap_or(f64::NAN);
    let max = t.last().copied().unwrap_or(f64::NAN);
    match score(traj, reference) {
        Some(s) => println!(
            "{name:<34} {:>9.3} {:>8.2}% {:>8.1} {:>9.1} {:>9.1} {:>7}",
            s.rmse_m, s.end_pct, s.path_m, p50, max, failed
        ),
        None => println!("{name:<34} (too few poses matched the reference)"),
    }
}

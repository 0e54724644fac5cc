//! Association precision and recall of FastSLAM on real KITTI stereo features (the
//! stereo_vo_large data set, read in place; it may not be committed), against the data set's own
//! landmark ids, camera-only (constant velocity):
//! `cargo run --release -p fastslam --example vo_association -- ../shared/data/stereo_vo_large [particles] [cv_velocity_sigma_mps] [motion|optimal] [vo-poses]`.
//! With `vo-poses` every frame starts from the data set's own VO pose instead of the filter's
//! tracking: a diagnostic that separates association from tracking.
//!
//! An association of an observation (data-set id d) to a filter landmark is correct when that
//! landmark was created from an observation of d. Precision = correct / associated; recall =
//! correct / observations whose data-set landmark the filter already had in its map.

use std::collections::HashMap;

use fastslam::{FastSlam, FastSlamConfig, Observation};
use geometry::{StereoPixels, StereoRig};
use nalgebra::{Isometry3, Vector3};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = args.get(1).cloned().unwrap_or_else(|| "../shared/data/stereo_vo_large".into());
    let particles = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(100);
    let vo = match datasets::StereoVo::load(&dir) {
        Ok(v) => v,
        Err(e) => {
            eprintln!("vo_association: {e}");
            std::process::exit(2);
        }
    };
    let c = vo.calibration;
    let rig = StereoRig {
        f_px: c.fx_px,
        cx_px: c.cx_px,
        cy_px: c.cy_px,
        baseline_m: c.baseline_m,
        width_px: 1242,
        height_px: 375,
    };
    let cv: f64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1.0);
    let proposal = match args.get(4).map(String::as_str) {
        Some("optimal") => fastslam::Proposal::Optimal,
        _ => fastslam::Proposal::Motion,
    };
    let use_vo_poses = args.get(5).is_some_and(|a| a == "vo-poses");
    let mut f = FastSlam::new(FastSlamConfig { particles, cv_velocity_sigma_mps: cv, proposal, ..Default::default() })
        .expect("valid config");
    let mut created_from: HashMap<u32, u64> = HashMap::new(); // filter id -> data-set id
    let mut known: HashMap<u64, ()> = HashMap::new(); // data-set ids the filter has mapped
    let (mut tot_assoc, mut tot_correct, mut tot_possible) = (0usize, 0usize, 0usize);
    println!(
        "{:>5} {:>5} {:>8} {:>8} {:>9} {:>9} {:>7}",
        "frame", "obs", "assoc", "correct", "precision", "recall", "new"
    );
    let frames = datasets::group_by_frame(&vo.factors);
    let mut last_id = None;
    for fr in &frames {
        if let Some(last) = last_id {
            f.predict_constant_velocity((fr.frame_id - last) as f64 * 0.1);
        }
        last_id = Some(fr.frame_id);
        // Diagnostic: the data set's own VO pose instead of the filter's tracking, to separate
        // association from tracking.
        if use_vo_poses && let Some(cp) = vo.poses.iter().find(|p| p.frame_id == fr.frame_id) {
            let m = cp.world_from_camera;
            let rot = nalgebra::Rotation3::from_matrix_unchecked(m.fixed_view::<3, 3>(0, 0).into_owned());
            f.set_pose(Isometry3::from_parts(
                nalgebra::Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
                nalgebra::UnitQuaternion::from_rotation_matrix(&rot),
            ));
        }
        let mut obs = vec![];
        let mut ids = vec![];
        for o in &fr.observations {
            let px = StereoPixels { u_left_px: o.u_left_px, u_right_px: o.u_right_px, v_px: o.v_px };
            let Ok(cov) = rig.triangulation_covariance(&px, 0.5) else { continue };
            if let Ok(ob) = Observation::from_camera(&Vector3::from(o.point_cam_m), &cov, None, &Isometry3::identity())
            {
                obs.push(ob);
                ids.push(o.landmark_id);
            }
        }
        let possible = ids.iter().filter(|d| known.contains_key(d)).count();
        let r = f.update(&obs);
        if std::env::var("DBG").is_ok() {
            let e = f.estimate();
            eprintln!(
                "frame {} matched {} amb {} new {} neff {:.1} pos {:?} lm {}",
                fr.frame_id,
                r.matched,
                r.ambiguous,
                r.new,
                r.n_eff,
                e.map_from_body.translation.vector.as_slice(),
                r.landmarks
            );
        }
        let (mut assoc, mut correct) = (0, 0);
        for (j, a) in r.associations.iter().enumerate() {
            if let Some(fid) = a {
                assoc += 1;
                if created_from.get(fid) == Some(&ids[j]) {
                    correct += 1;
                }
            }
        }
        // Landmarks created this frame: remember which data-set landmark each came from.
        for (j, a) in r.associations.iter().enumerate() {
            if a.is_none() {
                created_from.insert(r.first_new_id + j as u32, ids[j]);
                known.insert(ids[j], ());
            }
        }
        tot_assoc += assoc;
        tot_correct += correct;
        tot_possible += possible;
        let pct = |a: usize, b: usize| if b == 0 { f64::NAN } else { 100.0 * a as f64 / b as f64 };
        println!(
            "{:>5} {:>5} {:>8} {:>8} {:>8.1}% {:>8.1}% {:>7}",
            fr.frame_id,
            obs.len(),
            assoc,
            correct,
            pct(correct, assoc),
            pct(correct, possible),
            r.new
        );
    }
    let pct = |a: usize, b: usize| if b == 0 { f64::NAN } else { 100.0 * a as f64 / b as f64 };
    println!(
        "total: {tot_assoc} associations, {tot_correct} correct: precision {:.1}%, recall {:.1}% ({particles} particles)",
        pct(tot_correct, tot_assoc),
        pct(tot_correct, tot_possible)
    );
}

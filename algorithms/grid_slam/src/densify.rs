//! Poses between scans, shaped by the odometry (docs/EQUATIONS.md §8, "Between scans").
//!
//! A laser SLAM estimates a pose at each scan; wheel odometry runs at a higher rate (the
//! subsampled Intel and ACES logs keep a scan every 2-3 s and odometry every 0.1-0.2 s). Between
//! two estimated poses `a` at `t_a` and `b` at `t_b` the pose at `t` follows the odometry's motion
//! from `t_a`, and the disagreement the odometry has with `b` at `t_b` is spread over the interval
//! in proportion to the time:
//!
//! x(t) = a ⊕ (r(t) + s·e), with r(t) = o_a⁻¹ ⊕ o(t), e = (a⁻¹ ⊕ b) − r(t_b) and s = (t − t_a)/(t_b − t_a),
//!
//! where the motions r and the error e are in `a`'s frame and added component by component (x,
//! y and the wrapped angle; e is small: what the odometry drifts in one interval). At `t_a` this is `a`, at `t_b` it is `b`, and with odometry that agrees with the
//! poses it is the odometry's own path between them. The same construction spreads seeded drift
//! over the odometry between two scans ([`crate::drift`]): the drifted poses at the scans are the
//! anchors and the log's poses the shape.
//!
//! Frames: every pose is `map_from_body` (or `odom_from_body` for the odometry), m and rad;
//! stamps are seconds on the data's clock.

use omni::{Pose2, wrap_angle};

/// The pose at fraction `s` of the interval from `a` to `b` whose motion follows `shape` from
/// `shape_a` (the shape at `a`'s stamp) to `shape_t` (at the stamp wanted), with `shape`'s
/// disagreement with `b` at `shape_b` spread in proportion to `s` (module docs).
pub fn shaped(a: &Pose2, b: &Pose2, shape_a: &Pose2, shape_b: &Pose2, shape_t: &Pose2, s: f64) -> Pose2 {
    let (want, got, r) = (a.between(b), shape_a.between(shape_b), shape_a.between(shape_t));
    let p = a.compose(&Pose2 {
        x_m: r.x_m + s * (want.x_m - got.x_m),
        y_m: r.y_m + s * (want.y_m - got.y_m),
        theta_rad: r.theta_rad + s * wrap_angle(want.theta_rad - got.theta_rad),
    });
    Pose2 { theta_rad: wrap_angle(p.theta_rad), ..p }
}

/// `track` interpolated at `t` (linear in x, y and the wrapped angle), or `None` outside its span.
/// `track` is sorted by stamp.
pub fn interpolate(track: &[(f64, Pose2)], t: f64) -> Option<Pose2> {
    let i = track.partition_point(|(s, _)| *s < t);
    let b = track.get(i)?;
    if b.0 == t {
        return Some(b.1);
    }
    let a = track.get(i.checked_sub(1)?)?;
    let f = (t - a.0) / (b.0 - a.0);
    Some(Pose2 {
        x_m: a.1.x_m + f * (b.1.x_m - a.1.x_m),
        y_m: a.1.y_m + f * (b.1.y_m - a.1.y_m),
        theta_rad: wrap_angle(a.1.theta_rad + f * wrap_angle(b.1.theta_rad - a.1.theta_rad)),
    })
}

/// For each of `poses` (in stamp order), the poses at the stamps of `track` (sorted) strictly
/// between the pose before it and it, [`shaped`] by `track`; none for the first, none for an
/// interval whose ends `track` does not cover, none after a pose whose stamp is not after the
/// one before.
pub fn between(poses: &[(f64, Pose2)], track: &[(f64, Pose2)]) -> Vec<Vec<(f64, Pose2)>> {
    let mut out = vec![Vec::new(); poses.len()];
    for (k, w) in poses.windows(2).enumerate() {
        let ((ta, a), (tb, b)) = (w[0], w[1]);
        if tb <= ta {
            continue;
        }
        let (Some(oa), Some(ob)) = (interpolate(track, ta), interpolate(track, tb)) else { continue };
        let first = track.partition_point(|(s, _)| *s <= ta);
        out[k + 1] = track[first..]
            .iter()
            .take_while(|(s, _)| *s < tb)
            .map(|(t, o)| (*t, shaped(&a, &b, &oa, &ob, o, (t - ta) / (tb - ta))))
            .collect();
    }
    out
}

/// [`between`] with the shape taken from `samples` where they are and from `shape_at_poses` (the
/// shape's own value at each of `poses`' stamps) at the poses: the odometry's motion from a pose
/// starts at the value it had there, not at a sample near it, and a pose is never a sample (a
/// pose out of stamp order is not put between others). The poses between are at `samples`'
/// stamps only.
pub fn between_samples(
    poses: &[(f64, Pose2)],
    shape_at_poses: &[(f64, Pose2)],
    samples: &[(f64, Pose2)],
) -> Vec<Vec<(f64, Pose2)>> {
    let mut track: Vec<(f64, Pose2)> = shape_at_poses.to_vec();
    track.extend(samples.iter().filter(|(t, _)| t.is_finite()));
    track.sort_by(|a, b| a.0.total_cmp(&b.0));
    track.dedup_by(|later, earlier| later.0 == earlier.0);
    let at_poses: std::collections::HashSet<u64> = shape_at_poses.iter().map(|s| s.0.to_bits()).collect();
    let mut b = between(poses, &track);
    for list in &mut b {
        list.retain(|(t, _)| !at_poses.contains(&t.to_bits()));
    }
    b
}

/// `poses` with the poses [`between`] them inserted, in order.
pub fn densify(poses: &[(f64, Pose2)], track: &[(f64, Pose2)]) -> Vec<(f64, Pose2)> {
    interleave(poses, &between(poses, track))
}

/// Each of `poses` preceded by its `between` list (as [`between`] returns them).
pub fn interleave(poses: &[(f64, Pose2)], between: &[Vec<(f64, Pose2)>]) -> Vec<(f64, Pose2)> {
    let mut out = Vec::with_capacity(poses.len() + between.iter().map(Vec::len).sum::<usize>());
    for (k, p) in poses.iter().enumerate() {
        out.extend(between.get(k).into_iter().flatten());
        out.push(*p);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(x: f64, y: f64, th: f64) -> Pose2 {
        Pose2 { x_m: x, y_m: y, theta_rad: th }
    }

    fn close(a: &Pose2, b: &Pose2) -> bool {
        (a.x_m - b.x_m).abs() < 1e-9
            && (a.y_m - b.y_m).abs() < 1e-9
            && wrap_angle(a.theta_rad - b.theta_rad).abs() < 1e-9
    }

    /// A quarter circle of radius 2 m, 1 rad/s, as (stamp, pose) every 0.1 s.
    fn arc(t0: f64, t1: f64) -> Vec<(f64, Pose2)> {
        let n = ((t1 - t0) / 0.1).round() as usize;
        (0..=n)
            .map(|k| {
                let t = t0 + k as f64 * 0.1;
                (t, p(2.0 * t.sin(), 2.0 - 2.0 * t.cos(), t))
            })
            .collect()
    }

    #[test]
    fn between_two_poses_the_path_follows_the_odometry_and_ends_on_them() {
        let truth = arc(0.0, 1.5);
        // The SLAM poses at 0 and 1.5 s are the truth's; the odometry is the truth seen from a
        // frame shifted and turned, and drifting: 5 % too long.
        let frame = p(10.0, -3.0, 0.7);
        let odo: Vec<(f64, Pose2)> =
            truth.iter().map(|(t, q)| (*t, frame.compose(&p(q.x_m * 1.05, q.y_m * 1.05, q.theta_rad)))).collect();
        let poses = [truth[0], truth[15]];
        let d = densify(&poses, &odo);
        assert_eq!(d.len(), 16, "both ends and the 14 odometry stamps strictly between");
        assert!(close(&d[0].1, &truth[0].1) && close(&d[15].1, &truth[15].1), "the ends are the poses");
        let worst = d.iter().zip(&truth).map(|(a, b)| (a.1.x_m - b.1.x_m).hypot(a.1.y_m - b.1.y_m)).fold(0.0, f64::max);
        // A straight line between the ends misses the arc's middle by 0.54 m; the odometry's
        // shape, 5 % too long with the error spread, by 5 % of that.
        let straight = (truth[7].1.x_m - 0.5 * (truth[0].1.x_m + truth[15].1.x_m))
            .hypot(truth[7].1.y_m - 0.5 * (truth[0].1.y_m + truth[15].1.y_m));
        assert!(straight > 0.5, "{straight}");
        assert!(worst < 0.06 * straight, "{worst}");
    }

    #[test]
    fn odometry_that_agrees_with_the_poses_is_taken_as_it_is_and_gaps_stay_gaps() {
        let truth = arc(0.0, 1.0);
        let poses = [truth[0], truth[4], truth[10]];
        let d = densify(&poses, &truth);
        assert_eq!(d.len(), truth.len());
        for (a, b) in d.iter().zip(&truth) {
            assert!(a.0 == b.0 && close(&a.1, &b.1), "{a:?} {b:?}");
        }
        // Odometry that starts after the first pose leaves that interval as it was.
        let late = &truth[3..];
        let d = densify(&poses, late);
        assert_eq!(d.iter().filter(|(t, _)| *t < 0.4 - 1e-9).count(), 1, "nothing between 0 and 0.4 s");
        assert_eq!(d.len(), 3 + 5, "0.5-0.9 s between the last two");
        assert_eq!(densify(&[], &truth), vec![]);
        assert_eq!(densify(&poses[..1], &truth), poses[..1].to_vec());
    }

    #[test]
    fn interpolation_wraps_the_angle() {
        let track = [(0.0, p(0.0, 0.0, 3.1)), (1.0, p(1.0, 0.0, -3.1))];
        let m = interpolate(&track, 0.5).expect("inside");
        assert!((m.theta_rad.abs() - std::f64::consts::PI).abs() < 1e-9, "{m:?}");
        assert!(interpolate(&track, 1.5).is_none() && interpolate(&track, -0.1).is_none());
    }
}

//! The relations metric of Kümmerle et al. 2009 ("On measuring the accuracy of SLAM
//! algorithms"): for each relation (t1, t2, δ), with δ the true motion from the pose at t1
//! to the pose at t2 in the frame of t1, the error is e = (x_t1⁻¹ ⊕ x_t2) ⊖ δ; the score is the
//! mean ± std of ‖e_xy‖ (m) and |e_θ| (deg) over the relations the trajectory covers. Relations
//! that span more than [`LONG_SPAN_S`] test global consistency (a loop that is not closed fails
//! exactly those), so their mean is reported apart, with the share of relations off by more
//! than [`FAR_OFF_M`].

use crate::GridSlamError;
use omni::{Pose2, wrap_angle};
use std::path::Path;

/// One relation: the motion from the pose at `t1_s` to the pose at `t2_s`, in the frame of the
/// first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Relation {
    /// First stamp, s (the relations file's clock).
    pub t1_s: f64,
    /// Second stamp, s.
    pub t2_s: f64,
    /// The motion (x, y, yaw).
    pub delta: Pose2,
}

/// Reads a relations file: `t1 t2 dx dy dz droll dpitch dyaw` per line (m, rad); blank lines and
/// `#` comments are skipped. Errors name file:line.
pub fn read_relations(path: &Path) -> Result<Vec<Relation>, GridSlamError> {
    let text =
        std::fs::read_to_string(path).map_err(|e| GridSlamError::Io { path: path.display().to_string(), source: e })?;
    parse_relations(&text, &path.display().to_string())
}

/// Parses relations text (see [`read_relations`]); `source` names it in errors.
pub fn parse_relations(text: &str, source: &str) -> Result<Vec<Relation>, GridSlamError> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |why: String| GridSlamError::Parse { file: source.to_string(), line: n + 1, why };
        let v: Vec<f64> = line
            .split_whitespace()
            .map(|f| f.parse::<f64>().map_err(|_| bad(format!("'{f}' is not a number"))))
            .collect::<Result<_, _>>()?;
        if v.len() != 8 {
            return Err(bad(format!("expected 8 fields (t1 t2 dx dy dz droll dpitch dyaw), found {}", v.len())));
        }
        if v.iter().any(|x| !x.is_finite()) {
            return Err(bad("a field is not finite".into()));
        }
        out.push(Relation { t1_s: v[0], t2_s: v[1], delta: Pose2 { x_m: v[2], y_m: v[3], theta_rad: v[7] } });
    }
    Ok(out)
}

/// Relations whose stamps are further apart than this, s, are the "long" ones: they span a
/// loop, or most of one, and only a globally consistent trajectory gets them right.
pub const LONG_SPAN_S: f64 = 60.0;

/// A relation whose translation error is over this, m, counts as failed (`over_far_share`).
pub const FAR_OFF_M: f64 = 0.5;

/// Reads `null` back as NaN: JSON has no NaN, so a score of nothing (no relation scored, none
/// that long) is written as `null`.
fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(<Option<f64> as serde::Deserialize>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// The score of a trajectory against relations (a mean of nothing is NaN, written as `null`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct RelationScore {
    /// Relations scored.
    pub scored: usize,
    /// Relations the trajectory does not cover (a stamp outside it, or in a gap longer than
    /// the allowed one).
    pub uncovered: usize,
    /// Mean translational error, m.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub trans_mean_m: f64,
    /// Its std dev, m.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub trans_std_m: f64,
    /// Largest translational error, m.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub trans_max_m: f64,
    /// Mean rotational error, deg.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub rot_mean_deg: f64,
    /// Its std dev, deg.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub rot_std_deg: f64,
    /// Largest rotational error, deg.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub rot_max_deg: f64,
    /// Relations scored that span more than [`LONG_SPAN_S`].
    pub long_scored: usize,
    /// Their mean translational error, m (NaN, written as null, when there are none).
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub long_trans_mean_m: f64,
    /// Share of the scored relations whose translation error is over [`FAR_OFF_M`] (0..1).
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub over_far_share: f64,
}

/// The pose at `t_s` interpolated linearly (yaw along the shorter arc) between the two
/// trajectory poses around it; `None` outside the trajectory or across a gap over `max_gap_s`.
pub fn pose_at(traj: &[(f64, Pose2)], t_s: f64, max_gap_s: f64) -> Option<Pose2> {
    let i = traj.partition_point(|(t, _)| *t < t_s);
    if let Some((t, p)) = traj.get(i)
        && (*t - t_s).abs() < 1e-9
    {
        return Some(*p);
    }
    if i == 0 || i >= traj.len() {
        return None;
    }
    let ((ta, a), (tb, b)) = (traj[i - 1], traj[i]);
    if tb - ta > max_gap_s {
        return None;
    }
    let f = (t_s - ta) / (tb - ta);
    Some(Pose2 {
        x_m: a.x_m + f * (b.x_m - a.x_m),
        y_m: a.y_m + f * (b.y_m - a.y_m),
        theta_rad: wrap_angle(a.theta_rad + f * wrap_angle(b.theta_rad - a.theta_rad)),
    })
}

/// Scores `traj` (sorted by stamp; stamps on the trajectory's clock) against `relations`; a
/// relation's stamps are mapped onto the trajectory's clock by subtracting `offset_s`.
pub fn score(traj: &[(f64, Pose2)], relations: &[Relation], offset_s: f64, max_gap_s: f64) -> RelationScore {
    let (mut et, mut er, mut long) = (Vec::new(), Vec::new(), Vec::new());
    let mut uncovered = 0;
    for r in relations {
        let (Some(a), Some(b)) =
            (pose_at(traj, r.t1_s - offset_s, max_gap_s), pose_at(traj, r.t2_s - offset_s, max_gap_s))
        else {
            uncovered += 1;
            continue;
        };
        let rel = a.between(&b);
        // e = rel ⊕ δ⁻¹
        let e = rel.compose(&invert(&r.delta));
        et.push(e.x_m.hypot(e.y_m));
        er.push(e.theta_rad.abs().to_degrees());
        if (r.t2_s - r.t1_s).abs() > LONG_SPAN_S {
            long.push(e.x_m.hypot(e.y_m));
        }
    }
    let stats = |v: &[f64]| {
        if v.is_empty() {
            return (f64::NAN, f64::NAN, f64::NAN);
        }
        let n = v.len() as f64;
        let m = v.iter().sum::<f64>() / n;
        let s = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n).sqrt();
        (m, s, v.iter().cloned().fold(0.0, f64::max))
    };
    let (tm, ts, tx) = stats(&et);
    let (rm, rs, rx) = stats(&er);
    let far = et.iter().filter(|e| **e > FAR_OFF_M).count();
    RelationScore {
        long_scored: long.len(),
        long_trans_mean_m: stats(&long).0,
        over_far_share: if et.is_empty() { f64::NAN } else { far as f64 / et.len() as f64 },
        scored: et.len(),
        uncovered,
        trans_mean_m: tm,
        trans_std_m: ts,
        trans_max_m: tx,
        rot_mean_deg: rm,
        rot_std_deg: rs,
        rot_max_deg: rx,
    }
}

/// The inverse of a planar pose.
pub fn invert(p: &Pose2) -> Pose2 {
    p.between(&Pose2::default())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn circle(n: usize) -> Vec<(f64, Pose2)> {
        (0..n)
            .map(|k| {
                let a = k as f64 * 0.05;
                (
                    k as f64 * 0.1,
                    Pose2 {
                        x_m: 3.0 * a.cos(),
                        y_m: 3.0 * a.sin(),
                        theta_rad: wrap_angle(a + std::f64::consts::FRAC_PI_2),
                    },
                )
            })
            .collect()
    }

    #[test]
    fn a_trajectory_scores_zero_against_its_own_relations_and_the_error_of_a_bias_shows() {
        let traj = circle(200);
        let rels: Vec<Relation> = (0..150)
            .map(|k| {
                let (t1, t2) = (k as f64 * 0.1 + 0.05 + 100.0, k as f64 * 0.1 + 0.95 + 100.0);
                let a = pose_at(&traj, t1 - 100.0, 1.0).expect("inside");
                let b = pose_at(&traj, t2 - 100.0, 1.0).expect("inside");
                Relation { t1_s: t1, t2_s: t2, delta: a.between(&b) }
            })
            .collect();
        let s = score(&traj, &rels, 100.0, 1.0);
        assert_eq!((s.scored, s.uncovered), (150, 0));
        assert!(s.trans_mean_m < 1e-9 && s.rot_mean_deg < 1e-9, "{s:?}");
        // A trajectory that turns 1% too fast: rotational error ≈ 1% of each relation's turn.
        let fast: Vec<(f64, Pose2)> = traj
            .iter()
            .map(|(t, p)| (*t, Pose2 { theta_rad: wrap_angle(p.theta_rad + 0.01 * t * 0.5), ..*p }))
            .collect();
        let s2 = score(&fast, &rels, 100.0, 1.0);
        assert!((s2.rot_mean_deg - (0.01f64 * 0.9 * 0.5).to_degrees()).abs() < 1e-6, "{s2:?}");
        // Relations outside the trajectory are counted as uncovered.
        let s3 = score(&traj, &rels, 90.0, 1.0);
        assert!(s3.uncovered > 0);
    }

    #[test]
    fn a_loop_that_is_not_closed_shows_in_the_long_relations_and_the_far_off_share() {
        // A straight run out and back along x (1 m/s, 200 s): the truth returns to the start.
        let truth: Vec<(f64, Pose2)> = (0..=200)
            .map(|k| {
                let t = k as f64;
                let x = if t <= 100.0 { t } else { 200.0 - t };
                (t, Pose2 { x_m: x, y_m: 0.0, theta_rad: 0.0 })
            })
            .collect();
        // Short relations (10 s) all along, and long ones (150 s) that span the turn.
        let mut rels = vec![];
        for (t1, t2) in (0..19)
            .map(|k| (k as f64 * 10.0, k as f64 * 10.0 + 10.0))
            .chain((0..5).map(|k| (k as f64 * 10.0, k as f64 * 10.0 + 150.0)))
        {
            let (a, b) = (pose_at(&truth, t1, 2.0).unwrap(), pose_at(&truth, t2, 2.0).unwrap());
            rels.push(Relation { t1_s: t1, t2_s: t2, delta: a.between(&b) });
        }
        let s = score(&truth, &rels, 0.0, 2.0);
        assert_eq!((s.scored, s.long_scored), (24, 5));
        assert!(s.long_trans_mean_m < 1e-9 && s.over_far_share == 0.0, "{s:?}");
        // The way back drifts sideways 2 cm per second (the double wall of an unclosed loop):
        // short relations stay good, every long one is off by metres.
        let drifted: Vec<(f64, Pose2)> =
            truth.iter().map(|(t, p)| (*t, Pose2 { y_m: 0.02 * (t - 100.0).max(0.0), ..*p })).collect();
        let d = score(&drifted, &rels, 0.0, 2.0);
        assert!(d.trans_mean_m < 0.6 && d.long_trans_mean_m > 0.9, "{d:?}");
        assert!((d.over_far_share - 5.0 / 24.0).abs() < 1e-9, "{d:?}");
        // None long: the mean is NaN (null in JSON), not 0.
        let short = score(&truth, &rels[..19], 0.0, 2.0);
        assert!(short.long_trans_mean_m.is_nan() && short.long_scored == 0);
    }

    #[test]
    fn relations_files_are_parsed_and_errors_name_the_line() {
        let r = parse_relations("# c\n1 2 0.5 0 0 0 0 0.1\n\n", "x").expect("ok");
        assert_eq!(r.len(), 1);
        assert_eq!(r[0].delta, Pose2 { x_m: 0.5, y_m: 0.0, theta_rad: 0.1 });
        let e = parse_relations("1 2 0.5 0 0 0 0 0.1\n1 2 x 0 0 0 0 0\n", "f.relations").unwrap_err();
        assert!(e.to_string().contains("f.relations:2"), "{e}");
        let e = parse_relations("1 2 3\n", "f").unwrap_err();
        assert!(e.to_string().contains("8 fields"), "{e}");
    }
}

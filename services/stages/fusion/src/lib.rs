//! The `fusion` process's settings, the conversions from the wire, and the end-of-run outputs
//! (TUM trajectories, the global map as PLY, per-segment transforms, accuracy, a top-view plot).
//! The fusion itself is [`fusion::engine::Fusion`]; [`stage::FusionStage`] is the stage around it; `main.rs` one line.

use pipeline_runtime::StageError;
use pipeline_runtime::Validate;
use std::path::Path;

pub mod journal;
pub mod stage;
pub mod summary;

use pipeline_runtime::summary::{CountedPercentiles, PositionNees, finite};
use summary::{FusedAte, FusedLatency, FusedNees, FusionPart, FusionSummary};

use fusion::engine::{FinalResult, FixInput, Fusion, FusionConfig, PairInput, Source};
use fusion::global_map::MapLandmark;
use nalgebra::{Isometry3, Matrix3, Vector3};
use pipeline_runtime::{Issues, ProcessSettings};
use serde::{Deserialize, Serialize};
use shared_types::{BuoyFix, Landmark, MsgHeader, SyncedPair};

/// Settings of the `fusion` process.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionSettings {
    /// The engine: `align.{min_pairs, min_spread_ratio, min_extent_m}`, `gate_probability`,
    /// `no_overlap_frames`, `merge.*` (documented in `algorithms/fusion/src/engine.rs`,
    /// `align.rs`, `global_map.rs`).
    pub fusion: FusionConfig,
    /// The SLAM process that gets the new-local-map commands.
    pub slam_process: String,
    /// The processes whose end of stream ends this one's input: all of them; empty: the first
    /// upstream end of stream.
    pub end_after: Vec<String>,
    /// Ground truth to evaluate against at the end (TUM, relative to the output directory);
    /// skipped when missing.
    pub ground_truth: String,
    /// Write `trajectories.png` (top view) at the end.
    pub plot: bool,
}

impl Default for FusionSettings {
    fn default() -> Self {
        Self {
            fusion: FusionConfig::default(),
            slam_process: "slam".into(),
            end_after: vec!["sync".into(), "buoy".into(), "slam".into()],
            ground_truth: "ground_truth.tum".into(),
            plot: true,
        }
    }
}

impl ProcessSettings for FusionSettings {
    fn shm_estimate_bytes(&self, _extra_subscribers: usize) -> u64 {
        // Fused poses, the global map (grows by powers of two), commands.
        (1 << 20) + (16 << 20)
    }
}

impl Validate for FusionSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.nested("fusion", &self.fusion);
        issues.check(!self.slam_process.is_empty(), "slam_process", "must name the SLAM process");
    }
}

/// A synced pair from the wire.
pub fn pair_from_wire(h: &MsgHeader, p: &SyncedPair) -> PairInput {
    PairInput {
        t_s: h.stamp_ns as f64 / 1e9,
        segment: p.slam.segment_id,
        local_from_body: p.slam.frame_from_body(),
        local_covariance: p.slam.covariance_matrix(),
        buoy_m: Vector3::from(p.buoy_position_m),
        buoy_cov_m2: Matrix3::from_row_slice(&p.buoy_covariance_m2),
    }
}

/// A buoy fix from the wire.
pub fn fix_from_wire(h: &MsgHeader, f: &BuoyFix) -> FixInput {
    FixInput {
        t_s: h.stamp_ns as f64 / 1e9,
        position_m: Vector3::from(f.position_m),
        covariance_m2: Matrix3::from_row_slice(&f.covariance_m2),
    }
}

/// A landmark from the wire; NaN or a negative observation count drops it.
pub fn landmark_from_wire(l: &Landmark) -> Option<MapLandmark> {
    let mean = Vector3::from(l.mean_m);
    let cov = Matrix3::from_row_slice(&l.covariance_m2);
    if !(mean.iter().all(|v| v.is_finite()) && cov.iter().all(|v| v.is_finite())) {
        return None;
    }
    Some(MapLandmark {
        id: l.id,
        segment: l.segment_id,
        mean_m: mean,
        cov_m2: cov,
        descriptor: l.descriptor.iter().any(|b| *b != 0).then_some(l.descriptor),
        observations: l.observation_count,
    })
}

/// Counts by source.
#[derive(Debug, Clone, Default, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SourceCounts {
    /// Fused poses.
    pub fused: u64,
    /// Camera only (outside the gate).
    pub camera_only: u64,
    /// Buoy only (no transform yet).
    pub buoy_only: u64,
}

impl SourceCounts {
    /// Counts one.
    pub fn add(&mut self, s: Source) {
        match s {
            Source::Fused => self.fused += 1,
            Source::CameraOnly => self.camera_only += 1,
            Source::BuoyOnly => self.buoy_only += 1,
        }
    }
}

/// Everything the process logged during the run, for the end-of-run outputs.
#[derive(Debug, Default)]
pub struct RunLog {
    /// The published (live) fused poses: (t, world_from_body).
    pub live: Vec<(f64, Isometry3<f64>)>,
    /// The live poses' position covariances (world frame, m²), one per entry of `live`.
    pub live_position_cov_m2: Vec<Matrix3<f64>>,
    /// The buoy positions synchronised to the SLAM poses: (t, position).
    pub buoy: Vec<(f64, Vector3<f64>)>,
    /// Their covariances (m²), one per entry of `buoy`.
    pub buoy_cov_m2: Vec<Matrix3<f64>>,
    /// Counts of the live poses.
    pub live_sources: SourceCounts,
    /// New local maps requested.
    pub segment_requests: u64,
    /// Inputs dropped as invalid, by reason.
    pub invalid: std::collections::BTreeMap<String, u64>,
    /// Latency from the stereo frame entering the pipeline to the fused pose leaving, ms.
    pub stereo_to_fused_ms: Vec<f64>,
    /// The predicted poses published (flag `FUSED_PREDICTED`): (t, world_from_body).
    pub predicted: Vec<(f64, Isometry3<f64>)>,
    /// The first pose published at each stamp (the predicted one, or the refined one when none
    /// was predicted): what a consumer that takes the first pose gets.
    pub first: Vec<(f64, Isometry3<f64>)>,
    /// Latency from the stereo frame to the first fused pose of its stamp leaving, ms.
    pub stereo_to_first_fused_ms: Vec<f64>,
    /// Predicted pairs that fusion could not turn into a pose (invalid), counted.
    pub predicted_invalid: u64,
}

fn positions(p: &[(f64, Isometry3<f64>)]) -> Vec<(f64, Vector3<f64>)> {
    p.iter().map(|(t, x)| (*t, x.translation.vector)).collect()
}

/// Writes `segment_transforms.json` (each local map's transform to the world and its alignment's
/// quality); returns how many local maps there were.
fn write_segment_transforms(out_dir: &Path, engine: &Fusion) -> Result<usize, StageError> {
    let segments: Vec<serde_json::Value> = engine
        .segments()
        .map(|s| {
            let a = s.alignment.as_ref();
            serde_json::json!({
                "segment": s.id,
                "poses": s.pairs.len(),
                "status": s.status,
                "landmarks": s.landmarks.len(),
                "translation_m": a.map(|a| a.global_from_local.translation.vector.as_slice().to_vec()),
                "rotation_xyzw": a.map(|a| shared_types::convert::quat_to_xyzw(&a.global_from_local.rotation)),
                "pairs": a.map(|a| a.pairs),
                "rms_residual_m": a.map(|a| a.rms_residual_m),
                "spread_ratio": a.map(|a| a.spread_ratio),
                "handed_over_from": s.handover.as_ref().map(|h| h.from),
                // The prior's σ: translation (m) and rotation (deg, world x, y, z).
                "handover_prior_sd": engine.handover_prior_of(s.id).map(|p| {
                    let sd = |i: usize| p.covariance[(i, i)].max(0.0).sqrt();
                    serde_json::json!({
                        "translation_m": [sd(0), sd(1), sd(2)],
                        "rotation_deg": [sd(3).to_degrees(), sd(4).to_degrees(), sd(5).to_degrees()],
                    })
                }),
                "prior_rejected": s.prior_rejected,
            })
        })
        .collect();
    std::fs::write(out_dir.join("segment_transforms.json"), serde_json::to_vec_pretty(&segments)?)?;
    Ok(segments.len())
}

/// Draws `trajectories.png`: the top view of the ground truth, the buoy fixes, the SLAM path
/// mapped to the world (broken where a local map has no transform) and the fused path.
fn plot_trajectories(
    out_dir: &Path,
    series_truth: &[(f64, f64)],
    buoy: &[(f64, Vector3<f64>)],
    slam_world: &[(f64, Isometry3<f64>)],
    fused: &[(f64, Isometry3<f64>)],
) {
    let xy = |v: &[(f64, Vector3<f64>)]| v.iter().map(|(_, p)| (p.x, p.y)).collect::<Vec<_>>();
    // The mapped SLAM path has holes (segments without a transform): break the line there.
    let mut slam = vec![];
    for w in slam_world.windows(2) {
        let p = w[0].1.translation.vector;
        slam.push((p.x, p.y));
        if w[1].0 - w[0].0 > 0.5 {
            slam.push((f64::NAN, f64::NAN));
        }
    }
    if let Some((_, last)) = slam_world.last() {
        slam.push((last.translation.vector.x, last.translation.vector.y));
    }
    let (buoy, fused_xy) = (xy(buoy), xy(&positions(fused)));
    let series = [
        fusion::plot::Series { label: "ground truth", color: (0, 0, 0), points: series_truth, thin: true },
        fusion::plot::Series { label: "buoy", color: (230, 120, 0), points: &buoy, thin: false },
        fusion::plot::Series { label: "SLAM (mapped to the world)", color: (40, 90, 220), points: &slam, thin: false },
        fusion::plot::Series { label: "fused", color: (20, 160, 60), points: &fused_xy, thin: false },
    ];
    match fusion::plot::plot_top_view(
        &out_dir.join("trajectories.png"),
        "Top view: ground truth, buoy, SLAM, fused",
        &series,
        1200,
        900,
    ) {
        Ok(r) if !r.text => tracing::warn!("trajectories.png drawn without text: no TrueType font found"),
        Ok(_) => {}
        Err(e) => tracing::warn!("trajectories.png not written: {e}"),
    }
}

/// Writes the end-of-run outputs into `out_dir` and returns the summary part.
pub fn write_outputs(
    out_dir: &Path,
    settings: &FusionSettings,
    engine: &Fusion,
    result: &FinalResult,
    log: &RunLog,
) -> Result<FusionPart, StageError> {
    use geometry::tum::write_tum;
    std::fs::create_dir_all(out_dir)?;
    let fused: Vec<(f64, Isometry3<f64>)> = result.path.iter().map(|o| (o.t_s, o.world_from_body)).collect();
    write_tum(&out_dir.join("fused_global.tum"), fused.iter().map(|(t, p)| (*t, p)))?;
    write_tum(&out_dir.join("fused_live.tum"), log.live.iter().map(|(t, p)| (*t, p)))?;
    write_tum(&out_dir.join("fused_first.tum"), log.first.iter().map(|(t, p)| (*t, p)))?;
    write_tum(&out_dir.join("slam_global.tum"), result.slam_world.iter().map(|(t, p)| (*t, p)))?;
    let buoy_poses: Vec<(f64, Isometry3<f64>)> =
        log.buoy.iter().map(|(t, p)| (*t, Isometry3::translation(p.x, p.y, p.z))).collect();
    write_tum(&out_dir.join("buoy.tum"), buoy_poses.iter().map(|(t, p)| (*t, p)))?;
    fusion::global_map::write_ply(&out_dir.join("global_map.ply"), &result.global_map).map_err(StageError::stage)?;
    let mut final_sources = SourceCounts::default();
    for o in &result.path {
        final_sources.add(o.source);
    }
    let segments = write_segment_transforms(out_dir, engine)?;
    let merged = result.global_map.iter().filter(|l| l.members.len() > 1).count();
    let mut part = FusionPart {
        fusion: FusionSummary {
            poses: result.path.len(),
            live: log.live_sources.clone(),
            final_: final_sources,
            segments,
            segments_aligned: engine.segments().filter(|s| s.alignment.is_some()).count(),
            segments_handed_over: engine.segments().filter(|s| s.handover.is_some()).count(),
            priors_rejected: engine.segments().filter(|s| s.prior_rejected).count(),
            new_local_maps_requested: log.segment_requests,
            global_landmarks: result.global_map.len(),
            global_landmarks_merged: merged,
            invalid_inputs: log.invalid.clone(),
            predicted: log.predicted.len(),
            fix_error_autocorrelation: result.fix_correlation.rho().to_vec(),
        },
        pipeline_latency_ms: FusedLatency {
            stereo_to_fused_pose: CountedPercentiles::of(&log.stereo_to_fused_ms),
            stereo_to_first_fused_pose: CountedPercentiles::of(&log.stereo_to_first_fused_ms),
        },
        ate_m: None,
        nees: None,
    };
    let truth = geometry::tum::read_tum(&out_dir.join(&settings.ground_truth));
    let truth = match truth {
        Ok(t) if !t.is_empty() => Some(t),
        Ok(_) => None,
        Err(e) => {
            tracing::info!("no accuracy evaluation: {e}");
            None
        }
    };
    let mut series_truth = vec![];
    if let Some(truth) = &truth {
        let tp = positions(truth);
        let ate = |est: &[(f64, Vector3<f64>)]| geometry::trajectory::ate_nearest(est, &tp, false);
        let ates = FusedAte {
            fused: finite(ate(&positions(&fused))),
            fused_live: finite(ate(&positions(&log.live))),
            fused_first: finite(ate(&positions(&log.first))),
            fused_predicted: finite(ate(&positions(&log.predicted))),
            buoy: finite(ate(&log.buoy)),
            slam_global: finite(ate(&positions(&result.slam_world))),
        };
        tracing::info!("ATE (3-D, nearest stamp, no alignment): {}", serde_json::to_string(&ates)?);
        part.ate_m = Some(ates);
        // The covariances' consistency: the truth interpolated to each pose's stamp between rows
        // at most 1 s apart on either side (docs/EQUATIONS.md §8a).
        let nees = |est: Vec<(f64, Vector3<f64>, Matrix3<f64>)>, name: &str| {
            let n = geometry::trajectory::position_nees(&est, &tp, false, 1.0)?;
            let nees = PositionNees::new(n.mean, n.dof, n.samples, n.per_axis, n.skipped, n.interval_95);
            tracing::info!(
                "{name}: position NEES {:.2} over {} poses (per axis x, y, z {:.2}, {:.2}, {:.2}; consistent within [{:.2}, {:.2}] at 95 %: {})",
                n.mean,
                n.samples,
                n.per_axis[0],
                n.per_axis[1],
                n.per_axis[2],
                n.interval_95.0,
                n.interval_95.1,
                nees.verdict()
            );
            Some(nees)
        };
        let live: Vec<_> =
            log.live.iter().zip(&log.live_position_cov_m2).map(|((t, p), c)| (*t, p.translation.vector, *c)).collect();
        let path: Vec<_> = result
            .path
            .iter()
            .map(|o| (o.t_s, o.world_from_body.translation.vector, o.covariance.fixed_view::<3, 3>(0, 0).into_owned()))
            .collect();
        let synced: Vec<_> = log.buoy.iter().zip(&log.buoy_cov_m2).map(|((t, p), c)| (*t, *p, *c)).collect();
        let buoy = nees(synced, "buoy positions synchronised to the SLAM poses");
        let (fused_live, fused) = (nees(live, "live fused poses"), nees(path, "final fused path"));
        if fused_live.is_some() || fused.is_some() || buoy.is_some() {
            part.nees = Some(FusedNees { fused, fused_live, buoy });
        }
        series_truth = tp.iter().map(|(_, p)| (p.x, p.y)).collect();
    }
    if settings.plot {
        plot_trajectories(out_dir, &series_truth, &log.buoy, &result.slam_world, &fused);
    }
    Ok(part)
}

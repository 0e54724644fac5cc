//! The synchronizer as a [`Stage`]: its ports around [`SyncState`]. Fixes are taken before poses
//! in each wake-up, so that a pose and the fix that brackets it in one wake-up are paired.

use pipeline_runtime::StageError;
use std::time::Instant;

use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::summary::Percentiles;
use pipeline_runtime::{Input, Output, ProcessContext, Runtime, Wake};
use shared_types::services::{BUOY_FIX, SLAM_POSE, SYNC_PAIR};
use shared_types::{BuoyFix, MsgHeader, PoseEstimate, SyncedPair, convert};

use crate::summary::{FixCounts, SyncSummary, SynchronizerPart};
use crate::{SyncState, SynchronizerSettings};

/// The `synchronizer` stage.
pub struct SynchronizerStage {
    settings: SynchronizerSettings,
    st: SyncState,
    poses: Input<PoseEstimate, MsgHeader>,
    fixes: Input<BuoyFix, MsgHeader>,
    pairs: Output<SyncedPair, MsgHeader>,
}

impl Stage for SynchronizerStage {
    type Settings = SynchronizerSettings;

    fn open(_ctx: &ProcessContext, settings: SynchronizerSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        let st = SyncState::new(&settings).map_err(|p| StageError::Settings(format!("synchronizer: {p:?}")))?;
        let poses = rt.input(SLAM_POSE)?;
        let fixes = rt.input(BUOY_FIX)?;
        let pairs = rt.output(SYNC_PAIR)?;
        tracing::info!(max_latency_s = settings.sync.max_latency_s, end_after = ?settings.end_after, "synchronizer ready");
        Ok(Self { settings, st, poses, fixes, pairs })
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::from_list(&self.settings.end_after)
    }

    fn tick(&self) -> Option<std::time::Duration> {
        Some(std::time::Duration::from_millis(100))
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, inputs_ended: bool) -> Result<Step, StageError> {
        while let Some(s) = self.fixes.receive()? {
            self.st.push_fix(s.user_header(), s.payload());
        }
        let now = Instant::now();
        let mut predicted = vec![];
        while let Some(s) = self.poses.receive()? {
            let (h, pose) = (*s.user_header(), *s.payload());
            if self.settings.predict
                && let Some(p) = self.st.predict(&h, &pose)
            {
                predicted.push(p);
            }
            self.st.push_pose(h, pose, now);
        }
        let paired = self.st.step(Instant::now(), inputs_ended);
        // A pose paired in this very wake-up needs no prediction.
        predicted.retain(|p| !paired.iter().any(|q| q.header.stamp_ns == p.header.stamp_ns));
        for p in predicted.into_iter().chain(paired) {
            self.st.stats.predicted += u64::from(p.predicted);
            let b = &p.buoy;
            self.pairs.send_value(
                MsgHeader { stamp_ns: p.header.stamp_ns, origin_ns: p.header.origin_ns, ..Default::default() },
                SyncedPair {
                    slam: p.pose,
                    buoy_position_m: b.position_m.into(),
                    buoy_covariance_m2: convert::mat3_to_row_major(&b.covariance_m2),
                    newest_fix_stamp_ns: (b.newest_fix_s * 1e9).round().max(0.0) as u64,
                    flags: b.flags.bits() | if p.predicted { shared_types::SYNC_PREDICTED } else { 0 },
                    fixes_used: b.fixes_used as u32,
                },
            )?;
        }
        if let Some(deadline) = self.st.next_deadline() {
            rt.wake_at(deadline);
        }
        // Poses waiting for their fix: lost (and counted) if it is killed now.
        self.poses.set_held(self.st.pending.len() as u64);
        Ok(if self.st.pending.is_empty() { Step::Idle } else { Step::Pending })
    }

    type Summary = SynchronizerPart;

    fn finish(&mut self, _rt: &mut Runtime, _ending: Ending) -> Result<Self::Summary, StageError> {
        let st = &self.st;
        let ms: Vec<f64> = st.added_latency_s.iter().map(|s| s * 1e3).collect();
        let added_latency_ms = Percentiles::of(&ms);
        let max_latency_ms = self.settings.sync.max_latency_s * 1e3;
        tracing::info!(
            pairs = ms.len(),
            extrapolated = st.stats.extrapolated,
            unavailable = st.stats.unavailable,
            "added latency p50 {:.2} ms, max {:.2} ms (bound {max_latency_ms:.0} ms)",
            added_latency_ms.p50.unwrap_or(f64::NAN),
            added_latency_ms.max.unwrap_or(f64::NAN),
        );
        Ok(SynchronizerPart {
            synchronizer: SyncSummary {
                pairs: ms.len() as u64,
                poses: st.stats.clone(),
                fixes: FixCounts::from(st.synchronizer().counters()),
                max_latency_ms,
                added_latency_ms,
            },
        })
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.pairs.sent().saturating_sub(1), self.pairs.sent())
    }
}

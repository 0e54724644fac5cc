//! One shape for every stage: a [`Stage`] is its state plus what it does on a wake-up, and the
//! runtime owns everything around it ([`run_stage`]):
//!
//! - the loop (a WaitSet that never spins), heartbeats and statistics (see [`Runtime::run`]);
//! - the end of stream: it reads the ends of stream before the data in each wake-up (so nothing
//!   sent before an end is missed), tracks which upstream processes ended, and decides when the
//!   stage's inputs are over by one rule, [`Stage::end_after`] ([`EndAfter`]): every process
//!   named in the stage's `end_after` setting has ended, or, with an empty list, the first
//!   upstream process has. Then, once the stage says it is idle, it calls [`Stage::finish`],
//!   writes the summary part, and sends the stage's own end of stream. A source ends itself
//!   ([`EndAfter::Itself`], [`Step::Done`]);
//! - a stop (SIGTERM/SIGINT) before that: [`Stage::finish`] with [`Ending::Stopped`], so that
//!   whatever the stage has is written and scored;
//! - the summary part: `<out>/parts/<process>.json`, the object `finish` returns, plus
//!   `processes.<name>.upstream_failed` when an upstream process failed for good;
//! - after its end the process stays up (its last samples stay valid for slow readers) until
//!   the supervisor stops it.
//!
//! A stage's `main` is [`stage_main`]: `fn main() -> ExitCode { pipeline_runtime::stage_main::<MyStage>() }`.

use std::collections::BTreeSet;
use std::path::Path;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use shared_types::services::END_OF_STREAM;
use shared_types::{EndOfStream, MsgHeader};

use crate::config::ProcessSettings;
use crate::error::StageError;
use crate::ports::Input;
use crate::restart::{Restart, StateStore};
use crate::runtime::{Flow, ProcessContext, Runtime, StopReason, Wake};

/// What a wake-up left.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step {
    /// Nothing left to do until more data arrives (or the next tick).
    Idle,
    /// Work is pending on something to come (data, or a deadline the stage set with
    /// [`Runtime::wake_at`]): not finished even when the inputs have ended.
    Pending,
    /// Work left in the stage's own queue: wake again at once (the inputs are drained between
    /// steps, so a source waiting on this stage never waits for more than one step).
    Busy,
    /// The stage has ended its stream by itself (a source at the end of its data): finish now.
    Done,
}

/// How a stage's run ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ending {
    /// Its inputs ended and everything was processed (or a source reached its end).
    EndOfStream,
    /// Stopped by a signal before that: write what there is.
    Stopped,
}

/// When a stage's inputs are over.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EndAfter {
    /// When the first upstream process ends: one that published one of the stage's inputs (the
    /// end of a process that feeds it nothing, a recorder say, does not end it).
    FirstUpstream,
    /// When every process named has ended.
    All(Vec<String>),
    /// Never by its inputs: the stage ends itself with [`Step::Done`] (a source).
    Itself,
}

impl EndAfter {
    /// The rule of an `end_after` setting: every process listed; empty, the first upstream one.
    pub fn from_list(list: &[String]) -> Self {
        if list.is_empty() { EndAfter::FirstUpstream } else { EndAfter::All(list.to_vec()) }
    }

    /// True when the inputs are over, given the other processes that `ended` and those of them
    /// that `fed` the stage (published one of its inputs, or did not say what they published).
    pub fn inputs_ended(&self, ended: &BTreeSet<String>, fed: &BTreeSet<String>) -> bool {
        match self {
            EndAfter::FirstUpstream => !fed.is_empty(),
            EndAfter::All(names) => names.iter().all(|n| ended.contains(n)),
            EndAfter::Itself => false,
        }
    }
}

/// A pipeline stage. See the module docs for what the runtime does around it.
pub trait Stage: Sized {
    /// Its settings (`[processes.<name>.settings]`), validated before [`Stage::open`] (and by
    /// `--check`).
    type Settings: ProcessSettings;

    /// Builds the stage: opens its inputs and outputs on `rt`, restores a killed instance's state
    /// if it keeps one.
    fn open(ctx: &ProcessContext, settings: Self::Settings, rt: &mut Runtime) -> Result<Self, StageError>;

    /// When this stage's inputs are over (usually `EndAfter::from_list(&settings.end_after)`).
    fn end_after(&self) -> EndAfter;

    /// Interval of the stage's own tick (`wake.tick`), if it wants one.
    fn tick(&self) -> Option<Duration> {
        None
    }

    /// One wake-up: drain the inputs, do the work, publish. `inputs_ended`: every upstream
    /// process the stage waits for has ended, and everything they sent is already queued.
    fn step(&mut self, rt: &mut Runtime, wake: Wake, inputs_ended: bool) -> Result<Step, StageError>;

    /// This stage's part of summary.json: a struct that serialises to a JSON object (merged into
    /// the summary by the supervisor), deriving `schemars::JsonSchema` as well so that
    /// docs/summary.schema.json describes its keys and units.
    type Summary: serde::Serialize + schemars::JsonSchema;

    /// The end ([`Ending`]): write the final outputs and return this stage's part of summary.json.
    /// Long work should call [`Runtime::keep_alive`] between its parts.
    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError>;

    /// `(last_seq, messages_sent)` of the stage's main output, for its end of stream.
    fn end_of_stream(&self) -> (u64, u64);

    /// A restarted instance (the supervisor restarted the process after a kill or a failure):
    /// what its predecessors kept through [`Runtime::state`] (journal lines, snapshots). Called
    /// once, after [`Stage::open`] and before the first wake-up. Returns how many journal lines
    /// it took, in order: the runtime keeps those and drops the rest (a line this version cannot
    /// read), so the journal goes on from what the stage has. The default keeps nothing (a stage
    /// without restart state starts over).
    fn restore(&mut self, restart: Restart) -> Result<usize, StageError> {
        let _ = restart;
        Ok(0)
    }

    /// Whether the runtime sends this stage's end of stream after [`Stage::finish`] (a replayer
    /// told not to, because the recording carries the ends of stream of the processes it replays).
    fn sends_end_of_stream(&self) -> bool {
        true
    }
}

/// A stage's summary as a JSON object: `null` (a `Summary` of `None`: nothing to report) is `{}`.
fn summary_object(v: serde_json::Value) -> serde_json::Value {
    if v.is_null() { serde_json::json!({}) } else { v }
}

/// Writes a summary part (`<out>/parts/<process>.json`).
pub fn write_summary_part(out_dir: &Path, name: &str, part: &serde_json::Value) -> Result<(), StageError> {
    let dir = out_dir.join("parts");
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join(format!("{name}.json")), serde_json::to_vec_pretty(part)?)?;
    Ok(())
}

/// The runtime's bookkeeping around a [`Stage`]: the end-of-stream input, which upstream
/// processes ended, and whether the stage has finished. [`run_stage`] calls [`Driver::wake`]
/// on every wake-up of the loop; [`crate::testing::StageHarness`] calls it directly.
pub(crate) struct Driver {
    eos: Input<EndOfStream, MsgHeader>,
    end_after: EndAfter,
    ended: BTreeSet<String>,
    /// Of `ended`, the processes that fed this stage's inputs.
    fed: BTreeSet<String>,
    /// The summary part, once the stage has finished.
    pub(crate) part: Option<serde_json::Value>,
    run_dir: std::path::PathBuf,
    name: String,
}

impl Driver {
    /// Opens the end-of-stream input and the restart state on `rt` for `stage`; a restarted
    /// instance (`restart`) gets its predecessors' state ([`Stage::restore`]).
    pub(crate) fn new<S: Stage>(
        ctx: &ProcessContext,
        rt: &mut Runtime,
        stage: &mut S,
        restart: bool,
    ) -> Result<Self, StageError> {
        let remapped = rt.remapped_inputs();
        if stage.end_after() == EndAfter::FirstUpstream && !remapped.is_empty() {
            let list = remapped.iter().map(|(f, t)| format!("`{f}` as `{t}`")).collect::<Vec<_>>().join(", ");
            return Err(StageError::Settings(format!(
                "processes.{}: its inputs {list} are remapped, so the end of stream cannot tell which \
                 process feeds them: name the processes it ends after in its `end_after` setting",
                ctx.name
            )));
        }
        std::fs::create_dir_all(&ctx.out_dir)?;
        let (mut store, restored) = StateStore::open(&ctx.run_dir, &ctx.name, restart)?;
        let restored_seqs = restored.as_ref().map(|r| r.input_seqs.clone());
        if let Some(r) = restored {
            let lines = r.journal.len();
            let kept = stage.restore(r.clone())?.min(lines);
            store.keep(&r, kept)?;
            tracing::info!(
                journal_lines = kept,
                snapshots = r.snapshots.len(),
                "restarted: took the state the killed instance kept"
            );
            if kept < lines || r.cut_lines > 0 {
                tracing::warn!(
                    dropped = lines - kept + r.cut_lines,
                    "journal lines dropped on restart (cut short by the kill, or unreadable): what they \
                     recorded is lost"
                );
            }
        }
        rt.set_state(store);
        if let Some(r) = &restored_seqs {
            rt.resume_inputs(r);
        }
        Ok(Self {
            eos: rt.input::<EndOfStream, MsgHeader>(END_OF_STREAM)?,
            end_after: stage.end_after(),
            ended: BTreeSet::new(),
            fed: BTreeSet::new(),
            part: None,
            run_dir: ctx.run_dir.clone(),
            name: ctx.name.clone(),
        })
    }

    /// True once the stage has finished.
    pub(crate) fn done(&self) -> bool {
        self.part.is_some()
    }

    fn with_failures(&self, rt: &Runtime, mut part: serde_json::Value) -> serde_json::Value {
        let failed = rt.failed_upstream();
        if !failed.is_empty() && part.is_object() {
            part["processes"][&self.name]["upstream_failed"] = serde_json::json!(failed);
        }
        part
    }

    /// One wake-up: the ends of stream, then the stage's step; at the end of its inputs (or
    /// when it is done by itself) its finish, the summary part and its end of stream. Returns
    /// the step (`None` once finished).
    pub(crate) fn wake<S: Stage>(
        &mut self,
        rt: &mut Runtime,
        stage: &mut S,
        wake: Wake,
    ) -> Result<Option<Step>, StageError> {
        if self.done() {
            return Ok(None);
        }
        for (name, outputs) in rt.ends_upstream(&self.eos)? {
            // (before the data: see Runtime::ended_upstream)
            if rt.feeds_inputs(outputs) {
                self.fed.insert(name.clone());
            } else if self.end_after == EndAfter::FirstUpstream {
                tracing::info!(process = %name, "`{name}` ended; it published none of this stage's inputs: going on");
            }
            self.ended.insert(name);
        }
        let over = self.end_after.inputs_ended(&self.ended, &self.fed);
        let step = stage.step(rt, wake, over)?;
        rt.state().flush()?;
        rt.save_inputs()?;
        if step == Step::Busy {
            rt.wake_at(Instant::now());
        }
        if step == Step::Done || (over && step == Step::Idle) {
            let part = summary_object(serde_json::to_value(stage.finish(rt, Ending::EndOfStream)?)?);
            rt.state().flush()?;
            let part = self.with_failures(rt, part);
            write_summary_part(&self.run_dir, &self.name, &part)?;
            self.part = Some(part);
            if stage.sends_end_of_stream() {
                let (last_seq, sent) = stage.end_of_stream();
                rt.send_end_of_stream(last_seq, sent)?;
            }
        }
        Ok(Some(step))
    }

    /// A stop before the end of the inputs: the stage's finish with [`Ending::Stopped`] and the
    /// summary part (nothing when it has finished already).
    pub(crate) fn stop<S: Stage>(&mut self, rt: &mut Runtime, stage: &mut S) -> Result<(), StageError> {
        if self.done() {
            return Ok(());
        }
        tracing::info!("stopped before the end of its inputs: writing what there is");
        let part = summary_object(serde_json::to_value(stage.finish(rt, Ending::Stopped)?)?);
        let part = self.with_failures(rt, part);
        write_summary_part(&self.run_dir, &self.name, &part)?;
        self.part = Some(part);
        Ok(())
    }
}

/// Runs `stage` to its end and until the process is stopped (see the module docs).
pub fn run_stage<S: Stage>(ctx: &ProcessContext, rt: &mut Runtime, mut stage: S) -> Result<StopReason, StageError> {
    let mut driver = Driver::new(ctx, rt, &mut stage, crate::restart::is_restart())?;
    let tick = stage.tick();
    let stop = rt.run(&mut stage, tick, |rt, stage, wake| {
        driver.wake(rt, stage, wake)?;
        Ok::<_, StageError>(Flow::Continue)
    })?;
    driver.stop(rt, &mut stage)?;
    Ok(stop)
}

/// The whole `main` of a stage: `--check` (see [`crate::protocol`]), logging, the context and
/// runtime, [`Stage::open`] with its validated settings, and [`run_stage`].
pub fn stage_main<S: Stage>() -> ExitCode {
    crate::protocol::process_main::<S::Settings, StageError>(|args| {
        let (ctx, mut rt) = Runtime::start(args)?;
        let settings: S::Settings = ctx.settings()?;
        let stage = S::open(&ctx, settings, &mut rt)?;
        run_stage(&ctx, &mut rt, stage)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_rule_for_the_end_of_the_inputs() {
        let ended = |names: &[&str]| names.iter().map(|s| s.to_string()).collect::<BTreeSet<_>>();
        let none = ended(&[]);
        let all = EndAfter::from_list(&["slam".to_string(), "buoy".to_string()]);
        assert!(!all.inputs_ended(&none, &none));
        assert!(!all.inputs_ended(&ended(&["slam"]), &ended(&["slam"])));
        assert!(all.inputs_ended(&ended(&["buoy", "slam", "other"]), &none), "named processes, fed or not");
        let first = EndAfter::from_list(&[]);
        assert_eq!(first, EndAfter::FirstUpstream, "an empty list waits for the first upstream end");
        assert!(!first.inputs_ended(&none, &none));
        assert!(!first.inputs_ended(&ended(&["recorder"]), &none), "a process that fed nothing");
        assert!(first.inputs_ended(&ended(&["recorder", "ingest"]), &ended(&["ingest"])));
        let both = ended(&["ingest", "slam"]);
        assert!(!EndAfter::Itself.inputs_ended(&both, &both), "a source ends itself");
    }
}

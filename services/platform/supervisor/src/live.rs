//! The live view: when the supervisor's stdout is a terminal, one status block redrawn in place
//! (`indicatif`) instead of a status line every `run.status_interval_s`:
//!
//! ```text
//! [######################>-----------------]  56% of the data · 00:00:41 elapsed · ETA 00:00:32
//! process        state        msg/s  backlog  dropped  restarts
//! ingest         ready       1203.4        0        0         0
//! slam           ready         10.1        2        0         0
//! ```
//!
//! The progress bar follows the sources' own progress (a replay's share of its data time, a
//! simulation's share of its mission: `Runtime::set_progress`), its ETA is indicatif's estimate
//! from the rate of that progress. Per process: its state, messages per second (in and out), its
//! backlog (messages published on its inputs that it has not taken yet), what it dropped by its
//! own policy, and its restarts. The full log (the supervisor's and every process's stdout and
//! stderr) goes to `<out>/run.log`; warnings and errors are also printed above the block. At the
//! end the block stays as it was last drawn and the summary follows it.
//!
//! `--no-live` (or a stdout that is not a terminal: a pipe, a file, CI) keeps the plain log on
//! stderr with the periodic status line.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};

/// How often the block is redrawn with new numbers.
const REDRAW: Duration = Duration::from_millis(500);
/// Window of the per-process message rate.
const RATE_WINDOW: Duration = Duration::from_secs(1);

/// Whether a run shows the live view: stdout a terminal and not turned off with `--no-live`.
pub fn wanted(no_live: bool) -> bool {
    !no_live && std::io::IsTerminal::is_terminal(&std::io::stdout())
}

/// `<out>/run.log`, shared by the supervisor's log sink and the threads that forward the
/// processes' output.
struct RunLog {
    file: Mutex<File>,
    /// Where warnings go besides the file: above the block while it lives, then plain stderr.
    multi: Mutex<Option<MultiProgress>>,
}

impl RunLog {
    fn write(&self, line: &[u8], loud: bool) {
        {
            let mut f = self.file.lock().unwrap_or_else(|e| e.into_inner());
            // A full disk must not stop the run: the line is lost from the file only.
            let _ = f.write_all(line);
            if !line.ends_with(b"\n") {
                let _ = f.write_all(b"\n");
            }
        }
        if loud {
            let text = String::from_utf8_lossy(line);
            let text = text.trim_end();
            match &*self.multi.lock().unwrap_or_else(|e| e.into_inner()) {
                Some(m) => {
                    let _ = m.println(text);
                }
                None => eprintln!("{text}"),
            }
        }
    }
}

/// Whether a process's log line is a warning or an error: the level is the second word of a text
/// line (after the time stamp), or the `level` field of a JSON line.
fn is_loud(line: &[u8]) -> bool {
    if line.starts_with(b"{") {
        let has = |n: &[u8]| line.windows(n.len()).any(|w| w == n);
        return has(b"\"level\":\"WARN\"") || has(b"\"level\":\"ERROR\"");
    }
    let text = String::from_utf8_lossy(line);
    matches!(text.split_whitespace().nth(1), Some("WARN" | "ERROR"))
}

/// What the block shows of one process.
#[derive(Debug, Clone, Default)]
pub struct RowView {
    /// Process name.
    pub name: String,
    /// State label (starting, ready, backoff, done, failed, ...).
    pub state: String,
    /// Messages in and out so far, over its instances.
    pub messages: u64,
    /// Messages published on its inputs that it has not taken yet.
    pub backlog: u64,
    /// Messages it dropped by its own policy, plus messages of its outputs that reached no
    /// subscriber.
    pub dropped: u64,
    /// Restarts so far.
    pub restarts: u32,
    /// Its source's progress, 0 to 1, when it reports one.
    pub progress: Option<f64>,
}

/// The live status block and the run's log file.
pub struct Live {
    bar: ProgressBar,
    header: ProgressBar,
    rows: Vec<ProgressBar>,
    log: Arc<RunLog>,
    path: PathBuf,
    last_draw: Option<Instant>,
    /// Per row: (time, messages) at the start of the rate window, and the last rate.
    rates: Vec<(Instant, u64, f64)>,
}

impl Live {
    /// Opens `<out_dir>/run.log` (truncated), sends the supervisor's log lines there from now on,
    /// and draws an empty block for `names`.
    pub fn start(out_dir: &Path, names: &[String]) -> std::io::Result<Self> {
        let path = out_dir.join("run.log");
        let file = File::create(&path)?;
        let multi = MultiProgress::with_draw_target(ProgressDrawTarget::stdout());
        let log = Arc::new(RunLog { file: Mutex::new(file), multi: Mutex::new(Some(multi.clone())) });
        let sink = log.clone();
        pipeline_runtime::logging::set_line_sink(Some(Arc::new(move |level, line| {
            sink.write(line, level <= tracing::Level::WARN)
        })));
        let bar = multi.add(ProgressBar::new(1000));
        bar.set_style(Self::waiting_style());
        bar.set_message("waiting for a source to report its progress");
        // Each line cut at the terminal's width: a wrapped line would break the redraw in place.
        let text = ProgressStyle::with_template("{wide_msg}").expect("a valid template");
        let header = multi.add(ProgressBar::new(0).with_style(text.clone()));
        header.set_message(format!(
            "{:<14} {:<10} {:>8} {:>7} {:>7} {:>8}",
            "process", "state", "msg/s", "backlog", "dropped", "restarts"
        ));
        let now = Instant::now();
        let rows = names
            .iter()
            .map(|n| {
                let r = multi.add(ProgressBar::new(0).with_style(text.clone()));
                r.set_message(format!("{n:<14} {:<10}", "pending"));
                r
            })
            .collect();
        Ok(Self { bar, header, rows, log, path, last_draw: None, rates: vec![(now, 0, 0.0); names.len()] })
    }

    fn waiting_style() -> ProgressStyle {
        ProgressStyle::with_template("{spinner} {elapsed_precise} elapsed · {wide_msg}").expect("a valid template")
    }

    fn progress_style() -> ProgressStyle {
        ProgressStyle::with_template(
            "[{wide_bar}] {percent:>3}% of the data · {elapsed_precise} elapsed · ETA {eta_precise}",
        )
        .expect("a valid template")
        .progress_chars("#>-")
    }

    /// The path of the run's log file.
    pub fn log_path(&self) -> &Path {
        &self.path
    }

    /// Forwards a process's stdout or stderr, line by line, to the run's log on a thread of its
    /// own (warnings and errors also above the block); the thread ends with the stream.
    pub fn forward(&self, stream: impl Read + Send + 'static) {
        let log = self.log.clone();
        let spawned = std::thread::Builder::new().name("live-log".into()).spawn(move || {
            let mut r = BufReader::new(stream);
            let mut line = Vec::new();
            loop {
                line.clear();
                match r.read_until(b'\n', &mut line) {
                    Ok(0) | Err(_) => break,
                    Ok(_) => log.write(&line, is_loud(&line)),
                }
            }
        });
        if let Err(e) = spawned {
            tracing::warn!("a process's output is not forwarded to run.log: {e}");
        }
    }

    /// Redraws the block from `rows` (in the order of `start`'s names) if it is due.
    pub fn draw(&mut self, now: Instant, rows: &[RowView]) {
        if self.last_draw.is_some_and(|t| now - t < REDRAW) {
            return;
        }
        self.last_draw = Some(now);
        // The slowest source sets the run's progress.
        let progress = rows.iter().filter_map(|r| r.progress).reduce(f64::min);
        if let Some(p) = progress {
            if self.bar.message().starts_with("waiting") {
                self.bar.set_style(Self::progress_style());
                self.bar.set_message("");
            }
            self.bar.set_position((p * 1000.0).round() as u64);
        } else {
            self.bar.tick();
        }
        for ((bar, row), rate) in self.rows.iter().zip(rows).zip(&mut self.rates) {
            let (t0, m0, last) = *rate;
            let dt = now - t0;
            if dt >= RATE_WINDOW {
                let r = row.messages.saturating_sub(m0) as f64 / dt.as_secs_f64();
                *rate = (now, row.messages, r);
            }
            let r = if dt >= RATE_WINDOW { rate.2 } else { last };
            let flag = if row.dropped > 0 || row.state == "failed" { " !" } else { "" };
            bar.set_message(format!(
                "{:<14} {:<10} {:>8.1} {:>7} {:>7} {:>8}{flag}",
                row.name, row.state, r, row.backlog, row.dropped, row.restarts
            ));
        }
    }

    /// Draws `rows` one last time and leaves the block on screen; log lines from now on go to
    /// the file, and warnings also to stderr.
    pub fn finish(mut self, rows: &[RowView]) {
        self.last_draw = None;
        self.draw(Instant::now(), rows);
        if self.bar.position() > 0 {
            self.bar.finish();
        } else {
            self.bar.finish_with_message("no source reported its progress");
        }
        self.header.finish();
        for r in &self.rows {
            r.finish();
        }
        *self.log.multi.lock().unwrap_or_else(|e| e.into_inner()) = None;
        // The cursor is at the end of the block's last line: the summary starts on a new one.
        println!();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warnings_and_errors_are_told_apart_from_other_lines_in_both_formats() {
        assert!(is_loud(b"2026-12-04T18:18:13.410478Z  WARN [link] lost"));
        assert!(is_loud(b"2026-12-04T18:18:13.410478Z ERROR [link] failed"));
        assert!(is_loud(br#"{"timestamp":"x","level":"WARN","fields":{}}"#));
        assert!(!is_loud(b"2026-12-04T18:18:13.410478Z  INFO [ingest] progress 50%: WARN in text"));
        assert!(!is_loud(br#"{"timestamp":"x","level":"INFO","fields":{"message":"WARN"}}"#));
    }
}

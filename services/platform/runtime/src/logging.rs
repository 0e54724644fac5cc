//! tracing setup: human-readable lines by default, JSON with `--log-format json`; the process
//! name is in every line. `RUST_LOG` filters as usual (default `info`). iceoryx2's own log goes
//! through tracing too (its `tracing` feature), at warnings and above unless `RUST_LOG` asks for more.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use tracing_subscriber::EnvFilter;
use tracing_subscriber::layer::SubscriberExt as _;
use tracing_subscriber::util::SubscriberInitExt as _;
use tracing_subscriber::{Layer as _, fmt};

use crate::config::LogFormat;

/// Installs the global subscriber for process `name`. Safe to call more than once (later calls
/// are ignored). Keep the returned guard alive for the whole `main`: in JSON mode it is the
/// `process` span that puts the name into every line.
#[must_use = "the process name is only in log lines while the guard lives"]
pub fn init(name: &str, format: LogFormat) -> Option<tracing::span::EnteredSpan> {
    init_with(name, format, std::io::IsTerminal::is_terminal(&std::io::stderr()))
}

/// Like [`init`], but every line goes to a [`LineSink`] instead of stderr once one is set with
/// [`set_line_sink`] (until then, to stderr), and colours are off: for the supervisor's live view,
/// which keeps its terminal for the status block and writes the full log to a file.
#[must_use = "the process name is only in log lines while the guard lives"]
pub fn init_redirectable(name: &str, format: LogFormat) -> Option<tracing::span::EnteredSpan> {
    REDIRECTABLE.store(true, Ordering::Relaxed);
    init_with(name, format, false)
}

/// Where log lines go after [`set_line_sink`]: each formatted line (with its newline) and its level.
pub type LineSink = Arc<dyn Fn(tracing::Level, &[u8]) + Send + Sync>;

static REDIRECTABLE: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
static SINK: std::sync::RwLock<Option<LineSink>> = std::sync::RwLock::new(None);

/// Lines logged after [`init_redirectable`] and before the first [`set_line_sink`]: handed to
/// the sink when it comes (warnings and errors also went to stderr at once).
static PENDING: std::sync::Mutex<Vec<(tracing::Level, Vec<u8>)>> = std::sync::Mutex::new(Vec::new());

/// Sends every log line from now on to `sink` (`None`: back to stderr), after the lines logged
/// since [`init_redirectable`] while there was none. Has an effect only after
/// [`init_redirectable`].
pub fn set_line_sink(sink: Option<LineSink>) {
    let mut slot = SINK.write().unwrap_or_else(|e| e.into_inner());
    if let Some(f) = &sink {
        for (level, line) in std::mem::take(&mut *PENDING.lock().unwrap_or_else(|e| e.into_inner())) {
            f(level, &line);
        }
    }
    *slot = sink;
}

/// The writer of one log line: collected, then handed to the sink (or stderr) whole on drop.
struct LineWriter {
    level: tracing::Level,
    buf: Vec<u8>,
}

impl std::io::Write for LineWriter {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.buf.extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Drop for LineWriter {
    fn drop(&mut self) {
        if self.buf.is_empty() {
            return;
        }
        let redirectable = REDIRECTABLE.load(Ordering::Relaxed);
        let sink = if redirectable { SINK.read().unwrap_or_else(|e| e.into_inner()).clone() } else { None };
        match sink {
            Some(f) => f(self.level, &self.buf),
            None => {
                if redirectable {
                    // Until the sink comes: kept for it, and only warnings and errors shown now.
                    let mut pending = PENDING.lock().unwrap_or_else(|e| e.into_inner());
                    if pending.len() < 10_000 {
                        pending.push((self.level, self.buf.clone()));
                    }
                    if self.level > tracing::Level::WARN {
                        return;
                    }
                }
                // A closed stderr is ignored (see `init_with`).
                let _ = std::io::Write::write_all(&mut std::io::stderr().lock(), &self.buf);
            }
        }
    }
}

struct MakeLineWriter;

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for MakeLineWriter {
    type Writer = LineWriter;
    fn make_writer(&'a self) -> LineWriter {
        LineWriter { level: tracing::Level::INFO, buf: Vec::new() }
    }
    fn make_writer_for(&'a self, meta: &tracing::Metadata<'_>) -> LineWriter {
        LineWriter { level: *meta.level(), buf: Vec::new() }
    }
}

fn init_with(name: &str, format: LogFormat, ansi: bool) -> Option<tracing::span::EnteredSpan> {
    // Zenoh's Unix-socket link warns on every connect ("Can not create a new UnixSocketStream
    // link bound to ...": a client's socket has no path of its own; zenoh-link-unixsock_stream
    // 1.10, `new_link`). The bridge's Zenoh connects only over Unix sockets, to its own TLS
    // relay, which reports its links' failures itself: at ERROR only, so that a WARN in a run's
    // log means something. RUST_LOG replaces this filter whole.
    let filter = EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| EnvFilter::new("info,zenoh_link_unixsock_stream::unicast=error"));
    iceoryx2::prelude::set_log_level(iceoryx2::prelude::LogLevel::Warn);
    // A closed stderr (output piped into `head`, a pager that quit) must not kill the process: by
    // default tracing-subscriber reports a failed write with `eprintln!`, which panics on a broken
    // pipe, and a supervisor that dies that way leaves its run's shared memory behind.
    let layer = match format {
        LogFormat::Text => fmt::layer()
            .with_writer(MakeLineWriter)
            .with_ansi(ansi)
            .log_internal_errors(false)
            .with_target(false)
            .fmt_fields(NamedFields(name.to_string()))
            .boxed(),
        LogFormat::Json => fmt::layer()
            .with_writer(MakeLineWriter)
            .with_ansi(ansi)
            .log_internal_errors(false)
            .json()
            .with_current_span(true)
            .with_span_list(false)
            .boxed(),
    };
    // The counters see their libraries' events at INFO and above whatever RUST_LOG says.
    let counted = tracing_subscriber::filter::Targets::new()
        .with_targets(COUNTED_TARGETS.iter().map(|t| (*t, tracing::Level::INFO)))
        .with_targets(WATCHED_TRACE_TARGETS.iter().map(|t| (*t, tracing::Level::TRACE)));
    let result =
        tracing_subscriber::registry().with(layer.with_filter(filter)).with(Counting.with_filter(counted)).try_init();
    PROCESS_NAME.get_or_init(|| name.to_string());
    match (format, result) {
        (LogFormat::Json, Ok(())) => Some(tracing::info_span!("process", process = name).entered()),
        _ => None,
    }
}

static PROCESS_NAME: std::sync::OnceLock<String> = std::sync::OnceLock::new();

/// The name given to [`init`].
pub fn process_name() -> &'static str {
    PROCESS_NAME.get().map(String::as_str).unwrap_or("?")
}

/// Field formatter that prefixes every line's fields with `[name]`.
struct NamedFields(String);

impl<'w> tracing_subscriber::fmt::FormatFields<'w> for NamedFields {
    fn format_fields<R: tracing_subscriber::field::RecordFields>(
        &self,
        mut writer: tracing_subscriber::fmt::format::Writer<'w>,
        fields: R,
    ) -> std::fmt::Result {
        write!(writer, "[{}] ", self.0)?;
        tracing_subscriber::fmt::format::DefaultFields::new().format_fields(writer, fields)
    }
}

/// Counters of log events from other crates, for what a library reports only in its log (the
/// Foxglove SDK's "outbox for client ... full": it dropped messages for a slow client).
static COUNTERS: std::sync::Mutex<Vec<(String, String, Arc<AtomicU64>)>> = std::sync::Mutex::new(Vec::new());

/// The libraries whose log events [`count_events`] can count (INFO and above, whatever the log's
/// own filter).
pub const COUNTED_TARGETS: &[&str] = &["foxglove", "zenoh_link_tls"];

/// The libraries whose log events [`watch_events`] also sees at TRACE and DEBUG: Zenoh's access
/// control reports a refused message only at TRACE (with the peer and the key), and nowhere else.
pub const WATCHED_TRACE_TARGETS: &[&str] = &["zenoh::net::routing::interceptor::access_control"];

/// What a watcher does with the message of an event it watches.
type Watcher = Box<dyn Fn(&str) + Send + Sync>;

/// Watchers of log events from other crates ([`watch_events`]).
static WATCHERS: std::sync::Mutex<Vec<(String, String, Watcher)>> = std::sync::Mutex::new(Vec::new());

/// Calls `f` with the message of every log event, from now on, whose target starts with
/// `target_prefix` (under one of [`COUNTED_TARGETS`] at INFO and above, or of
/// [`WATCHED_TRACE_TARGETS`] at any level) and whose message contains `needle`. `f` runs on the
/// thread that logged, while the watchers are locked: keep it short, and never log from it.
pub fn watch_events(target_prefix: &str, needle: &str, f: impl Fn(&str) + Send + Sync + 'static) {
    WATCHERS.lock().unwrap_or_else(|e| e.into_inner()).push((target_prefix.into(), needle.into(), Box::new(f)));
}

/// A counter of the log events whose target starts with `target_prefix` (under one of
/// [`COUNTED_TARGETS`]) and whose message contains `needle`, from now on. The count is of the
/// events, which a library may throttle: it says that something happened and how often it was
/// reported, not how many items it concerned.
pub fn count_events(target_prefix: &str, needle: &str) -> Arc<AtomicU64> {
    let c = Arc::new(AtomicU64::new(0));
    COUNTERS.lock().unwrap_or_else(|e| e.into_inner()).push((target_prefix.into(), needle.into(), c.clone()));
    c
}

struct Counting;

/// The `message` field of an event.
fn message_of(event: &tracing::Event<'_>) -> String {
    struct Message(String);
    impl tracing::field::Visit for Message {
        fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
            if field.name() == "message" {
                self.0 = format!("{value:?}");
            }
        }
        fn record_str(&mut self, field: &tracing::field::Field, value: &str) {
            if field.name() == "message" {
                self.0 = value.to_string();
            }
        }
    }
    let mut m = Message(String::new());
    event.record(&mut m);
    m.0
}

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for Counting {
    fn on_event(&self, event: &tracing::Event<'_>, _ctx: tracing_subscriber::layer::Context<'_, S>) {
        let target = event.metadata().target();
        let info_or_above = *event.metadata().level() <= tracing::Level::INFO;
        let mut message = None;
        if info_or_above {
            let counters = COUNTERS.lock().unwrap_or_else(|e| e.into_inner());
            for (_, needle, c) in counters.iter().filter(|(p, _, _)| target.starts_with(p.as_str())) {
                if message.get_or_insert_with(|| message_of(event)).contains(needle.as_str()) {
                    c.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
        let watched_level = info_or_above || WATCHED_TRACE_TARGETS.iter().any(|t| target.starts_with(t));
        if watched_level {
            let watchers = WATCHERS.lock().unwrap_or_else(|e| e.into_inner());
            for (_, needle, f) in watchers.iter().filter(|(p, _, _)| target.starts_with(p.as_str())) {
                let m = message.get_or_insert_with(|| message_of(event));
                if m.contains(needle.as_str()) {
                    f(m);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_of_a_target_with_a_message_are_counted() {
        let _g = init("test", LogFormat::Text);
        let full = count_events("foxglove::websocket", "outbox for client");
        let other = count_events("somewhere_else", "outbox for client");
        tracing::info!(target: "foxglove::websocket::connected_client::send_lossy", "outbox for client 127.0.0.1:5 full");
        tracing::info!(target: "foxglove::websocket::server", "client connected");
        tracing::info!("outbox for client in our own crate");
        // Counted whatever the log's filter (RUST_LOG) lets through; below INFO not.
        tracing::debug!(target: "foxglove::websocket", "outbox for client at debug");
        assert_eq!(full.load(Ordering::Relaxed), 1);
        assert_eq!(other.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn watched_events_are_seen_at_trace_for_the_watched_targets_only() {
        let _g = init("test", LogFormat::Text);
        let seen = Arc::new(std::sync::Mutex::new(vec![]));
        let s = seen.clone();
        watch_events("zenoh::net::routing::interceptor", "is unauthorized", move |m| {
            s.lock().unwrap().push(m.to_string())
        });
        tracing::trace!(target: "zenoh::net::routing::interceptor::access_control", "z1 is unauthorized to Put (ingress) on k");
        tracing::trace!(target: "zenoh::net::routing::interceptor::access_control", "z1 is authorized to Put (ingress) on k");
        tracing::trace!(target: "zenoh::net::routing::somewhere", "z2 is unauthorized to Put (ingress) on k");
        assert_eq!(*seen.lock().unwrap(), vec!["z1 is unauthorized to Put (ingress) on k".to_string()]);
    }
}

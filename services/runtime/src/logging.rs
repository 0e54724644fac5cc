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
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    iceoryx2::prelude::set_log_level(iceoryx2::prelude::LogLevel::Warn);
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    // A closed stderr (output piped into `head`, a pager that quit) must not kill the process: by
    // default tracing-subscriber reports a failed write with `eprintln!`, which panics on a broken
    // pipe, and a supervisor that dies that way leaves its run's shared memory behind.
    let layer = match format {
        LogFormat::Text => fmt::layer()
            .with_writer(std::io::stderr)
            .with_ansi(ansi)
            .log_internal_errors(false)
            .with_target(false)
            .fmt_fields(NamedFields(name.to_string()))
            .boxed(),
        LogFormat::Json => fmt::layer()
            .with_writer(std::io::stderr)
            .with_ansi(ansi)
            .log_internal_errors(false)
            .json()
            .with_current_span(true)
            .with_span_list(false)
            .boxed(),
    };
    // The counters see their libraries' events at INFO and above whatever RUST_LOG says.
    let counted = tracing_subscriber::filter::Targets::new()
        .with_targets(COUNTED_TARGETS.iter().map(|t| (*t, tracing::Level::INFO)));
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

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for Counting {
    fn on_event(&self, event: &tracing::Event<'_>, _ctx: tracing_subscriber::layer::Context<'_, S>) {
        let counters = COUNTERS.lock().unwrap_or_else(|e| e.into_inner());
        let target = event.metadata().target();
        if !counters.iter().any(|(prefix, _, _)| target.starts_with(prefix.as_str())) {
            return;
        }
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
        for (prefix, needle, c) in counters.iter() {
            if target.starts_with(prefix.as_str()) && m.0.contains(needle.as_str()) {
                c.fetch_add(1, Ordering::Relaxed);
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
}

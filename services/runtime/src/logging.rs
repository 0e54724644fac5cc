//! tracing setup: human-readable lines by default, JSON with `--log-format json`; the process
//! name is in every line. `RUST_LOG` filters as usual (default `info`). iceoryx2's own log goes
//! through tracing too (its `tracing` feature), at warnings and above unless `RUST_LOG` asks for more.

use tracing_subscriber::EnvFilter;

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
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(ansi)
        .log_internal_errors(false);
    let result = match format {
        LogFormat::Text => builder.with_target(false).fmt_fields(NamedFields(name.to_string())).try_init(),
        LogFormat::Json => builder.json().with_current_span(true).with_span_list(false).try_init(),
    };
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

//! Process kinds are plug-ins: the supervisor knows no stage. The binary of kind `k` is the
//! executable `k` next to the supervisor's own (or `processes.<name>.binary`), and it speaks the
//! runtime's protocol ([`pipeline_runtime::protocol`]): `--config F --name N` runs it, and with
//! `--check` it validates its own settings and prints a [`CheckReport`] (issues with their dotted
//! keys, its shared-memory estimate) which the pre-flight collects. A user's stage built on the
//! runtime is therefore a kind as soon as it is built, without a line changed here.
//!
//! The one built-in kind is `external`: any executable (C++, Python, a driver) given by
//! `binary`, started with its `args` only, taking no settings table.

use std::io::Read as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use pipeline_runtime::CheckReport;
use pipeline_runtime::config::ConfigIssue;
use pipeline_runtime::protocol::CHECK_PROTOCOL;

/// The kind of processes that do not speak the runtime's protocol.
pub const EXTERNAL: &str = "external";

/// How long a binary may take to answer `--check`.
pub const CHECK_TIMEOUT: Duration = Duration::from_secs(20);

/// True when `kind` can name a binary: ASCII letters, digits, `_` and `-`.
pub fn is_valid_kind_name(kind: &str) -> bool {
    !kind.is_empty() && kind.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// Where the binary of `kind` is by convention: `<bin_dir>/<kind>`.
pub fn conventional_binary(bin_dir: &Path, kind: &str) -> PathBuf {
    bin_dir.join(kind)
}

/// The settings of an `external` process: none (its options go in `args`).
pub fn check_external(name: &str, table: &toml::Table) -> Vec<ConfigIssue> {
    if table.is_empty() {
        vec![]
    } else {
        vec![ConfigIssue {
            key: format!("processes.{name}.settings"),
            message: "an external process takes no settings table; pass its options in `args`".into(),
        }]
    }
}

/// Runs `<binary> --check --config <config> --name <name>` and reads its verdict. An error says
/// why the binary gave none (it does not speak the protocol, failed, or hung).
pub fn run_check(binary: &Path, config: &Path, name: &str, timeout: Duration) -> Result<CheckReport, String> {
    let mut child = Command::new(binary)
        .arg("--check")
        .arg("--config")
        .arg(config)
        .arg("--name")
        .arg(name)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot run it: {e}"))?;
    let mut stdout = child.stdout.take().expect("piped");
    let mut stderr = child.stderr.take().expect("piped");
    let out = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stdout.read_to_string(&mut s);
        s
    });
    let err = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });
    let deadline = Instant::now() + timeout;
    let status = loop {
        match child.try_wait() {
            Ok(Some(status)) => break status,
            Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(5)),
            Ok(None) => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(format!("no answer to --check within {:.0} s", timeout.as_secs_f64()));
            }
            Err(e) => return Err(format!("waiting for it: {e}")),
        }
    };
    let (out, err) = (out.join().unwrap_or_default(), err.join().unwrap_or_default());
    let first_error_line = || err.lines().find(|l| !l.trim().is_empty()).unwrap_or("").trim().to_string();
    if !status.success() {
        return Err(format!("`--check` failed ({status}): {}", first_error_line()));
    }
    let report: CheckReport = out.lines().rev().find_map(|l| serde_json::from_str(l).ok()).ok_or_else(|| {
        "it does not speak the pipeline protocol (no JSON verdict from `--check` on stdout); \
                        a process that is not built on the runtime is kind = \"external\""
            .to_string()
    })?;
    if report.protocol != CHECK_PROTOCOL {
        return Err(format!(
            "it speaks protocol version {}, this supervisor {CHECK_PROTOCOL}: rebuild it against this runtime",
            report.protocol
        ));
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kind_names_are_file_names() {
        assert!(is_valid_kind_name("octree_mapper") && is_valid_kind_name("my-stage2"));
        for bad in ["", "../x", "a b", "a/b", "ü"] {
            assert!(!is_valid_kind_name(bad), "{bad}");
        }
    }

    #[test]
    fn a_binary_that_does_not_speak_the_protocol_is_named_as_such() {
        let e = run_check(Path::new("/bin/true"), Path::new("x.toml"), "p", CHECK_TIMEOUT).unwrap_err();
        assert!(e.contains("does not speak the pipeline protocol"), "{e}");
        let e = run_check(Path::new("/bin/false"), Path::new("x.toml"), "p", CHECK_TIMEOUT).unwrap_err();
        assert!(e.contains("`--check` failed"), "{e}");
        let e = run_check(Path::new("/nonexistent/bin"), Path::new("x.toml"), "p", CHECK_TIMEOUT).unwrap_err();
        assert!(e.contains("cannot run it"), "{e}");
        let e = run_check(Path::new("/bin/sleep"), Path::new("x.toml"), "p", Duration::from_millis(50));
        // `sleep --check` fails at once on an unknown option; either way it is not a verdict.
        assert!(e.is_err());
    }
}

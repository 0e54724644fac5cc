//! What a restarted process finds: the supervisor tells each instance how many times the process
//! was restarted before it ([`ENV_RESTARTS`], 0 for the first), and stages that keep state for a
//! restart put it under `<out_dir>/state/` ([`state_path`]). A first instance ignores (and
//! overwrites) whatever an earlier run left there; only a restart reads it back.
//!
//! Journals are text, one record per line, appended as the stage goes: a line cut short by the
//! kill is dropped with everything after it ([`parse_lines`]).

use std::fs::File;
use std::path::{Path, PathBuf};

/// An error with a process's restart state: the file and what was being done are named.
#[derive(Debug, thiserror::Error)]
pub enum StateError {
    /// Reading, creating or writing a state file failed.
    #[error("{action} the restart state {}: {source}", path.display())]
    Io {
        /// What was being done ("reading", "creating", "writing").
        action: &'static str,
        /// The file (or its directory).
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A state file holds something that cannot be restored.
    #[error("the restart state {}: {what}", path.display())]
    Malformed {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        what: String,
    },
}

impl StateError {
    /// An I/O error while `action` on `path`.
    pub fn io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> StateError + use<> {
        let path = path.to_path_buf();
        move |source| StateError::Io { action, path, source }
    }
}

/// Environment variable in which the supervisor gives the number of restarts before this instance.
pub const ENV_RESTARTS: &str = "SLAM_PIPELINE_RESTARTS";

/// Restarts before this instance (0 for the first, or when not run by the supervisor).
pub fn restart_count() -> u32 {
    std::env::var(ENV_RESTARTS).ok().and_then(|v| v.parse().ok()).unwrap_or(0)
}

/// True when the supervisor started this process as a restart of a killed or failed instance.
pub fn is_restart() -> bool {
    restart_count() > 0
}

/// `<out_dir>/state/<process>.<extension>`: where a process keeps state for its restart.
pub fn state_path(out_dir: &Path, process: &str, extension: &str) -> PathBuf {
    out_dir.join("state").join(format!("{process}.{extension}"))
}

/// The text of a state file, `None` if there is none.
pub fn read_state_text(path: &Path) -> Result<Option<String>, StateError> {
    match std::fs::read_to_string(path) {
        Ok(t) => Ok(Some(t)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(StateError::io("reading", path)(e)),
    }
}

/// Creates (truncating) a state file and its directory.
pub fn create_state_file(path: &Path) -> Result<File, StateError> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(StateError::io("creating the directory of", path))?;
    }
    File::create(path).map_err(StateError::io("creating", path))
}

/// Feeds the lines of a journal to `parse` until one does not parse (returns false): that line,
/// cut short by a kill, is dropped with every line after it. Returns the number of lines dropped.
pub fn parse_lines(text: &str, mut parse: impl FnMut(&str) -> bool) -> usize {
    let lines: Vec<&str> = text.lines().collect();
    lines.iter().position(|l| !parse(l)).map_or(0, |i| lines.len() - i)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cut_line_is_dropped_with_the_rest_and_a_missing_file_is_no_state() {
        let mut seen = vec![];
        let dropped = parse_lines("1\n2\nx\n4\n", |l| l.parse::<u32>().map(|v| seen.push(v)).is_ok());
        assert_eq!((seen, dropped), (vec![1, 2], 2));
        assert_eq!(parse_lines("", |_| false), 0);
        let dir = tempfile::tempdir().expect("temp dir");
        let path = state_path(dir.path(), "slam", "journal");
        assert!(path.ends_with("state/slam.journal"));
        assert!(read_state_text(&path).expect("no file").is_none());
        drop(create_state_file(&path).expect("create"));
        assert_eq!(read_state_text(&path).expect("read").as_deref(), Some(""));
    }
}

//! What a restarted process finds: the supervisor tells each instance how many times the process
//! was restarted before it ([`ENV_RESTARTS`], 0 for the first), and the runtime keeps each stage's
//! restart state under `<out_dir>/state/<process>/` ([`StateStore`]): a journal of text lines the
//! stage records as it goes ([`StateStore::record`], reached through
//! [`Runtime::state`](crate::Runtime::state)) and named snapshots ([`StateStore::snapshot`]).
//! A first instance starts with an empty directory; a restarted one is given what is there
//! ([`Restart`], through [`Stage::restore`](crate::Stage::restore)), and the runtime keeps the
//! journal lines the stage took: a line cut short by the kill is dropped with everything after it.

use std::fs::File;
use std::io::Write as _;
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

/// The text of a state file, `None` if there is none.
fn read_state_text(path: &Path) -> Result<Option<String>, StateError> {
    match std::fs::read_to_string(path) {
        Ok(t) => Ok(Some(t)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(StateError::io("reading", path)(e)),
    }
}

/// What a restarted instance gets back from its killed predecessors ([`crate::Stage::restore`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Restart {
    /// The journal's lines, in the order they were recorded (only whole lines: one cut short by
    /// the kill is not here, and counted in `cut_lines`).
    pub journal: Vec<String>,
    /// Journal lines cut short by the kill (0 or 1).
    pub cut_lines: usize,
    /// The snapshots, by key: their files (read them with [`Restart::read_snapshot`], or hand
    /// the path to a library that reads files).
    pub snapshots: std::collections::BTreeMap<String, PathBuf>,
    /// Per input service and publisher, the first sequence number the killed instance had not
    /// received or not kept (kept by the runtime, [`StateStore::save_inputs`]): the runtime
    /// counts what the restarted instance finds missing from there.
    pub input_seqs: Vec<(String, u128, u64)>,
}

impl Restart {
    /// The bytes of snapshot `key`, `None` if there is none.
    pub fn read_snapshot(&self, key: &str) -> Result<Option<Vec<u8>>, StateError> {
        match self.snapshots.get(key) {
            Some(p) => std::fs::read(p).map(Some).map_err(StateError::io("reading", p)),
            None => Ok(None),
        }
    }
}

/// The restart state of one process, kept by the runtime under `<out_dir>/state/<process>/`:
/// an append-only journal (`journal`, text lines the stage records as it goes, written in one
/// write per [`StateStore::flush`]) and named snapshots (`<key>`, each replaced atomically by a
/// temporary file renamed over it). A first instance starts with an empty directory (whatever
/// an earlier run left is removed); a restarted one is given what is there
/// ([`StateStore::open`]) and keeps the journal lines its stage took ([`StateStore::keep`]).
#[derive(Debug)]
pub struct StateStore {
    dir: Option<PathBuf>,
    journal: Option<File>,
    /// `.inputs`: where the inputs stand, overwritten in place.
    inputs: Option<File>,
    buffer: String,
    /// Journal lines recorded (and flushed) so far.
    lines: u64,
}

impl StateStore {
    /// A store that keeps nothing (a process without restart state, or a test fixture).
    pub fn disabled() -> Self {
        Self { dir: None, journal: None, inputs: None, buffer: String::new(), lines: 0 }
    }

    /// `<out_dir>/state/<process>/`.
    pub fn dir_of(out_dir: &Path, process: &str) -> PathBuf {
        out_dir.join("state").join(process)
    }

    /// Opens the store of `process`: for a restart (`restart`), what the killed instances left;
    /// else an empty directory.
    pub fn open(out_dir: &Path, process: &str, restart: bool) -> Result<(Self, Option<Restart>), StateError> {
        let dir = Self::dir_of(out_dir, process);
        let restored = if restart { Some(Self::read(&dir)?) } else { None };
        if !restart && dir.exists() {
            std::fs::remove_dir_all(&dir).map_err(StateError::io("removing", &dir))?;
        }
        std::fs::create_dir_all(&dir).map_err(StateError::io("creating", &dir))?;
        let path = dir.join("journal");
        // Rewritten by `keep` on a restart; empty for a first instance.
        let journal = if restart {
            std::fs::OpenOptions::new().create(true).append(true).open(&path)
        } else {
            File::create(&path)
        }
        .map_err(StateError::io("creating", &path))?;
        let inputs_path = dir.join(INPUTS_FILE);
        // A restart keeps what is there until its first save (which carries it on).
        let inputs = std::fs::OpenOptions::new()
            .create(true)
            .write(true)
            .truncate(!restart)
            .open(&inputs_path)
            .map_err(StateError::io("creating", &inputs_path))?;
        Ok((
            Self { dir: Some(dir), journal: Some(journal), inputs: Some(inputs), buffer: String::new(), lines: 0 },
            restored,
        ))
    }

    fn read(dir: &Path) -> Result<Restart, StateError> {
        let mut r = Restart::default();
        let path = dir.join("journal");
        if let Some(text) = read_state_text(&path)? {
            r.journal = text.split_inclusive('\n').map(|l| l.to_string()).collect();
            if r.journal.last().is_some_and(|l| !l.ends_with('\n')) {
                r.journal.pop();
                r.cut_lines = 1;
            }
            for l in &mut r.journal {
                l.pop();
            }
        }
        if let Some(text) = read_state_text(&dir.join(INPUTS_FILE))? {
            r.input_seqs = parse_inputs(&text);
        }
        if let Ok(entries) = std::fs::read_dir(dir) {
            for e in entries.flatten() {
                let Some(key) = e.file_name().to_str().map(str::to_string) else { continue };
                if key == "journal" || key.starts_with('.') {
                    continue;
                }
                r.snapshots.insert(key, e.path());
            }
        }
        Ok(r)
    }

    /// On a restart: keeps the first `n` journal lines of `restart` (those the stage took) and
    /// drops the rest.
    pub fn keep(&mut self, restart: &Restart, n: usize) -> Result<(), StateError> {
        let Some(dir) = &self.dir else { return Ok(()) };
        let path = dir.join("journal");
        let mut text = String::new();
        for l in restart.journal.iter().take(n) {
            text.push_str(l);
            text.push('\n');
        }
        let tmp = dir.join(".journal.tmp");
        std::fs::write(&tmp, text)
            .and_then(|_| std::fs::rename(&tmp, &path))
            .map_err(StateError::io("writing", &path))?;
        self.journal =
            Some(std::fs::OpenOptions::new().append(true).open(&path).map_err(StateError::io("opening", &path))?);
        self.lines = n as u64;
        Ok(())
    }

    /// True when the store keeps what is recorded (a process under a runtime with an output
    /// directory).
    pub fn is_enabled(&self) -> bool {
        self.journal.is_some()
    }

    /// Records one journal line (no newline inside), written at the next [`StateStore::flush`]
    /// (the runtime flushes after every wake-up; a stage flushes itself before it publishes what
    /// the line records, so that a restarted instance never misses what went out).
    pub fn record(&mut self, line: &str) {
        if self.journal.is_some() {
            debug_assert!(!line.contains('\n'), "a journal line has no newline: {line:?}");
            self.buffer.push_str(line);
            self.buffer.push('\n');
        }
    }

    /// Writes the recorded lines in one write.
    pub fn flush(&mut self) -> Result<(), StateError> {
        if self.buffer.is_empty() {
            return Ok(());
        }
        if let (Some(file), Some(dir)) = (self.journal.as_mut(), &self.dir) {
            file.write_all(self.buffer.as_bytes()).map_err(StateError::io("writing", &dir.join("journal")))?;
            self.lines += self.buffer.matches('\n').count() as u64;
        }
        self.buffer.clear();
        Ok(())
    }

    /// Overwrites where the inputs stand (`(service, publisher, first sequence number not
    /// received or kept)`), in place with one write: the runtime calls it after every wake-up in
    /// which that changed, so that a restarted instance knows where its killed predecessor
    /// stopped.
    pub fn save_inputs(&mut self, seqs: &[(String, u128, u64)]) -> Result<(), StateError> {
        use std::os::unix::fs::FileExt as _;
        let (Some(file), Some(dir)) = (self.inputs.as_ref(), &self.dir) else { return Ok(()) };
        let mut text = String::with_capacity(64 * seqs.len() + 4);
        for (service, publisher, seq) in seqs {
            text.push_str(&format!("{service}\t{publisher:x}\t{seq}\n"));
        }
        text.push_str("end\n");
        file.write_all_at(text.as_bytes(), 0).map_err(StateError::io("writing", &dir.join(INPUTS_FILE)))
    }

    /// Journal lines written so far (kept from a predecessor included).
    pub fn journal_lines(&self) -> u64 {
        self.lines
    }

    /// Replaces the snapshot `key` (letters, digits, `_`, `-`, `.`; not `journal`) with `bytes`:
    /// a temporary file renamed over it, so a kill leaves the old or the new one, whole.
    pub fn snapshot(&self, key: &str, bytes: &[u8]) -> Result<(), StateError> {
        let Some(dir) = &self.dir else { return Ok(()) };
        let path = dir.join(key);
        if key == "journal"
            || key.is_empty()
            || key.starts_with('.')
            || !key.chars().all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c))
        {
            return Err(StateError::Malformed { path, what: format!("`{key}` is not a snapshot key") });
        }
        let tmp = dir.join(format!(".{key}.tmp"));
        std::fs::write(&tmp, bytes).and_then(|_| std::fs::rename(&tmp, &path)).map_err(StateError::io("writing", &path))
    }

    /// The path of snapshot `key` (for a stage whose snapshot is written by a library that
    /// writes files itself; write to a temporary file and rename, as [`StateStore::snapshot`]).
    pub fn snapshot_path(&self, key: &str) -> Option<PathBuf> {
        self.dir.as_ref().map(|d| d.join(key))
    }
}

/// The runtime's own file in a process's state directory: where its inputs stand
/// (`<service>\t<publisher, hex>\t<first seq not received or kept>` lines, then `end`; a dot
/// file, so not a snapshot).
const INPUTS_FILE: &str = ".inputs";

/// The lines of [`INPUTS_FILE`] up to `end` (none without it: a file cut short says nothing).
fn parse_inputs(text: &str) -> Vec<(String, u128, u64)> {
    let mut out = vec![];
    for line in text.lines() {
        if line == "end" {
            return out;
        }
        let mut f = line.split('\t');
        let (Some(service), Some(publisher), Some(seq), None) = (f.next(), f.next(), f.next(), f.next()) else {
            return vec![];
        };
        let (Ok(publisher), Ok(seq)) = (u128::from_str_radix(publisher, 16), seq.parse()) else { return vec![] };
        out.push((service.to_string(), publisher, seq));
    }
    vec![]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn where_the_inputs_stand_comes_back_to_a_restart_and_a_shorter_save_overwrites_a_longer() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (mut st, _) = StateStore::open(dir.path(), "map", false).expect("open");
        let long =
            vec![("pipeline/sensors/cloud".to_string(), 0xabc_u128, 41), ("pipeline/slam/pose".to_string(), 7, 9)];
        st.save_inputs(&long).expect("save");
        st.save_inputs(&long[..1]).expect("save");
        drop(st);
        let (mut st, r) = StateStore::open(dir.path(), "map", true).expect("reopen");
        assert_eq!(r.expect("a restart").input_seqs, long[..1].to_vec());
        // A restarted instance that has not saved yet leaves its predecessor's for the next one.
        drop(st.journal.take());
        let (_, r) = StateStore::open(dir.path(), "map", true).expect("reopen");
        assert_eq!(r.expect("a restart").input_seqs, long[..1].to_vec());
        // A file without its end marker (cut short) says nothing.
        assert!(parse_inputs("pipeline/sensors/cloud\tabc\t41\n").is_empty());
        assert!(parse_inputs("pipeline/sensors/cloud\tzz\t41\nend\n").is_empty());
    }

    #[test]
    fn a_store_keeps_the_journal_and_snapshots_for_a_restart_and_a_first_instance_starts_empty() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (mut st, restored) = StateStore::open(dir.path(), "slam", false).expect("open");
        assert!(restored.is_none());
        st.record("a 1");
        st.record("b 2");
        st.flush().expect("flush");
        st.snapshot("map.bt", b"occupancy").expect("snapshot");
        assert!(st.snapshot("journal", b"x").is_err() && st.snapshot("../x", b"x").is_err());
        drop(st);
        // A kill in the middle of the next line.
        let journal = StateStore::dir_of(dir.path(), "slam").join("journal");
        let mut f = std::fs::OpenOptions::new().append(true).open(&journal).expect("journal");
        f.write_all(b"c 3 (cut").expect("write");
        drop(f);
        let (mut st, r) = StateStore::open(dir.path(), "slam", true).expect("reopen");
        let r = r.expect("a restart gets the state");
        assert_eq!((r.journal.clone(), r.cut_lines), (vec!["a 1".to_string(), "b 2".to_string()], 1));
        assert_eq!(r.read_snapshot("map.bt").expect("read").as_deref(), Some(&b"occupancy"[..]));
        // The stage took the first line only: the journal goes on after it.
        st.keep(&r, 1).expect("keep");
        st.record("d 4");
        st.flush().expect("flush");
        assert_eq!(std::fs::read_to_string(&journal).expect("journal"), "a 1\nd 4\n");
        drop(st);
        let (_, r) = StateStore::open(dir.path(), "slam", false).expect("a new run");
        assert!(r.is_none());
        assert_eq!(std::fs::read_to_string(&journal).expect("journal"), "", "a first instance starts empty");
        assert!(!StateStore::dir_of(dir.path(), "slam").join("map.bt").exists());
    }
}

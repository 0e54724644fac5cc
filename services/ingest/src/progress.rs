//! Where a restarted ingest resumes: the process records, before it publishes each item, how many
//! items it has taken from its source (plus its counters) in `<out>/state/<process>.progress`. A
//! restarted instance (the supervisor sets `SLAM_PIPELINE_RESTARTS` > 0) reads it, takes that many
//! items from the (deterministic) source without publishing them, and goes on with the next one:
//! downstream sees the stream continue with newer stamps instead of the mission replayed from the
//! start. Recording before publishing makes the delivery at most once: a kill between the record
//! and the send loses that one item, it never duplicates one.
//!
//! The record is one fixed-size text line overwritten in place with a single `pwrite`, which a
//! SIGKILL cannot tear, so no temporary file and rename are needed per item.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// Size of the record, bytes (the line is padded with spaces).
const RECORD_LEN: usize = 192;

/// What a killed instance had done.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Progress {
    /// Items taken from the source (published, skipped as empty, or lost to the kill).
    pub items: u64,
    /// Messages published per service: odometry, stereo, buoy ranges, depth, cloud, heading.
    pub counts: [u64; 6],
    /// Empty clouds skipped.
    pub empty_clouds: u64,
    /// Stamp of the first and of the last item taken, ns.
    pub first_last_stamp: Option<(u64, u64)>,
}

/// Why a progress record cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ProgressError {
    /// The file cannot be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// The record is not one this version writes.
    #[error("{path}: not a progress record: `{line}`")]
    Malformed {
        /// The file.
        path: PathBuf,
        /// The line read.
        line: String,
    },
}

impl Progress {
    /// The record's text (without padding).
    pub fn encode(&self) -> String {
        let (a, b) = self.first_last_stamp.unwrap_or((0, 0));
        let c = self.counts;
        format!(
            "v1 items={} counts={},{},{},{},{},{} empty={} first={} last={} stamped={}",
            self.items,
            c[0],
            c[1],
            c[2],
            c[3],
            c[4],
            c[5],
            self.empty_clouds,
            a,
            b,
            u8::from(self.first_last_stamp.is_some())
        )
    }

    /// Parses a record written by [`Progress::encode`] (trailing padding allowed).
    pub fn decode(text: &str) -> Option<Self> {
        let mut fields = text.split_whitespace();
        if fields.next()? != "v1" {
            return None;
        }
        let mut value = |key: &str| fields.next()?.strip_prefix(key)?.strip_prefix('=').map(str::to_string);
        let items = value("items")?.parse().ok()?;
        let counts_text = value("counts")?;
        let empty_clouds = value("empty")?.parse().ok()?;
        let first: u64 = value("first")?.parse().ok()?;
        let last: u64 = value("last")?.parse().ok()?;
        let stamped = value("stamped")? == "1";
        let counts: Vec<u64> = counts_text.split(',').map(str::parse).collect::<Result<_, _>>().ok()?;
        Some(Self {
            items,
            counts: counts.try_into().ok()?,
            empty_clouds,
            first_last_stamp: stamped.then_some((first, last)),
        })
    }
}

/// The progress file of one ingest process.
#[derive(Debug)]
pub struct ProgressFile {
    path: PathBuf,
    file: File,
}

impl ProgressFile {
    /// `<out_dir>/state/<process>.progress`.
    pub fn path(out_dir: &Path, process: &str) -> PathBuf {
        pipeline_runtime::restart::state_path(out_dir, process, "progress")
    }

    /// Reads the record a killed instance left; `Ok(None)` when there is none.
    pub fn read(path: &Path) -> Result<Option<Progress>, ProgressError> {
        let text = match std::fs::read_to_string(path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => return Err(ProgressError::Io { path: path.into(), source }),
        };
        Progress::decode(&text)
            .map(Some)
            .ok_or_else(|| ProgressError::Malformed { path: path.into(), line: text.trim_end().to_string() })
    }

    /// Opens (creating it and its directory) the file for recording.
    pub fn create(path: &Path) -> Result<Self, ProgressError> {
        let io = |source| ProgressError::Io { path: path.into(), source };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        let file = std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(path).map_err(io)?;
        Ok(Self { path: path.into(), file })
    }

    /// Overwrites the record with `p` (one `pwrite` of the fixed-size line).
    pub fn record(&self, p: &Progress) -> Result<(), ProgressError> {
        let mut line = p.encode();
        line.truncate(RECORD_LEN - 1);
        let mut buf = format!("{line:<width$}", width = RECORD_LEN - 1);
        buf.push('\n');
        self.file
            .write_all_at(buf.as_bytes(), 0)
            .map_err(|source| ProgressError::Io { path: self.path.clone(), source })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_record_reads_back_as_written_and_rewrites_in_place() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = ProgressFile::path(dir.path(), "ingest");
        assert!(ProgressFile::read(&path).expect("no file is no progress").is_none());
        let f = ProgressFile::create(&path).expect("create");
        let big = Progress {
            items: 123_456_789,
            counts: [1, 2, 3, 4, 5, u64::MAX],
            empty_clouds: 7,
            first_last_stamp: Some((10, u64::MAX)),
        };
        f.record(&big).expect("record");
        let small = Progress { items: 3, ..Default::default() };
        f.record(&small).expect("record");
        assert_eq!(ProgressFile::read(&path).expect("read"), Some(small), "a shorter record replaces a longer one");
        f.record(&big).expect("record");
        assert_eq!(ProgressFile::read(&path).expect("read"), Some(big));
        assert_eq!(std::fs::metadata(&path).expect("metadata").len(), RECORD_LEN as u64);
    }

    #[test]
    fn a_malformed_record_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("x.progress");
        std::fs::write(&path, "items=3\n").expect("write");
        let e = ProgressFile::read(&path).unwrap_err().to_string();
        assert!(e.contains("x.progress") && e.contains("not a progress record"), "{e}");
    }
}

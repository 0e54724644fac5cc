//! Writing a bag beside a live process:
//! - [`BagSink`]: a [`BagWriter`] on a thread of its own, so that compression and disk writes
//!   never hold up the process that publishes. What waits for the thread is bounded in bytes; a
//!   message refused because the writer is that far behind is counted per topic, never lost
//!   silently.
//! - [`prepare_bag_dir`]: where a new bag goes when one is there already (a restarted instance
//!   keeps the killed one's bag; a new run replaces an earlier run's, as it replaces every other
//!   output in the same directory).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, Sender, channel};
use std::thread::JoinHandle;

use crate::bag::{BagError, BagWriter};

/// What [`prepare_bag_dir`] found and did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NewBag {
    /// Nothing was there.
    Fresh,
    /// A first instance found an earlier run's bag (and its `.part<N>`s) and removed them.
    ReplacedEarlierRun {
        /// The directories removed.
        removed: Vec<PathBuf>,
    },
    /// A restarted instance found the killed instance's bag and kept it under another name.
    KeptKilledInstance {
        /// Where the killed instance's bag is now (`<dir>.part<N>`).
        part: PathBuf,
    },
}

/// True when `dir` holds nothing but what a bag writer leaves (`metadata.yaml`, `.mcap` files).
fn holds_only_a_bag(dir: &Path) -> Result<bool, BagError> {
    let io = |source| BagError::Io { path: dir.to_path_buf(), source };
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let entry = entry.map_err(io)?;
        let name = entry.file_name();
        let name = name.to_string_lossy();
        let is_file = entry.file_type().map_err(io)?.is_file();
        if !is_file || !(name == "metadata.yaml" || name.ends_with(".mcap")) {
            return Ok(false);
        }
    }
    Ok(true)
}

/// The `<dir>.part<N>` directories beside `dir`, in order of N.
fn parts_of(dir: &Path) -> Result<Vec<PathBuf>, BagError> {
    let (Some(parent), Some(name)) = (dir.parent(), dir.file_name().map(|n| n.to_string_lossy().into_owned())) else {
        return Ok(vec![]);
    };
    let parent = if parent.as_os_str().is_empty() { Path::new(".") } else { parent };
    let prefix = format!("{name}.part");
    let mut parts = vec![];
    let entries = match std::fs::read_dir(parent) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(vec![]),
        Err(source) => return Err(BagError::Io { path: parent.to_path_buf(), source }),
    };
    for entry in entries.flatten() {
        let n = entry.file_name().to_string_lossy().into_owned();
        if let Some(k) = n.strip_prefix(&prefix).and_then(|k| k.parse::<u32>().ok()) {
            parts.push((k, entry.path()));
        }
    }
    parts.sort();
    Ok(parts.into_iter().map(|(_, p)| p).collect())
}

/// Makes room for a new bag at `dir`.
///
/// - A restarted instance (`restart`) keeps the killed instance's bag as `<dir>.part<N>` (the
///   first free N): its messages are the run's too.
/// - A first instance removes an earlier run's bag at `dir` and its `<dir>.part<N>`s, as a run
///   overwrites every other output in its directory. Only directories that hold nothing but
///   `metadata.yaml` and `.mcap` files are removed; anything else there is an error that names
///   it, and nothing is removed.
pub fn prepare_bag_dir(dir: &Path, restart: bool) -> Result<NewBag, BagError> {
    if restart {
        if !dir.exists() {
            return Ok(NewBag::Fresh);
        }
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "bag".into());
        let part = (1..)
            .map(|k| dir.with_file_name(format!("{name}.part{k}")))
            .find(|p| !p.exists())
            .expect("some part number is free");
        std::fs::rename(dir, &part).map_err(|source| BagError::Io { path: dir.to_path_buf(), source })?;
        return Ok(NewBag::KeptKilledInstance { part });
    }
    let mut old = parts_of(dir)?;
    if dir.exists() {
        old.insert(0, dir.to_path_buf());
    }
    if old.is_empty() {
        return Ok(NewBag::Fresh);
    }
    for d in &old {
        if !d.is_dir() || !holds_only_a_bag(d)? {
            return Err(BagError::NotABag {
                path: d.clone(),
                why: "is in the way of the new bag and holds more than a bag (metadata.yaml, .mcap files): \
                      move it or choose another directory"
                    .into(),
            });
        }
    }
    for d in &old {
        std::fs::remove_dir_all(d).map_err(|source| BagError::Io { path: d.clone(), source })?;
    }
    Ok(NewBag::ReplacedEarlierRun { removed: old })
}

/// A bag written by a [`BagSink`]: what is in it and what is not.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct BagReport {
    /// The bag directory.
    pub dir: PathBuf,
    /// Messages written per topic.
    pub messages: BTreeMap<String, u64>,
    /// Messages not written per topic because they were refused (the writer was
    /// `max_queued_bytes` behind, had stopped, or the topic was not declared).
    pub refused: BTreeMap<String, u64>,
    /// Messages the writer failed to write (the first failure is `first_error`).
    pub write_errors: u64,
    /// The first write failure.
    pub first_error: Option<String>,
}

struct Job {
    topic: Arc<str>,
    log_time_ns: u64,
    data: Vec<u8>,
}

/// Why [`BagSink::write`] did not queue a message (the caller counts it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum NotQueued {
    /// The writer is `max_queued_bytes` behind.
    #[error("the bag writer is behind (its queue is full)")]
    WriterBehind,
    /// The writer thread has stopped.
    #[error("the bag writer thread has stopped")]
    Stopped,
    /// The topic was not declared in the bag before the writer started.
    #[error("the topic was not declared in the bag")]
    Undeclared,
}

/// A [`BagWriter`] on a thread of its own (see the module docs).
pub struct BagSink {
    dir: PathBuf,
    tx: Option<Sender<Job>>,
    queued_bytes: Arc<AtomicUsize>,
    max_queued_bytes: usize,
    topics: BTreeMap<String, Arc<str>>,
    refused: BTreeMap<String, u64>,
    thread: Option<JoinHandle<(BagWriter, u64, Option<String>)>>,
}

impl BagSink {
    /// Starts the thread that writes into `bag` (its topics declared already); at most
    /// `max_queued_bytes` of messages wait for it.
    pub fn spawn(bag: BagWriter, max_queued_bytes: usize) -> Result<Self, BagError> {
        let dir = bag.dir().to_path_buf();
        let topics = bag.counts().into_keys().map(|t| (t.clone(), Arc::from(t.as_str()))).collect();
        let (tx, rx) = channel();
        let queued_bytes = Arc::new(AtomicUsize::new(0));
        let q = queued_bytes.clone();
        let thread = std::thread::Builder::new()
            .name("bag-writer".into())
            .spawn(move || write_all(rx, bag, q))
            .map_err(|source| BagError::Io { path: dir.clone(), source })?;
        Ok(Self {
            dir,
            tx: Some(tx),
            queued_bytes,
            max_queued_bytes,
            topics,
            refused: BTreeMap::new(),
            thread: Some(thread),
        })
    }

    /// The bag directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Queues one encapsulated-CDR message on a declared topic, received at `log_time_ns`.
    /// A message not queued is counted in the report, per topic.
    pub fn write(&mut self, topic: &str, log_time_ns: u64, data: Vec<u8>) -> Result<(), NotQueued> {
        let refuse = |s: &mut Self, why| {
            *s.refused.entry(topic.to_string()).or_default() += 1;
            Err(why)
        };
        let Some(name) = self.topics.get(topic).cloned() else {
            return refuse(self, NotQueued::Undeclared);
        };
        let len = data.len();
        if self.queued_bytes.load(Ordering::Acquire) + len > self.max_queued_bytes {
            return refuse(self, NotQueued::WriterBehind);
        }
        let Some(tx) = &self.tx else { return refuse(self, NotQueued::Stopped) };
        self.queued_bytes.fetch_add(len, Ordering::AcqRel);
        if tx.send(Job { topic: name, log_time_ns, data }).is_err() {
            self.queued_bytes.fetch_sub(len, Ordering::AcqRel);
            return refuse(self, NotQueued::Stopped);
        }
        Ok(())
    }

    /// Bytes waiting for the writer now.
    pub fn queued_bytes(&self) -> usize {
        self.queued_bytes.load(Ordering::Acquire)
    }

    /// Writes what is queued, ends the bag (`metadata.yaml`) and reports.
    pub fn finish(mut self) -> Result<BagReport, BagError> {
        self.tx = None;
        let thread = self.thread.take().expect("finish runs once");
        let (mut bag, write_errors, first_error) = thread
            .join()
            .map_err(|_| BagError::NotABag { path: self.dir.clone(), why: "the bag writer thread panicked".into() })?;
        bag.finish()?;
        Ok(BagReport {
            dir: self.dir.clone(),
            messages: bag.counts(),
            refused: std::mem::take(&mut self.refused),
            write_errors,
            first_error,
        })
    }
}

impl Drop for BagSink {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take()
            && let Ok((mut bag, _, _)) = t.join()
        {
            let _ = bag.finish();
        }
    }
}

fn write_all(rx: Receiver<Job>, mut bag: BagWriter, queued: Arc<AtomicUsize>) -> (BagWriter, u64, Option<String>) {
    let (mut errors, mut first) = (0, None);
    while let Ok(job) = rx.recv() {
        let r = bag.write(&job.topic, job.log_time_ns, &job.data);
        queued.fetch_sub(job.data.len(), Ordering::AcqRel);
        if let Err(e) = r {
            errors += 1;
            first.get_or_insert_with(|| e.to_string());
        }
    }
    (bag, errors, first)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::BagQos;

    fn tmp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("bag_sink_{}_{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn bag_at(dir: &Path) {
        let mut w = BagWriter::create(dir).unwrap();
        w.add_topic("/a", "tf2_msgs/msg/TFMessage", BagQos { reliable: true, transient_local: false, depth: 10 })
            .unwrap();
        w.finish().unwrap();
    }

    #[test]
    fn a_new_run_replaces_an_earlier_runs_bag_and_parts_a_restart_keeps_the_killed_ones() {
        let root = tmp("prepare");
        let dir = root.join("ros2_bag");
        assert_eq!(prepare_bag_dir(&dir, false).unwrap(), NewBag::Fresh);
        bag_at(&dir);
        assert_eq!(
            prepare_bag_dir(&dir, true).unwrap(),
            NewBag::KeptKilledInstance { part: root.join("ros2_bag.part1") }
        );
        bag_at(&dir);
        assert_eq!(
            prepare_bag_dir(&dir, true).unwrap(),
            NewBag::KeptKilledInstance { part: root.join("ros2_bag.part2") }
        );
        bag_at(&dir);
        match prepare_bag_dir(&dir, false).unwrap() {
            NewBag::ReplacedEarlierRun { removed } => assert_eq!(removed.len(), 3, "{removed:?}"),
            other => panic!("{other:?}"),
        }
        assert!(!dir.exists() && !root.join("ros2_bag.part1").exists() && !root.join("ros2_bag.part2").exists());
        // Something that is not a bag in the way: an error naming it, nothing removed.
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("notes.txt"), "mine").unwrap();
        let e = prepare_bag_dir(&dir, false).unwrap_err().to_string();
        assert!(e.contains("ros2_bag") && e.contains("more than a bag"), "{e}");
        assert!(dir.join("notes.txt").exists());
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn the_sink_writes_on_its_thread_and_counts_what_it_refuses() {
        let root = tmp("sink");
        let dir = root.join("b");
        let mut w = BagWriter::create_with(&dir, crate::BagCompression::Lz4).unwrap();
        w.add_topic("/a", "tf2_msgs/msg/TFMessage", BagQos { reliable: true, transient_local: false, depth: 10 })
            .unwrap();
        let mut sink = BagSink::spawn(w, 1000).unwrap();
        let msg = crate::cdr::encode(&crate::msgs::TFMessage::default()).unwrap();
        for i in 0..50 {
            sink.write("/a", 1_000 + i, msg.clone()).unwrap();
        }
        // Larger than the whole queue: refused, counted.
        assert_eq!(sink.write("/a", 2_000, vec![0; 2000]), Err(NotQueued::WriterBehind));
        assert_eq!(sink.write("/b", 2_000, msg.clone()), Err(NotQueued::Undeclared));
        let r = sink.finish().unwrap();
        assert_eq!(r.messages["/a"], 50);
        assert_eq!(r.refused["/a"], 1);
        assert_eq!(r.refused["/b"], 1);
        assert_eq!(r.write_errors, 0);
        let mut read = crate::BagReader::open(&dir).unwrap();
        let mut n = 0;
        while let Some(m) = read.next_message().unwrap() {
            assert_eq!(&*m.topic, "/a");
            n += 1;
        }
        assert_eq!(n, 50);
        let _ = std::fs::remove_dir_all(&root);
    }
}

//! rosbag2 bags in MCAP storage (the default since ROS 2 Iron): reading one for replay, writing
//! one from a run.
//!
//! **Reading** ([`BagReader`]): a bag directory (`metadata.yaml` and the `.mcap` files it lists,
//! in order) or one `.mcap` file. Each file is read record by record (never whole into memory),
//! so what is wrong is found where it is and named with its byte offset:
//! - a chunk that does not decompress or parse, or whose CRC does not match, is skipped (its
//!   messages are lost) and the reading goes on at the next record ([`BagWarts::corrupt_chunks`]);
//! - a file cut short ends where the cut is ([`BagWarts::truncated_files`]);
//! - a message on a channel never declared, or not CDR-encoded, is skipped and counted.
//!
//! **Writing** ([`BagWriter`]): a bag directory with one chunked `.mcap` file (zstd at level 1 by
//! default, as `ros2 bag record`'s MCAP writer; [`BagCompression`]; schemas as
//! `ros2msg` from [`crate::schema`], messages `cdr`, the `ros2` profile, each channel's
//! `offered_qos_profiles`) and its `metadata.yaml`, which `ros2 bag info` / `ros2 bag play`
//! and Python `rosbags` read.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::fs::File;
use std::io::{BufReader, BufWriter, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use mcap::records::{Record, op};

/// Why a bag cannot be read or written at all (a damaged part of a readable bag is a wart,
/// [`BagWarts`], not an error).
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    /// A file cannot be opened, read or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// Not a bag this reader can read (named with why).
    #[error("{}: {why}", path.display())]
    NotABag {
        /// The path given.
        path: PathBuf,
        /// Why.
        why: String,
    },
    /// Writing MCAP failed.
    #[error("{}: {source}", path.display())]
    Mcap {
        /// The file.
        path: PathBuf,
        /// The MCAP writer's error.
        #[source]
        source: mcap::McapError,
    },
    /// A type this crate has no definition of, to write.
    #[error("no ROS 2 definition of `{0}` to write its schema")]
    UnknownType(String),
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> BagError + use<> {
    let path = path.to_path_buf();
    move |source| BagError::Io { path, source }
}

/// One message of a bag.
#[derive(Debug, Clone)]
pub struct BagMessage {
    /// The ROS topic (`/scan`).
    pub topic: Arc<str>,
    /// Its ROS 2 type (`sensor_msgs/msg/LaserScan`), from the channel's schema ("" without one).
    pub type_name: Arc<str>,
    /// When the recorder received it, ns (the bag's clock).
    pub log_time_ns: u64,
    /// Encapsulated CDR.
    pub data: Vec<u8>,
    /// The file it is in.
    pub file: Arc<Path>,
    /// Byte offset in the file of the record holding it (the chunk, for a chunked message).
    pub offset: u64,
}

/// What was wrong in the bag so far, by kind.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct BagWarts {
    /// Chunks skipped: they did not decompress or parse, or their CRC did not match.
    pub corrupt_chunks: u64,
    /// Files that end inside a record (the rest of the file is lost).
    pub truncated_files: u64,
    /// Messages on a channel that was never declared.
    pub unknown_channel_messages: u64,
    /// Messages whose channel is not CDR-encoded.
    pub not_cdr_messages: u64,
}

#[derive(Debug, Clone)]
struct ChannelInfo {
    topic: Arc<str>,
    type_name: Arc<str>,
    cdr: bool,
}

/// Reads a rosbag2 MCAP bag message by message, in file order (see the module docs).
pub struct BagReader {
    files: Vec<PathBuf>,
    next_file: usize,
    current: Option<FileReader>,
    queue: VecDeque<BagMessage>,
    schemas: HashMap<u16, (String, String)>,
    channels: HashMap<u16, ChannelInfo>,
    warts: BagWarts,
    /// Problems met, one line each (offset and what), for the log.
    problems: Vec<String>,
    bytes_total: u64,
    bytes_done: u64,
}

struct FileReader {
    path: Arc<Path>,
    r: BufReader<File>,
    offset: u64,
    len: u64,
}

/// The storage files of a bag: the `.mcap` files listed in a directory's `metadata.yaml`, or
/// the one file given.
pub fn bag_files(path: &Path) -> Result<Vec<PathBuf>, BagError> {
    let not = |why: String| BagError::NotABag { path: path.to_path_buf(), why };
    if path.is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    if !path.is_dir() {
        return Err(not("no such file or directory".into()));
    }
    let meta = path.join("metadata.yaml");
    if !meta.is_file() {
        let mut found: Vec<PathBuf> = std::fs::read_dir(path)
            .map_err(io(path))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
            .collect();
        found.sort();
        if found.is_empty() {
            return Err(not("a directory without metadata.yaml or .mcap files".into()));
        }
        return Ok(found);
    }
    let text = std::fs::read_to_string(&meta).map_err(io(&meta))?;
    let v: serde_yaml::Value =
        serde_yaml::from_str(&text).map_err(|e| not(format!("metadata.yaml is not YAML: {e}")))?;
    let info = &v["rosbag2_bagfile_information"];
    let storage = info["storage_identifier"].as_str().unwrap_or("");
    if storage != "mcap" {
        return Err(not(format!(
            "storage `{storage}`: only MCAP bags are read (convert with `ros2 bag convert` to storage_id mcap)"
        )));
    }
    if info["compression_mode"].as_str().is_some_and(|m| m.eq_ignore_ascii_case("file")) {
        return Err(not("a file-compressed bag (compression_mode FILE): decompress it first".into()));
    }
    let files: Vec<PathBuf> = info["relative_file_paths"]
        .as_sequence()
        .map(|s| s.iter().filter_map(|f| f.as_str()).map(|f| path.join(f)).collect())
        .unwrap_or_default();
    if files.is_empty() {
        return Err(not("metadata.yaml lists no relative_file_paths".into()));
    }
    Ok(files)
}

impl BagReader {
    /// Opens a bag directory or an `.mcap` file.
    pub fn open(path: &Path) -> Result<Self, BagError> {
        let files = bag_files(path)?;
        let mut bytes_total = 0;
        for f in &files {
            bytes_total += std::fs::metadata(f).map_err(io(f))?.len();
        }
        let mut me = Self {
            files,
            next_file: 0,
            current: None,
            queue: VecDeque::new(),
            schemas: HashMap::new(),
            channels: HashMap::new(),
            warts: BagWarts::default(),
            problems: vec![],
            bytes_total,
            bytes_done: 0,
        };
        me.open_next()?;
        Ok(me)
    }

    /// The storage files, in reading order.
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }

    /// What was wrong so far.
    pub fn warts(&self) -> &BagWarts {
        &self.warts
    }

    /// Takes the problems met since the last call, one line each (for the log).
    pub fn take_problems(&mut self) -> Vec<String> {
        std::mem::take(&mut self.problems)
    }

    /// Fraction of the bag's bytes read.
    pub fn progress(&self) -> f64 {
        let cur = self.current.as_ref().map_or(0, |c| c.offset);
        if self.bytes_total == 0 { 1.0 } else { ((self.bytes_done + cur) as f64 / self.bytes_total as f64).min(1.0) }
    }

    /// The topics declared so far, with their types.
    pub fn topics(&self) -> BTreeMap<String, String> {
        self.channels.values().map(|c| (c.topic.to_string(), c.type_name.to_string())).collect()
    }

    fn open_next(&mut self) -> Result<bool, BagError> {
        if let Some(c) = self.current.take() {
            self.bytes_done += c.offset;
        }
        let Some(path) = self.files.get(self.next_file).cloned() else { return Ok(false) };
        self.next_file += 1;
        let file = File::open(&path).map_err(io(&path))?;
        let len = file.metadata().map_err(io(&path))?.len();
        let mut r = BufReader::with_capacity(1 << 20, file);
        let mut magic = [0u8; 8];
        r.read_exact(&mut magic)
            .map_err(|e| BagError::NotABag { path: path.clone(), why: format!("cannot read the MCAP magic: {e}") })?;
        if magic != mcap::MAGIC {
            return Err(BagError::NotABag { path, why: "not an MCAP file (no MCAP magic at its start)".into() });
        }
        // Each file of a split bag declares its schemas and channels anew. Those of the summary
        // section come first: a channel declared in a chunk that turns out corrupt is still known.
        self.schemas.clear();
        self.channels.clear();
        if let Ok(records) = summary_records(&path, len) {
            for (op, body) in records {
                if let Ok(rec) = mcap::read::parse_record(op, &body) {
                    let rec = rec.into_owned();
                    self.take_declaration(rec);
                }
            }
        }
        self.current = Some(FileReader { path: path.into(), r, offset: 8, len });
        Ok(true)
    }

    /// The next message, `None` at the end of the bag. Damaged parts are skipped and counted;
    /// only a file that cannot be opened is an error.
    pub fn next_message(&mut self) -> Result<Option<BagMessage>, BagError> {
        loop {
            if let Some(m) = self.queue.pop_front() {
                return Ok(Some(m));
            }
            let Some(cur) = self.current.as_mut() else { return Ok(None) };
            let at = cur.offset;
            let mut head = [0u8; 9];
            match read_full(&mut cur.r, &mut head) {
                Ok(0) => {
                    // A clean end of file without a footer: the writer stopped before it.
                    let path = cur.path.clone();
                    self.truncated(&path, at, "the file ends without a footer");
                    self.open_next()?;
                    continue;
                }
                Ok(9) => {}
                Ok(_) => {
                    let path = cur.path.clone();
                    self.truncated(&path, at, "a record header is cut short");
                    self.open_next()?;
                    continue;
                }
                Err(e) => return Err(BagError::Io { path: cur.path.to_path_buf(), source: e }),
            }
            let opcode = head[0];
            let len = u64::from_le_bytes(head[1..9].try_into().unwrap_or_default());
            let remaining = cur.len.saturating_sub(at + 9);
            if len > remaining {
                let path = cur.path.clone();
                self.truncated(&path, at, &format!("a record of {len} bytes with {remaining} left"));
                self.open_next()?;
                continue;
            }
            let mut body = vec![0u8; len as usize];
            cur.r.read_exact(&mut body).map_err(io(&cur.path))?;
            cur.offset += 9 + len;
            let path = cur.path.clone();
            match opcode {
                op::FOOTER | op::DATA_END => {
                    // The summary section repeats what was read: the file is done.
                    self.open_next()?;
                }
                op::SCHEMA | op::CHANNEL | op::MESSAGE => match mcap::read::parse_record(opcode, &body) {
                    Ok(rec) => self.take_record(rec, &path, at),
                    Err(e) => {
                        self.problems
                            .push(format!("{}@{at}: a record that does not parse ({e}): skipped", path.display()));
                    }
                },
                op::CHUNK => self.read_chunk(&body, &path, at),
                _ => {}
            }
        }
    }

    fn truncated(&mut self, path: &Path, at: u64, what: &str) {
        self.warts.truncated_files += 1;
        self.problems.push(format!("{}@{at}: truncated ({what}): the rest of this file is lost", path.display()));
    }

    fn read_chunk(&mut self, body: &[u8], path: &Arc<Path>, at: u64) {
        let bad = |me: &mut Self, why: String| {
            me.warts.corrupt_chunks += 1;
            me.problems.push(format!("{}@{at}: corrupt chunk ({why}): its messages are skipped", path.display()));
        };
        let (header, data) = match mcap::read::parse_record(op::CHUNK, body) {
            Ok(Record::Chunk { header, data }) => (header, data),
            Ok(_) => return bad(self, "not a chunk".into()),
            Err(e) => return bad(self, e.to_string()),
        };
        let raw = match decompress(&header, &data) {
            Ok(raw) => raw,
            Err(why) => return bad(self, why),
        };
        if header.uncompressed_crc != 0 {
            let crc = crc32fast::hash(&raw);
            if crc != header.uncompressed_crc {
                return bad(self, format!("CRC {crc:#010x}, the chunk says {:#010x}", header.uncompressed_crc));
            }
        }
        // All or nothing: a chunk that fails half-way gives none of its messages.
        let mut records = vec![];
        let mut i = 0usize;
        while i < raw.len() {
            let Some(head) = raw.get(i..i + 9) else { return bad(self, format!("a record header cut short at {i}")) };
            let n = u64::from_le_bytes(head[1..9].try_into().unwrap_or_default());
            let Some(body) = usize::try_from(n).ok().and_then(|n| raw.get(i + 9..(i + 9).checked_add(n)?)) else {
                return bad(self, format!("a record of {n} bytes at {i} overruns the chunk's {} bytes", raw.len()));
            };
            if matches!(head[0], op::SCHEMA | op::CHANNEL | op::MESSAGE) {
                match mcap::read::parse_record(head[0], body) {
                    Ok(rec) => records.push(rec.into_owned()),
                    Err(e) => return bad(self, format!("record at {i}: {e}")),
                }
            }
            i += 9 + body.len();
        }
        for rec in records {
            self.take_record(rec, path, at);
        }
    }

    fn take_declaration(&mut self, rec: Record<'_>) {
        match rec {
            Record::Schema { header, data } => {
                self.schemas.insert(header.id, (header.name, String::from_utf8_lossy(&data).into_owned()));
            }
            Record::Channel(c) => {
                let type_name = self.schemas.get(&c.schema_id).map(|(n, _)| n.as_str()).unwrap_or("");
                self.channels.insert(
                    c.id,
                    ChannelInfo {
                        topic: c.topic.into(),
                        type_name: type_name.into(),
                        cdr: c.message_encoding == "cdr",
                    },
                );
            }
            _ => {}
        }
    }

    fn take_record(&mut self, rec: Record<'_>, path: &Arc<Path>, at: u64) {
        match rec {
            rec @ (Record::Schema { .. } | Record::Channel(_)) => self.take_declaration(rec),
            Record::Message { header, data } => match self.channels.get(&header.channel_id) {
                None => {
                    self.warts.unknown_channel_messages += 1;
                    if self.warts.unknown_channel_messages == 1 {
                        self.problems.push(format!(
                            "{}@{at}: a message on channel {} that was never declared: skipped",
                            path.display(),
                            header.channel_id
                        ));
                    }
                }
                Some(c) if !c.cdr => {
                    self.warts.not_cdr_messages += 1;
                    if self.warts.not_cdr_messages == 1 {
                        self.problems.push(format!(
                            "{}@{at}: `{}` is not CDR-encoded: its messages are skipped",
                            path.display(),
                            c.topic
                        ));
                    }
                }
                Some(c) => self.queue.push_back(BagMessage {
                    topic: c.topic.clone(),
                    type_name: c.type_name.clone(),
                    log_time_ns: header.log_time,
                    data: data.into_owned(),
                    file: path.clone(),
                    offset: at,
                }),
            },
            _ => {}
        }
    }
}

/// A chunk's records, decompressed (`""`, `zstd` or `lz4`, as MCAP allows), at most 1 GiB.
fn decompress(header: &mcap::records::ChunkHeader, data: &[u8]) -> Result<Vec<u8>, String> {
    const MAX: u64 = 1 << 30;
    if header.uncompressed_size > MAX {
        return Err(format!("it claims {} bytes uncompressed", header.uncompressed_size));
    }
    let size = header.uncompressed_size as usize;
    let raw = match header.compression.as_str() {
        "" => data.to_vec(),
        "zstd" => zstd::bulk::decompress(data, size).map_err(|e| format!("zstd: {e}"))?,
        "lz4" => {
            let mut out = Vec::with_capacity(size);
            lz4::Decoder::new(data).and_then(|d| d.take(MAX).read_to_end(&mut out)).map_err(|e| format!("lz4: {e}"))?;
            out
        }
        other => return Err(format!("compression `{other}` is not one MCAP defines")),
    };
    if raw.len() != size {
        return Err(format!("{} bytes uncompressed, the chunk says {size}", raw.len()));
    }
    Ok(raw)
}

/// The records of a file's summary section (`(opcode, body)`), found through its footer; an
/// error when the file has no footer (cut short) or no summary.
fn summary_records(path: &Path, len: u64) -> std::io::Result<Vec<(u8, Vec<u8>)>> {
    use std::io::{Seek, SeekFrom};
    const FOOTER: u64 = 1 + 8 + 20;
    let bad = |what: &str| std::io::Error::new(std::io::ErrorKind::InvalidData, what.to_string());
    if len < 8 + FOOTER + 8 {
        return Err(bad("too short"));
    }
    let mut f = File::open(path)?;
    f.seek(SeekFrom::Start(len - 8 - FOOTER))?;
    let mut tail = [0u8; (FOOTER + 8) as usize];
    f.read_exact(&mut tail)?;
    if tail[0] != op::FOOTER || tail[(FOOTER as usize)..] != mcap::MAGIC[..] {
        return Err(bad("no footer"));
    }
    let start = u64::from_le_bytes(tail[9..17].try_into().unwrap_or_default());
    let end = len - 8 - FOOTER;
    if start == 0 || start >= end {
        return Err(bad("no summary"));
    }
    f.seek(SeekFrom::Start(start))?;
    let mut buf = vec![0u8; (end - start) as usize];
    f.read_exact(&mut buf)?;
    let mut out = vec![];
    let mut at = 0usize;
    while at + 9 <= buf.len() {
        let n = u64::from_le_bytes(buf[at + 1..at + 9].try_into().unwrap_or_default()) as usize;
        let Some(body) = buf.get(at + 9..at + 9 + n) else { break };
        if matches!(buf[at], op::SCHEMA | op::CHANNEL) {
            out.push((buf[at], body.to_vec()));
        }
        at += 9 + n;
    }
    Ok(out)
}

fn read_full(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// QoS of a topic as rosbag2 records it (`offered_qos_profiles`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BagQos {
    /// Reliable (else best effort).
    pub reliable: bool,
    /// Transient local (else volatile).
    pub transient_local: bool,
    /// History depth.
    pub depth: u32,
}

impl BagQos {
    /// rosbag2's YAML for one offered profile.
    pub fn yaml(&self) -> String {
        format!(
            "- history: 1\n  depth: {}\n  reliability: {}\n  durability: {}\n  deadline:\n    sec: 0\n    nsec: 0\n  \
             lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n  \
             avoid_ros_namespace_conventions: false\n",
            self.depth,
            if self.reliable { 1 } else { 2 },
            if self.transient_local { 1 } else { 2 },
        )
    }
}

struct TopicCount {
    type_name: String,
    qos: BagQos,
    count: u64,
}

/// Chunk compression of a written bag. Each is one MCAP defines, read by `ros2 bag` and
/// `rosbags`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BagCompression {
    /// zstd at level 1: what `ros2 bag record -s mcap` writes by default (the MCAP library's
    /// default level): faster than zstd's own default level 3, for somewhat more bytes.
    #[default]
    Zstd,
    /// LZ4 frames: faster again than zstd level 1, for more bytes (docs/ros2.md has both
    /// measured on the main job's bag).
    Lz4,
    /// Uncompressed chunks (CRC-checked).
    None,
}

impl BagCompression {
    fn mcap(self) -> (Option<mcap::Compression>, u32) {
        match self {
            BagCompression::Zstd => (Some(mcap::Compression::Zstd), 1),
            BagCompression::Lz4 => (Some(mcap::Compression::Lz4), 0),
            BagCompression::None => (None, 0),
        }
    }
}

/// Writes a rosbag2 MCAP bag directory (see the module docs).
pub struct BagWriter {
    dir: PathBuf,
    file_name: String,
    writer: Option<mcap::Writer<BufWriter<File>>>,
    channels: HashMap<String, u16>,
    topics: BTreeMap<String, TopicCount>,
    sequence: u32,
    first_ns: Option<u64>,
    last_ns: u64,
}

impl BagWriter {
    /// Creates the bag directory `dir` (it must not exist, as with `ros2 bag record -o`) with
    /// `<dir name>_0.mcap` in it, zstd-compressed (as `ros2 bag record`).
    pub fn create(dir: &Path) -> Result<Self, BagError> {
        Self::create_with(dir, BagCompression::default())
    }

    /// [`BagWriter::create`] with the chunk compression given.
    pub fn create_with(dir: &Path, compression: BagCompression) -> Result<Self, BagError> {
        if dir.exists() {
            return Err(BagError::NotABag {
                path: dir.to_path_buf(),
                why: "exists already: a bag is written anew".into(),
            });
        }
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let stem = dir.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "bag".into());
        let file_name = format!("{stem}_0.mcap");
        let path = dir.join(&file_name);
        let file = File::create(&path).map_err(io(&path))?;
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .library("slam_pipeline ros2_interop")
            .compression(compression.mcap().0)
            .compression_level(compression.mcap().1)
            .create(BufWriter::with_capacity(1 << 20, file))
            .map_err(|source| BagError::Mcap { path: path.clone(), source })?;
        Ok(Self {
            dir: dir.to_path_buf(),
            file_name,
            writer: Some(writer),
            channels: HashMap::new(),
            topics: BTreeMap::new(),
            sequence: 0,
            first_ns: None,
            last_ns: 0,
        })
    }

    fn path(&self) -> PathBuf {
        self.dir.join(&self.file_name)
    }

    /// The bag directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Declares `topic` of ROS 2 type `type_name` (its schema from [`crate::schema`]) with the
    /// QoS it is offered with.
    pub fn add_topic(&mut self, topic: &str, type_name: &str, qos: BagQos) -> Result<(), BagError> {
        if self.channels.contains_key(topic) {
            return Ok(());
        }
        let schema = crate::schema::ros2msg_schema(type_name).ok_or_else(|| BagError::UnknownType(type_name.into()))?;
        let path = self.path();
        let w = self.writer.as_mut().ok_or_else(|| BagError::NotABag { path: path.clone(), why: "finished".into() })?;
        let mcap_err = |source| BagError::Mcap { path: path.clone(), source };
        let schema_id = w.add_schema(type_name, "ros2msg", schema.as_bytes()).map_err(mcap_err)?;
        let mut meta = BTreeMap::new();
        meta.insert("offered_qos_profiles".to_string(), qos.yaml());
        let id = w
            .add_channel(schema_id, topic, "cdr", &meta)
            .map_err(|source| BagError::Mcap { path: path.clone(), source })?;
        self.channels.insert(topic.to_string(), id);
        self.topics.insert(topic.to_string(), TopicCount { type_name: type_name.to_string(), qos, count: 0 });
        Ok(())
    }

    /// Writes one encapsulated-CDR message on a declared topic, received at `log_time_ns`.
    pub fn write(&mut self, topic: &str, log_time_ns: u64, data: &[u8]) -> Result<(), BagError> {
        let path = self.path();
        let id = *self.channels.get(topic).ok_or_else(|| BagError::NotABag {
            path: path.clone(),
            why: format!("topic `{topic}` was not declared"),
        })?;
        let w = self.writer.as_mut().ok_or_else(|| BagError::NotABag { path: path.clone(), why: "finished".into() })?;
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: self.sequence,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        w.write_to_known_channel(&header, data).map_err(|source| BagError::Mcap { path, source })?;
        if let Some(t) = self.topics.get_mut(topic) {
            t.count += 1;
        }
        self.first_ns = Some(self.first_ns.map_or(log_time_ns, |f| f.min(log_time_ns)));
        self.last_ns = self.last_ns.max(log_time_ns);
        Ok(())
    }

    /// Messages written per topic.
    pub fn counts(&self) -> BTreeMap<String, u64> {
        self.topics.iter().map(|(t, c)| (t.clone(), c.count)).collect()
    }

    /// Ends the MCAP file and writes `metadata.yaml`. Returns the bag directory.
    pub fn finish(&mut self) -> Result<PathBuf, BagError> {
        let path = self.path();
        if let Some(mut w) = self.writer.take() {
            w.finish().map_err(|source| BagError::Mcap { path: path.clone(), source })?;
        }
        let start = self.first_ns.unwrap_or(0);
        let duration = self.last_ns.saturating_sub(start);
        let total: u64 = self.topics.values().map(|t| t.count).sum();
        let mut y = String::from("rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: mcap\n");
        y.push_str(&format!("  duration:\n    nanoseconds: {duration}\n"));
        y.push_str(&format!("  starting_time:\n    nanoseconds_since_epoch: {start}\n"));
        y.push_str(&format!("  message_count: {total}\n  topics_with_message_count:\n"));
        for (topic, t) in &self.topics {
            let qos = t.qos.yaml().replace('"', "\\\"").replace('\n', "\\n");
            y.push_str(&format!(
                "    - topic_metadata:\n        name: {topic}\n        type: {}\n        serialization_format: cdr\n        \
                 offered_qos_profiles: \"{qos}\"\n        type_description_hash: \"\"\n      message_count: {}\n",
                t.type_name, t.count
            ));
        }
        y.push_str("  compression_format: \"\"\n  compression_mode: \"\"\n");
        y.push_str(&format!("  relative_file_paths:\n    - {}\n", self.file_name));
        y.push_str(&format!(
            "  files:\n    - path: {}\n      starting_time:\n        nanoseconds_since_epoch: {start}\n      duration:\n        \
             nanoseconds: {duration}\n      message_count: {total}\n",
            self.file_name
        ));
        y.push_str("  custom_data: ~\n  ros_distro: jazzy\n");
        let meta = self.dir.join("metadata.yaml");
        std::fs::write(&meta, y).map_err(io(&meta))?;
        Ok(self.dir.clone())
    }
}

impl Drop for BagWriter {
    fn drop(&mut self) {
        if self.writer.is_some() {
            let _ = self.finish();
        }
    }
}

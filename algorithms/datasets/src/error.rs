//! The error type of every reader and writer in this crate.
//!
//! Every error names the file it is about; errors in text (and in PLY headers) also name the
//! 1-based line, formatted `path:line: what is wrong`, e.g.
//! `data/Plaza2_TD.txt:17: expected 4 numbers, got 3`.

use std::io;
use std::path::PathBuf;

/// An error while reading or writing a data file.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// The file could not be opened, read, decompressed or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying I/O error.
        #[source]
        source: io::Error,
    },
    /// A line of a text file (or of a PLY header) is malformed.
    #[error("{}:{line}: {kind}", path.display())]
    Line {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with the line.
        kind: LineErrorKind,
    },
    /// The file as a whole (or a binary part of it, which has no lines) is malformed.
    #[error("{}: {kind}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong with the file.
        kind: FileErrorKind,
    },
    /// A PNG file could not be decoded.
    #[error("{}: cannot decode PNG: {source}", path.display())]
    PngDecode {
        /// The file.
        path: PathBuf,
        /// The decoder's error.
        #[source]
        source: png::DecodingError,
    },
    /// A PNG file could not be encoded.
    #[error("{}: cannot encode PNG: {source}", path.display())]
    PngEncode {
        /// The file.
        path: PathBuf,
        /// The encoder's error.
        #[source]
        source: png::EncodingError,
    },
}

impl DatasetError {
    /// The 1-based line number, for errors located on a line.
    pub fn line(&self) -> Option<usize> {
        match self {
            DatasetError::Line { line, .. } => Some(*line),
            _ => None,
        }
    }

    /// The line error kind, for errors located on a line.
    pub fn line_kind(&self) -> Option<&LineErrorKind> {
        match self {
            DatasetError::Line { kind, .. } => Some(kind),
            _ => None,
        }
    }

    /// The file error kind, for errors about a whole file or its binary content.
    pub fn file_kind(&self) -> Option<&FileErrorKind> {
        match self {
            DatasetError::File { kind, .. } => Some(kind),
            _ => None,
        }
    }
}

/// What is wrong with one line of a text file. Columns are 1-based.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LineErrorKind {
    /// The line is not valid UTF-8.
    #[error("line is not valid UTF-8")]
    NotUtf8,
    /// A record type the format does not have.
    #[error("unknown record `{text}`")]
    UnknownRecord {
        /// The line's first field.
        text: String,
    },
    /// The line has the wrong number of whitespace-separated fields.
    #[error("expected {expected} numbers, got {got}")]
    ColumnCount {
        /// Fields the format requires.
        expected: usize,
        /// Fields found.
        got: usize,
    },
    /// A field is not a number.
    #[error("column {column}: `{text}` is not a number")]
    NotANumber {
        /// 1-based column.
        column: usize,
        /// The field.
        text: String,
    },
    /// A field is NaN or infinite.
    #[error("column {column}: `{text}` is not a finite number")]
    NotFinite {
        /// 1-based column.
        column: usize,
        /// The field.
        text: String,
    },
    /// A field that holds an id is not a non-negative integer in range.
    #[error("column {column}: `{text}` is not a valid non-negative integer id")]
    NotAnId {
        /// 1-based column.
        column: usize,
        /// The field.
        text: String,
    },
    /// A range names a beacon that is not in the beacon list.
    #[error("beacon id {beacon_id} is not listed in {}", beacon_file.display())]
    UnknownBeacon {
        /// The beacon id.
        beacon_id: u32,
        /// The beacon list file.
        beacon_file: PathBuf,
    },
    /// A beacon id appears twice in the beacon list.
    #[error("beacon id {beacon_id} is listed twice (first on line {first_line})")]
    DuplicateBeacon {
        /// The beacon id.
        beacon_id: u32,
        /// The line of its first entry.
        first_line: usize,
    },
    /// A frame id appears twice in a pose list.
    #[error("frame id {frame_id} appears twice (first on line {first_line})")]
    DuplicateFrame {
        /// The frame id.
        frame_id: u32,
        /// The line of its first entry.
        first_line: usize,
    },
    /// A 4×4 homogeneous transform's bottom row is not (0, 0, 0, 1).
    #[error("bottom row of the 4x4 transform is {bottom_row:?}, expected [0, 0, 0, 1]")]
    NotHomogeneous {
        /// The bottom row found.
        bottom_row: [f64; 4],
    },
    /// A file that holds exactly one data line has more.
    #[error("unexpected extra data line (the file holds exactly one)")]
    ExtraDataLine,
    /// An OctoMap `NODE` line does not have six numbers after the keyword.
    #[error("NODE line: expected 6 numbers (x y z roll pitch yaw), got {got}")]
    NodeColumnCount {
        /// Numbers found after `NODE`.
        got: usize,
    },
    /// The first line of a PLY file is not `ply`.
    #[error("not a PLY file (first line must be `ply`)")]
    PlyMagic,
    /// The PLY `format` line is not one of the supported formats.
    #[error("unsupported PLY format line `{text}` (expected ascii, binary_little_endian or binary_big_endian 1.0)")]
    PlyFormat {
        /// The line.
        text: String,
    },
    /// A PLY header line could not be understood.
    #[error("malformed PLY header line `{text}`")]
    PlyHeaderLine {
        /// The line.
        text: String,
    },
    /// A PLY property has an unknown scalar type.
    #[error("unknown PLY property type `{type_name}`")]
    PlyUnknownType {
        /// The type name.
        type_name: String,
    },
    /// A vertex coordinate property is a list or has an integer type.
    #[error("vertex property `{property}` has type `{type_name}`, expected float, float32, double or float64")]
    PlyCoordinateType {
        /// x, y or z.
        property: String,
        /// The declared type.
        type_name: String,
    },
    /// The PLY header declares the same property twice in one element.
    #[error("property `{property}` is declared twice in element `{element}`")]
    PlyDuplicateProperty {
        /// The element.
        element: String,
        /// The property.
        property: String,
    },
    /// The PLY header has no `element vertex` (reported at `end_header`).
    #[error("PLY header declares no `element vertex`")]
    PlyNoVertexElement,
    /// The PLY vertex element lacks x, y or z (reported at `end_header`).
    #[error("PLY element vertex has no property `{property}`")]
    PlyMissingCoordinate {
        /// x, y or z.
        property: String,
    },
    /// An ASCII PLY data line does not match the element's properties.
    #[error("element `{element}`: expected {expected} values, got {got}")]
    PlyValueCount {
        /// The element.
        element: String,
        /// Values required (for list properties: as far as the line could be read).
        expected: usize,
        /// Values found.
        got: usize,
    },
}

/// What is wrong with a file as a whole, or with a binary part of it (which has no lines).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FileErrorKind {
    /// The file has no data lines where at least one is required.
    #[error("no data lines")]
    NoData,
    /// An OctoMap benchmark file (`scans.bin`, `scene.txt`) is malformed.
    #[error("{what}")]
    OctomapBench {
        /// What is wrong.
        what: String,
    },
    /// A directory holds no run of a data set.
    #[error("no data set run here: expected {expected}")]
    NoRun {
        /// The file looked for.
        expected: String,
    },
    /// A directory holds several runs of a data set and none was chosen.
    #[error("several data set runs here (prefixes {prefixes}): choose one with the `prefix` setting")]
    SeveralRuns {
        /// The prefixes found, comma separated.
        prefixes: String,
    },
    /// The PLY header ends before `end_header`.
    #[error("PLY header has no `end_header` line")]
    PlyHeaderUnterminated,
    /// The PLY data ends before all declared elements are read.
    #[error("PLY data ends inside element `{element}` instance {index} of {count}")]
    PlyTruncated {
        /// The element.
        element: String,
        /// 0-based instance index where the data ends.
        index: u64,
        /// Instances declared in the header.
        count: u64,
    },
    /// A binary PLY vertex coordinate is NaN or infinite.
    #[error("vertex {index}: `{property}` is {value:e}, not a finite number")]
    PlyNotFinite {
        /// 0-based vertex index.
        index: u64,
        /// x, y or z.
        property: String,
        /// The value read.
        value: f64,
    },
    /// A PLY list has a negative length.
    #[error("element `{element}` instance {index}: negative list length {length}")]
    PlyNegativeListLength {
        /// The element.
        element: String,
        /// 0-based instance index.
        index: u64,
        /// The length read.
        length: i64,
    },
    /// A depth PNG is not 16-bit grayscale.
    #[error("depth PNG must be 16-bit grayscale, got {color_type:?} at {bit_depth} bits")]
    UnsupportedPng {
        /// The PNG colour type.
        color_type: png::ColorType,
        /// Bits per sample.
        bit_depth: u8,
    },
    /// A raw depth file's size does not match width × height × 2 bytes.
    #[error("raw u16 image of {width}x{height} needs {expected_bytes} bytes, file has {got_bytes}")]
    RawSizeMismatch {
        /// Image width, px.
        width: u32,
        /// Image height, px.
        height: u32,
        /// Bytes required.
        expected_bytes: u64,
        /// Bytes found.
        got_bytes: u64,
    },
    /// An image has zero width or height, or is too large to hold in memory.
    #[error("unsupported image size {width}x{height}")]
    ImageSize {
        /// Image width, px.
        width: u32,
        /// Image height, px.
        height: u32,
    },
}

/// Shorthand for results of this crate.
pub type Result<T, E = DatasetError> = std::result::Result<T, E>;

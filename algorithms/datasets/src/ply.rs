//! PLY point clouds (Turk 1994): a reader for the vertex positions of `ascii`,
//! `binary_little_endian` and `binary_big_endian` files, and a minimal writer of `x y z` clouds.
//!
//! The reader takes `element vertex N` with properties `x`, `y`, `z` of type float/float32/
//! double/float64 (read as f32, metres by convention). Other vertex properties (colours,
//! normals, even lists) and other elements (faces with list properties, before or after the
//! vertices) are skipped. ASCII data has one element instance per line. Errors name the file
//! and, for the header and ASCII data, the line; for binary data the element and instance.
//! NaN or infinite coordinates are errors. Files ending in `.bz2` are decompressed on the fly.

use std::fs::File;
use std::io::{self, BufRead, BufWriter, Write};
use std::path::Path;

use crate::error::{DatasetError, FileErrorKind, LineErrorKind, Result};
use crate::lines::{Line, LineReader, io_error, open_buffered, read_rest};

/// The encoding of a PLY file's data section.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum PlyFormat {
    /// Text, one element instance per line.
    Ascii,
    /// Binary, little-endian.
    BinaryLittleEndian,
    /// Binary, big-endian.
    BinaryBigEndian,
}

impl PlyFormat {
    fn keyword(self) -> &'static str {
        match self {
            PlyFormat::Ascii => "ascii",
            PlyFormat::BinaryLittleEndian => "binary_little_endian",
            PlyFormat::BinaryBigEndian => "binary_big_endian",
        }
    }
}

/// A PLY scalar type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Scalar::F32 | Scalar::F64)
    }

    /// Decodes the first `self.size()` bytes of `b` (which must be long enough).
    fn decode(self, b: &[u8], big_endian: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if big_endian { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) }
            }};
        }
        match self {
            Scalar::I8 => f64::from(get!(i8, 1)),
            Scalar::U8 => f64::from(get!(u8, 1)),
            Scalar::I16 => f64::from(get!(i16, 2)),
            Scalar::U16 => f64::from(get!(u16, 2)),
            Scalar::I32 => f64::from(get!(i32, 4)),
            Scalar::U32 => f64::from(get!(u32, 4)),
            Scalar::F32 => f64::from(get!(f32, 4)),
            Scalar::F64 => get!(f64, 8),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PropKind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug, Clone)]
struct Property {
    name: String,
    kind: PropKind,
    /// 0, 1, 2 for x, y, z of the vertex element.
    coord: Option<usize>,
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: u64,
    properties: Vec<Property>,
    is_vertex: bool,
}

impl Element {
    /// Byte size of one instance when it has no list properties.
    fn fixed_size(&self) -> Option<usize> {
        self.properties.iter().try_fold(0usize, |acc, p| match p.kind {
            PropKind::Scalar(s) => Some(acc + s.size()),
            PropKind::List { .. } => None,
        })
    }
}

const COORDS: [&str; 3] = ["x", "y", "z"];

/// Parses the header; the reader is left just after `end_header`.
fn read_header<R: BufRead>(reader: &mut LineReader<R>) -> Result<(PlyFormat, Vec<Element>)> {
    let path = reader.path().to_path_buf();
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut first = true;
    loop {
        let Some(line) = reader.next_line()? else {
            return Err(DatasetError::File { path, kind: FileErrorKind::PlyHeaderUnterminated });
        };
        let bad_line = |line: &Line<'_>| line.error(LineErrorKind::PlyHeaderLine { text: line.text.to_string() });
        if first {
            if line.text != "ply" {
                return Err(line.error(LineErrorKind::PlyMagic));
            }
            first = false;
            continue;
        }
        let mut fields = line.fields();
        match fields.next().unwrap_or_default() {
            "format" => {
                let f = match (fields.next(), fields.next(), fields.next()) {
                    (Some("ascii"), Some("1.0"), None) => PlyFormat::Ascii,
                    (Some("binary_little_endian"), Some("1.0"), None) => PlyFormat::BinaryLittleEndian,
                    (Some("binary_big_endian"), Some("1.0"), None) => PlyFormat::BinaryBigEndian,
                    _ => return Err(line.error(LineErrorKind::PlyFormat { text: line.text.to_string() })),
                };
                if format.replace(f).is_some() {
                    return Err(bad_line(&line));
                }
            }
            "comment" | "obj_info" => {}
            "element" => {
                let (Some(name), Some(count), None) = (fields.next(), fields.next(), fields.next()) else {
                    return Err(bad_line(&line));
                };
                let count: u64 = count.parse().map_err(|_| bad_line(&line))?;
                let is_vertex = name == "vertex" && !elements.iter().any(|e| e.is_vertex);
                elements.push(Element { name: name.to_string(), count, properties: Vec::new(), is_vertex });
            }
            "property" => {
                let Some(element) = elements.last_mut() else { return Err(bad_line(&line)) };
                let type_error = |t: &str| line.error(LineErrorKind::PlyUnknownType { type_name: t.to_string() });
                let (kind, name, type_name) = match fields.next() {
                    Some("list") => {
                        let (Some(c), Some(i), Some(name), None) =
                            (fields.next(), fields.next(), fields.next(), fields.next())
                        else {
                            return Err(bad_line(&line));
                        };
                        let count = Scalar::parse(c).ok_or_else(|| type_error(c))?;
                        let item = Scalar::parse(i).ok_or_else(|| type_error(i))?;
                        if count.is_float() {
                            return Err(bad_line(&line));
                        }
                        (PropKind::List { count, item }, name, format!("list {c} {i}"))
                    }
                    Some(t) => {
                        let (Some(name), None) = (fields.next(), fields.next()) else {
                            return Err(bad_line(&line));
                        };
                        (PropKind::Scalar(Scalar::parse(t).ok_or_else(|| type_error(t))?), name, t.to_string())
                    }
                    None => return Err(bad_line(&line)),
                };
                if element.properties.iter().any(|p| p.name == name) {
                    return Err(line.error(LineErrorKind::PlyDuplicateProperty {
                        element: element.name.clone(),
                        property: name.to_string(),
                    }));
                }
                let coord = if element.is_vertex { COORDS.iter().position(|c| *c == name) } else { None };
                if coord.is_some() && !matches!(kind, PropKind::Scalar(s) if s.is_float()) {
                    return Err(line.error(LineErrorKind::PlyCoordinateType { property: name.to_string(), type_name }));
                }
                element.properties.push(Property { name: name.to_string(), kind, coord });
            }
            "end_header" => {
                if fields.next().is_some() {
                    return Err(bad_line(&line));
                }
                let Some(format) = format else { return Err(bad_line(&line)) };
                let Some(vertex) = elements.iter().find(|e| e.is_vertex) else {
                    return Err(line.error(LineErrorKind::PlyNoVertexElement));
                };
                for (i, c) in COORDS.iter().enumerate() {
                    if !vertex.properties.iter().any(|p| p.coord == Some(i)) {
                        return Err(line.error(LineErrorKind::PlyMissingCoordinate { property: c.to_string() }));
                    }
                }
                return Ok((format, elements));
            }
            _ => return Err(bad_line(&line)),
        }
    }
}

/// Reads the vertex positions of a PLY file (plain or `.bz2`).
pub fn read_ply(path: impl AsRef<Path>) -> Result<Vec<[f32; 3]>> {
    let path = path.as_ref();
    read_ply_from(open_buffered(path)?, path)
}

/// Reads the vertex positions of PLY data from `reader`; `path` names the source in errors.
pub fn read_ply_from<R: BufRead>(reader: R, path: &Path) -> Result<Vec<[f32; 3]>> {
    let mut lines = LineReader::new(reader, path, false);
    let (format, elements) = read_header(&mut lines)?;
    match format {
        PlyFormat::Ascii => read_ascii_body(&mut lines, &elements),
        PlyFormat::BinaryLittleEndian | PlyFormat::BinaryBigEndian => {
            let body = read_rest(lines.into_inner(), path)?;
            read_binary_body(&body, path, &elements, format == PlyFormat::BinaryBigEndian)
        }
    }
}

/// Upper bound of up-front allocation, whatever a header claims.
const MAX_PREALLOC: u64 = 1 << 20;

fn read_ascii_body<R: BufRead>(lines: &mut LineReader<R>, elements: &[Element]) -> Result<Vec<[f32; 3]>> {
    let mut points = Vec::new();
    for element in elements {
        if element.is_vertex {
            points.reserve(element.count.min(MAX_PREALLOC) as usize);
        }
        for index in 0..element.count {
            let path = lines.path().to_path_buf();
            let Some(line) = lines.next_line()? else {
                return Err(DatasetError::File {
                    path,
                    kind: FileErrorKind::PlyTruncated { element: element.name.clone(), index, count: element.count },
                });
            };
            let mut fields = line.fields().enumerate();
            let mut expected = 0usize;
            let mut point = [0f32; 3];
            let count_error = |expected: usize| {
                line.error(LineErrorKind::PlyValueCount {
                    element: element.name.clone(),
                    expected,
                    got: line.fields().count(),
                })
            };
            for p in &element.properties {
                match p.kind {
                    PropKind::Scalar(_) => {
                        expected += 1;
                        let Some((i, text)) = fields.next() else { return Err(count_error(expected)) };
                        if let Some(c) = p.coord {
                            point[c] = line.number::<f32>(i + 1, text)?;
                        }
                    }
                    PropKind::List { .. } => {
                        expected += 1;
                        let Some((i, text)) = fields.next() else { return Err(count_error(expected)) };
                        let n: u64 = line.id(i + 1, text)?;
                        let n = usize::try_from(n).map_err(|_| count_error(usize::MAX))?;
                        expected = expected.saturating_add(n);
                        if n > 0 && fields.nth(n - 1).is_none() {
                            return Err(count_error(expected));
                        }
                    }
                }
            }
            if fields.next().is_some() {
                return Err(count_error(expected));
            }
            if element.is_vertex {
                points.push(point);
            }
        }
    }
    Ok(points)
}

fn read_binary_body(body: &[u8], path: &Path, elements: &[Element], big_endian: bool) -> Result<Vec<[f32; 3]>> {
    let mut points = Vec::new();
    let mut pos = 0usize;
    for element in elements {
        let truncated = |index: u64| DatasetError::File {
            path: path.to_path_buf(),
            kind: FileErrorKind::PlyTruncated { element: element.name.clone(), index, count: element.count },
        };
        let not_finite = |index: u64, c: usize, value: f64| DatasetError::File {
            path: path.to_path_buf(),
            kind: FileErrorKind::PlyNotFinite { index, property: COORDS[c].to_string(), value },
        };
        let rest = &body[pos..];
        if let Some(size) = element.fixed_size() {
            // Fast path: fixed-size records.
            let available = rest.len().checked_div(size).map_or(element.count, |n| n as u64);
            if available < element.count {
                return Err(truncated(available));
            }
            let len = (element.count as usize) * size; // fits: at most rest.len()
            if element.is_vertex {
                let mut offsets = [(0usize, Scalar::F32); 3];
                let mut offset = 0;
                for p in &element.properties {
                    if let PropKind::Scalar(s) = p.kind {
                        if let Some(c) = p.coord {
                            offsets[c] = (offset, s);
                        }
                        offset += s.size();
                    }
                }
                points.reserve(element.count as usize);
                for (index, record) in rest[..len].chunks_exact(size.max(1)).enumerate() {
                    let mut point = [0f32; 3];
                    for (c, &(off, s)) in offsets.iter().enumerate() {
                        let v = s.decode(&record[off..], big_endian);
                        let v32 = v as f32;
                        if !v32.is_finite() {
                            return Err(not_finite(index as u64, c, v));
                        }
                        point[c] = v32;
                    }
                    points.push(point);
                }
            }
            pos += len;
            continue;
        }
        // General path: records with list properties.
        if element.is_vertex {
            points.reserve(element.count.min(MAX_PREALLOC) as usize);
        }
        for index in 0..element.count {
            let mut point = [0f32; 3];
            for p in &element.properties {
                match p.kind {
                    PropKind::Scalar(s) => {
                        let bytes = body.get(pos..pos + s.size()).ok_or_else(|| truncated(index))?;
                        if let Some(c) = p.coord {
                            let v = s.decode(bytes, big_endian);
                            if !(v as f32).is_finite() {
                                return Err(not_finite(index, c, v));
                            }
                            point[c] = v as f32;
                        }
                        pos += s.size();
                    }
                    PropKind::List { count, item } => {
                        let bytes = body.get(pos..pos + count.size()).ok_or_else(|| truncated(index))?;
                        let n = count.decode(bytes, big_endian);
                        if n < 0.0 {
                            return Err(DatasetError::File {
                                path: path.to_path_buf(),
                                kind: FileErrorKind::PlyNegativeListLength {
                                    element: element.name.clone(),
                                    index,
                                    length: n as i64,
                                },
                            });
                        }
                        pos += count.size();
                        let skip = (n as usize).checked_mul(item.size()).ok_or_else(|| truncated(index))?;
                        if body.len() - pos < skip {
                            return Err(truncated(index));
                        }
                        pos += skip;
                    }
                }
            }
            if element.is_vertex {
                points.push(point);
            }
        }
    }
    Ok(points)
}

/// Writes `points` as a PLY file with one `element vertex` of `float x, y, z`.
///
/// Refuses (before creating the file) points with NaN or infinite coordinates, which the reader
/// would reject.
pub fn write_ply(path: impl AsRef<Path>, points: &[[f32; 3]], format: PlyFormat) -> Result<()> {
    let path = path.as_ref();
    if let Some((index, p)) = points.iter().enumerate().find(|(_, p)| !p.iter().all(|v| v.is_finite())) {
        let c = p.iter().position(|v| !v.is_finite()).unwrap_or(0);
        return Err(DatasetError::File {
            path: path.to_path_buf(),
            kind: FileErrorKind::PlyNotFinite {
                index: index as u64,
                property: COORDS[c].to_string(),
                value: p[c].into(),
            },
        });
    }
    let file = File::create(path).map_err(|e| io_error(path, e))?;
    let mut w = BufWriter::with_capacity(1 << 16, file);
    write_ply_to(&mut w, points, format).map_err(|e| io_error(path, e))
}

/// Writes `points` as PLY data to `w` (one `element vertex` of `float x, y, z`), as given (no
/// check for non-finite values). ASCII values use the shortest text that reads back exactly.
pub fn write_ply_to<W: Write>(mut w: W, points: &[[f32; 3]], format: PlyFormat) -> io::Result<()> {
    write!(
        w,
        "ply\nformat {} 1.0\ncomment slam_pipeline datasets\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nend_header\n",
        format.keyword(),
        points.len()
    )?;
    match format {
        PlyFormat::Ascii => {
            for p in points {
                writeln!(w, "{} {} {}", p[0], p[1], p[2])?;
            }
        }
        PlyFormat::BinaryLittleEndian | PlyFormat::BinaryBigEndian => {
            let big = format == PlyFormat::BinaryBigEndian;
            let mut buf = Vec::with_capacity(12 * points.len().min(1 << 16));
            for chunk in points.chunks(1 << 16) {
                buf.clear();
                for v in chunk.iter().flatten() {
                    buf.extend_from_slice(&if big { v.to_be_bytes() } else { v.to_le_bytes() });
                }
                w.write_all(&buf)?;
            }
        }
    }
    w.flush()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::fs;

    const FORMATS: [PlyFormat; 3] = [PlyFormat::Ascii, PlyFormat::BinaryLittleEndian, PlyFormat::BinaryBigEndian];

    fn sample_points() -> Vec<[f32; 3]> {
        vec![[0.0, -1.5, 2.25], [1e-7, 3.4e38, -0.1], [123.456, -7.0, 0.3333333]]
    }

    #[test]
    fn round_trip_every_format() {
        let dir = tempfile::tempdir().unwrap();
        for format in FORMATS {
            let path = dir.path().join(format!("{}.ply", format.keyword()));
            write_ply(&path, &sample_points(), format).unwrap();
            assert_eq!(read_ply(&path).unwrap(), sample_points(), "{format:?}");
        }
        let path = dir.path().join("empty.ply");
        write_ply(&path, &[], PlyFormat::BinaryLittleEndian).unwrap();
        assert!(read_ply(&path).unwrap().is_empty());
    }

    #[test]
    fn writer_refuses_non_finite() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nan.ply");
        let e = write_ply(&path, &[[0.0, 0.0, 0.0], [0.0, f32::NAN, 0.0]], PlyFormat::Ascii).unwrap_err();
        assert_eq!(e.to_string(), format!("{}: vertex 1: `y` is NaN, not a finite number", path.display()));
        assert!(!path.exists());
    }

    /// Ascii file with extra vertex properties, a list property, and faces after the vertices.
    const ASCII_MESH: &str = "ply\r\nformat ascii 1.0\ncomment made by hand\nobj_info x\n\
element vertex 3\nproperty uchar red\nproperty double x\nproperty float32 y\nproperty list uchar int idx\n\
property float64 z\nproperty float nx\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n\
255 1.5 2 2 7 8 3 0.1\n0 -1 -2 0 -3 0.2\n\n1 1e2 2e-1 1 9 3.25 0.3\n3 0 1 2\n4 0 1 2 2\n";

    #[test]
    fn ascii_skips_other_properties_and_elements() {
        let pts = read_ply_from(ASCII_MESH.as_bytes(), Path::new("mesh.ply")).unwrap();
        assert_eq!(pts, [[1.5, 2.0, 3.0], [-1.0, -2.0, -3.0], [100.0, 0.2, 3.25]]);
    }

    /// Binary file with faces both before and after the vertices, extra properties and types.
    fn binary_mesh(big: bool) -> Vec<u8> {
        let fmt = if big { "binary_big_endian" } else { "binary_little_endian" };
        let mut b = format!(
            "ply\nformat {fmt} 1.0\nelement face 1\nproperty list uchar int vertex_indices\n\
             element vertex 2\nproperty float x\nproperty short s\nproperty double y\nproperty float z\n\
             property uchar r\nelement face2 2\nproperty list int ushort idx\nproperty uint flag\nend_header\n"
        )
        .into_bytes();
        macro_rules! put {
            ($v:expr) => {
                b.extend_from_slice(&if big { $v.to_be_bytes() } else { $v.to_le_bytes() })
            };
        }
        put!(3u8);
        for i in [0i32, 1, 2] {
            put!(i);
        }
        for (x, s, y, z, r) in [(1.0f32, -3i16, 2.0f64, 3.0f32, 7u8), (-4.0, 9, 5.5, -6.0, 8)] {
            put!(x);
            put!(s);
            put!(y);
            put!(z);
            put!(r);
        }
        put!(2i32);
        put!(1u16);
        put!(2u16);
        put!(77u32);
        put!(0i32);
        put!(78u32);
        b
    }

    #[test]
    fn binary_skips_other_properties_and_elements() {
        for big in [false, true] {
            let pts = read_ply_from(&binary_mesh(big)[..], Path::new("m.ply")).unwrap();
            assert_eq!(pts, [[1.0, 2.0, 3.0], [-4.0, 5.5, -6.0]], "big endian: {big}");
        }
    }

    #[test]
    fn binary_vertex_with_list_property() {
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty list uchar float w\n\
property float x\nproperty float y\nproperty float z\nend_header\n"
            .to_vec();
        for (n, v) in [(2u8, 1.0f32), (0, 2.0)] {
            b.push(n);
            for _ in 0..n {
                b.extend_from_slice(&9f32.to_le_bytes());
            }
            for _ in 0..3 {
                b.extend_from_slice(&v.to_le_bytes());
            }
        }
        assert_eq!(read_ply_from(&b[..], Path::new("l.ply")).unwrap(), [[1.0; 3], [2.0; 3]]);
        let e = read_ply_from(&b[..b.len() - 1], Path::new("l.ply")).unwrap_err();
        assert_eq!(e.to_string(), "l.ply: PLY data ends inside element `vertex` instance 1 of 2");
    }

    #[test]
    fn binary_errors() {
        let full = binary_mesh(false);
        let e = read_ply_from(&full[..full.len() - 1], Path::new("m.ply")).unwrap_err();
        assert_eq!(e.to_string(), "m.ply: PLY data ends inside element `face2` instance 1 of 2");
        let header_len = full.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let cut = header_len + 13 + 10; // inside the first vertex
        let e = read_ply_from(&full[..cut], Path::new("m.ply")).unwrap_err();
        assert_eq!(e.to_string(), "m.ply: PLY data ends inside element `vertex` instance 0 of 2");

        let mut nan = Vec::new();
        write_ply_to(&mut nan, &[[0.0, 0.0, 0.0], [1.0, 2.0, f32::INFINITY]], PlyFormat::BinaryLittleEndian).unwrap();
        let e = read_ply_from(&nan[..], Path::new("n.ply")).unwrap_err();
        assert_eq!(e.to_string(), "n.ply: vertex 1: `z` is inf, not a finite number");

        // A double too large for f32 is not finite as f32.
        let mut big = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty double x\n\
property double y\nproperty double z\nend_header\n"
            .to_vec();
        for v in [0.0f64, 1e300, 0.0] {
            big.extend_from_slice(&v.to_le_bytes());
        }
        let e = read_ply_from(&big[..], Path::new("d.ply")).unwrap_err();
        assert_eq!(e.to_string(), "d.ply: vertex 0: `y` is 1e300, not a finite number");

        // A header claiming a huge count with no data must fail cleanly, without allocating it.
        let huge = b"ply\nformat binary_little_endian 1.0\nelement vertex 18446744073709551615\n\
property float x\nproperty float y\nproperty float z\nend_header\n";
        let e = read_ply_from(&huge[..], Path::new("h.ply")).unwrap_err();
        assert!(matches!(e.file_kind(), Some(FileErrorKind::PlyTruncated { index: 0, .. })), "{e}");
    }

    #[test]
    fn header_errors_name_the_line() {
        let h = |body: &str| format!("ply\nformat ascii 1.0\n{body}");
        let cases = [
            ("plx\n".to_string(), "1: not a PLY file (first line must be `ply`)"),
            (
                "ply\nformat binary 1.0\nend_header\n".to_string(),
                "2: unsupported PLY format line `format binary 1.0` (expected ascii, binary_little_endian or binary_big_endian 1.0)",
            ),
            (h("element vertex 1\nproperty float128 x\n"), "4: unknown PLY property type `float128`"),
            (
                h("element vertex 1\nproperty int x\n"),
                "4: vertex property `x` has type `int`, expected float, float32, double or float64",
            ),
            (
                h("element vertex 1\nproperty list uchar float y\n"),
                "4: vertex property `y` has type `list uchar float`, expected float, float32, double or float64",
            ),
            (h("element face 1\nend_header\n"), "4: PLY header declares no `element vertex`"),
            (
                h("element vertex 1\nproperty float x\nproperty float y\nend_header\n"),
                "6: PLY element vertex has no property `z`",
            ),
            (
                h("element vertex 1\nproperty float x\nproperty float x\n"),
                "5: property `x` is declared twice in element `vertex`",
            ),
            (h("property float x\n"), "3: malformed PLY header line `property float x`"),
            (h("element vertex -1\n"), "3: malformed PLY header line `element vertex -1`"),
            (h("bogus\n"), "3: malformed PLY header line `bogus`"),
        ];
        for (text, expected) in cases {
            let e = read_ply_from(text.as_bytes(), Path::new("h.ply")).unwrap_err();
            assert_eq!(e.to_string(), format!("h.ply:{expected}"));
        }
        let e = read_ply_from(&b"ply\nformat ascii 1.0\n"[..], Path::new("h.ply")).unwrap_err();
        assert_eq!(e.to_string(), "h.ply: PLY header has no `end_header` line");
    }

    #[test]
    fn ascii_body_errors_name_the_line() {
        let head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n\
                    element face 1\nproperty list uchar int v\nend_header\n";
        let cases = [
            ("1 2 3\n1 2\n3 0 1 2\n", "h.ply:11: element `vertex`: expected 3 values, got 2"),
            ("1 2 3\n1 2 3 4\n3 0 1 2\n", "h.ply:11: element `vertex`: expected 3 values, got 4"),
            ("1 2 3\n1 nan 3\n3 0 1 2\n", "h.ply:11: column 2: `nan` is not a finite number"),
            ("1 2 3\n1 a 3\n3 0 1 2\n", "h.ply:11: column 2: `a` is not a number"),
            ("1 2 3\n1 2 3\n3 0 1\n", "h.ply:12: element `face`: expected 4 values, got 3"),
            ("1 2 3\n1 2 3\n3 0 1 2 5\n", "h.ply:12: element `face`: expected 4 values, got 5"),
            ("1 2 3\n", "h.ply: PLY data ends inside element `vertex` instance 1 of 2"),
        ];
        for (body, expected) in cases {
            let e = read_ply_from(format!("{head}{body}").as_bytes(), Path::new("h.ply")).unwrap_err();
            assert_eq!(e.to_string(), expected);
        }
    }

    #[test]
    fn reads_bz2_ply() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.ply.bz2");
        let mut enc = bzip2::write::BzEncoder::new(fs::File::create(&path).unwrap(), bzip2::Compression::fast());
        write_ply_to(&mut enc, &sample_points(), PlyFormat::BinaryLittleEndian).unwrap();
        enc.finish().unwrap();
        assert_eq!(read_ply(&path).unwrap(), sample_points());
    }

    proptest! {
        #[test]
        fn round_trip_any_finite_cloud(
            pts in proptest::collection::vec(proptest::array::uniform3(-1e30f32..1e30f32), 0..200),
            fmt in 0usize..3,
        ) {
            let mut bytes = Vec::new();
            write_ply_to(&mut bytes, &pts, FORMATS[fmt]).unwrap();
            prop_assert_eq!(read_ply_from(&bytes[..], Path::new("p.ply")).unwrap(), pts);
        }
    }
}

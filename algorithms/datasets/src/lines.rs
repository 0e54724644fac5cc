//! The shared line reader of the text formats: opens plain or `.bz2` files, yields each data
//! line with its 1-based number, splits it into whitespace-separated fields and turns a parse
//! failure into a [`DatasetError::Line`] naming the file and line.

use std::fs::File;
use std::io::{self, BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::str::FromStr;

use crate::error::{DatasetError, LineErrorKind, Result};

const BUF_CAPACITY: usize = 1 << 16;

/// Wraps an I/O error with the file's path.
pub(crate) fn io_error(path: &Path, source: io::Error) -> DatasetError {
    DatasetError::Io { path: path.to_path_buf(), source }
}

/// True when the path ends in `.bz2` (case-insensitive).
pub(crate) fn is_bz2(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("bz2"))
}

/// Opens a file for buffered reading, decompressing it when its name ends in `.bz2`.
pub(crate) fn open_buffered(path: &Path) -> Result<Box<dyn BufRead>> {
    let file = File::open(path).map_err(|e| io_error(path, e))?;
    if is_bz2(path) {
        let decoder = bzip2::read::MultiBzDecoder::new(BufReader::with_capacity(BUF_CAPACITY, file));
        Ok(Box::new(BufReader::with_capacity(BUF_CAPACITY, decoder)))
    } else {
        Ok(Box::new(BufReader::with_capacity(BUF_CAPACITY, file)))
    }
}

/// A float type the readers parse (f32 or f64).
pub(crate) trait Float: FromStr + Copy + Default {
    /// Neither NaN nor infinite.
    fn finite(self) -> bool;
}

impl Float for f32 {
    fn finite(self) -> bool {
        self.is_finite()
    }
}

impl Float for f64 {
    fn finite(self) -> bool {
        self.is_finite()
    }
}

/// Reads a text file line by line, skipping blank lines and (optionally) `#` comment lines.
pub(crate) struct LineReader<R> {
    path: PathBuf,
    inner: R,
    buf: Vec<u8>,
    line_no: usize,
    hash_comments: bool,
}

impl LineReader<Box<dyn BufRead>> {
    /// Opens `path` (plain or `.bz2`); `hash_comments` skips lines whose first non-blank
    /// character is `#`.
    pub(crate) fn open(path: &Path, hash_comments: bool) -> Result<Self> {
        Ok(Self::new(open_buffered(path)?, path, hash_comments))
    }
}

impl<R: BufRead> LineReader<R> {
    /// Reads from `inner`, reporting errors against `path`.
    pub(crate) fn new(inner: R, path: &Path, hash_comments: bool) -> Self {
        Self { path: path.to_path_buf(), inner, buf: Vec::with_capacity(256), line_no: 0, hash_comments }
    }

    /// The file's path.
    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    /// The underlying reader, positioned just after the last line read.
    pub(crate) fn into_inner(self) -> R {
        self.inner
    }

    /// The next data line (not blank, not a comment), or `None` at the end of the file.
    pub(crate) fn next_line(&mut self) -> Result<Option<Line<'_>>> {
        loop {
            self.buf.clear();
            let n = self.inner.read_until(b'\n', &mut self.buf).map_err(|e| io_error(&self.path, e))?;
            if n == 0 {
                return Ok(None);
            }
            self.line_no += 1;
            // Work with offsets so the borrow of `self.buf` ends before the next iteration.
            let (start, end) = match std::str::from_utf8(&self.buf) {
                Ok(text) => {
                    let head_trimmed = text.trim_start_matches('\u{feff}').trim_ascii_start();
                    let start = text.len() - head_trimmed.len();
                    (start, start + head_trimmed.trim_ascii_end().len())
                }
                Err(_) => {
                    return Err(DatasetError::Line {
                        path: self.path.clone(),
                        line: self.line_no,
                        kind: LineErrorKind::NotUtf8,
                    });
                }
            };
            let first = self.buf.get(start).copied();
            if start == end || (self.hash_comments && first == Some(b'#')) {
                continue;
            }
            // Valid UTF-8: a sub-slice at character boundaries of a string checked above.
            let text = std::str::from_utf8(&self.buf[start..end]).unwrap_or_default();
            return Ok(Some(Line { path: &self.path, no: self.line_no, text }));
        }
    }
}

/// One data line: its file, 1-based number and text (trimmed).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Line<'a> {
    pub(crate) path: &'a Path,
    pub(crate) no: usize,
    pub(crate) text: &'a str,
}

impl<'a> Line<'a> {
    /// The error `kind` located on this line.
    pub(crate) fn error(&self, kind: LineErrorKind) -> DatasetError {
        DatasetError::Line { path: self.path.to_path_buf(), line: self.no, kind }
    }

    /// The whitespace-separated fields.
    pub(crate) fn fields(&self) -> std::str::SplitAsciiWhitespace<'a> {
        self.text.split_ascii_whitespace()
    }

    /// Exactly `N` fields, else a column-count error.
    pub(crate) fn fields_exact<const N: usize>(&self) -> Result<[&'a str; N]> {
        let mut out = [""; N];
        let mut got = 0;
        for field in self.fields() {
            if got < N {
                out[got] = field;
            }
            got += 1;
        }
        if got != N {
            return Err(self.error(LineErrorKind::ColumnCount { expected: N, got }));
        }
        Ok(out)
    }

    /// Exactly `N` finite numbers.
    pub(crate) fn numbers<T: Float, const N: usize>(&self) -> Result<[T; N]> {
        let fields = self.fields_exact::<N>()?;
        let mut out = [T::default(); N];
        for (i, (slot, text)) in out.iter_mut().zip(fields).enumerate() {
            *slot = self.number::<T>(i + 1, text)?;
        }
        Ok(out)
    }

    /// Parses the field `text` of 1-based `column` as a finite number.
    pub(crate) fn number<T: Float>(&self, column: usize, text: &str) -> Result<T> {
        match text.parse::<T>() {
            Ok(v) if v.finite() => Ok(v),
            Ok(_) => Err(self.error(LineErrorKind::NotFinite { column, text: text.to_string() })),
            Err(_) => Err(self.error(LineErrorKind::NotANumber { column, text: text.to_string() })),
        }
    }

    /// Parses an id: a non-negative integer, written either as an integer (`5`) or as a float
    /// with an integral value (`5.0000000000000000e+000`, as MATLAB exports write it).
    pub(crate) fn id<T: TryFrom<u64>>(&self, column: usize, text: &str) -> Result<T> {
        let bad = || self.error(LineErrorKind::NotAnId { column, text: text.to_string() });
        let value = match text.parse::<u64>() {
            Ok(v) => v,
            Err(_) => {
                let v: f64 = text.parse().map_err(|_| bad())?;
                // 2^53: beyond it not every integer is representable, so refuse.
                if !(v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v <= 9_007_199_254_740_992.0) {
                    return Err(bad());
                }
                v as u64
            }
        };
        T::try_from(value).map_err(|_| bad())
    }
}

/// Reads the rest of `reader` into memory.
pub(crate) fn read_rest(mut reader: impl Read, path: &Path) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    reader.read_to_end(&mut out).map_err(|e| io_error(path, e))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reader(text: &str, comments: bool) -> LineReader<&[u8]> {
        LineReader::new(text.as_bytes(), Path::new("mem.txt"), comments)
    }

    #[test]
    fn skips_blank_and_comment_lines_and_counts_all_lines() {
        let mut r = reader("# c\n\n 1 2\t\r\n\t#x\n3 4", true);
        let l = r.next_line().unwrap().unwrap();
        assert_eq!((l.no, l.text), (3, "1 2"));
        let l = r.next_line().unwrap().unwrap();
        assert_eq!((l.no, l.text), (5, "3 4"));
        assert!(r.next_line().unwrap().is_none());
    }

    #[test]
    fn hash_is_data_without_comment_mode() {
        let mut r = reader("# c\n", false);
        assert_eq!(r.next_line().unwrap().unwrap().text, "# c");
    }

    #[test]
    fn numbers_and_errors() {
        let mut r = reader("1e+003\t-2.5e-001\t\n1 x\n1 nan\n1 2 3\n", false);
        assert_eq!(r.next_line().unwrap().unwrap().numbers::<f64, 2>().unwrap(), [1000.0, -0.25]);
        let e = r.next_line().unwrap().unwrap().numbers::<f64, 2>().unwrap_err();
        assert_eq!(e.to_string(), "mem.txt:2: column 2: `x` is not a number");
        let e = r.next_line().unwrap().unwrap().numbers::<f32, 2>().unwrap_err();
        assert_eq!(e.to_string(), "mem.txt:3: column 2: `nan` is not a finite number");
        let e = r.next_line().unwrap().unwrap().numbers::<f64, 2>().unwrap_err();
        assert_eq!(e.to_string(), "mem.txt:4: expected 2 numbers, got 3");
    }

    #[test]
    fn ids() {
        let mut r = reader("5 5.0000e+000 1.5 -1 4294967296", false);
        let l = r.next_line().unwrap().unwrap();
        let f: Vec<&str> = l.fields().collect();
        assert_eq!(l.id::<u32>(1, f[0]).unwrap(), 5);
        assert_eq!(l.id::<u32>(2, f[1]).unwrap(), 5);
        assert!(l.id::<u32>(3, f[2]).is_err());
        assert!(l.id::<u32>(4, f[3]).is_err());
        assert!(l.id::<u32>(5, f[4]).is_err());
        assert_eq!(l.id::<u64>(5, f[4]).unwrap(), 4_294_967_296);
    }

    #[test]
    fn invalid_utf8_is_a_line_error() {
        let bytes: &[u8] = b"1 2\n\xff\xfe\n";
        let mut r = LineReader::new(bytes, Path::new("bin.txt"), false);
        r.next_line().unwrap();
        let e = r.next_line().unwrap_err();
        assert_eq!(e.to_string(), "bin.txt:2: line is not valid UTF-8");
    }
}

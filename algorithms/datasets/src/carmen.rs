//! CARMEN log files (`.log`, `.clf`; plain, `.gz` or `.bz2`), the format of the Radish 2-D laser
//! data sets: `FLASER`, `RAWLASER1..4`, `ROBOTLASER1` and `ODOM` lines are read, and `PARAM` lines
//! are kept by name (the robot's parameters, e.g. `robot_frontlaser_offset`: where the laser sits,
//! [`CarmenLog::front_laser_offset_m`]); every other message type (`NEFF`, `SYNC`, `TRUEPOS`,
//! `RLASER`, ...) is skipped and counted by type, and so are `PARAM` lines; `#` lines are comments.
//!
//! The reader is lenient line by line, strict about the file: a malformed line (too few fields, a
//! field that is not a number, a beam count that disagrees with the line's length) is skipped,
//! counted and described (`file:line: what`), and reading goes on; a file that ends inside a
//! compressed stream or mid-line is reported as truncated, keeping everything read before it.
//! Only a file that cannot be opened is an error.
//!
//! Line formats (CARMEN 0.7):
//! - `FLASER n r1..rn x y θ odom_x odom_y odom_θ ipc_timestamp ipc_hostname logger_timestamp`:
//!   the beams span 180° counter-clockwise from −90° (the robot's right); n odd (181, 361): the
//!   last beam is at +90°; n even (180, 360): beams are 180°/n apart.
//! - `RAWLASERk type start_angle fov resolution max_range accuracy remission_mode n r1..rn
//!   m e1..em ipc_timestamp ipc_hostname logger_timestamp` (no pose).
//! - `ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r1..rn m
//!   e1..em laser_x laser_y laser_θ robot_x robot_y robot_θ tv rv forward_safety side_safety
//!   turn_axis ipc_timestamp ipc_hostname logger_timestamp`.
//! - `ODOM x y θ tv rv accel ipc_timestamp ipc_hostname logger_timestamp`.
//! - `PARAM name value ipc_timestamp ipc_hostname logger_timestamp`.
//!
//! Stamps are the `ipc_timestamp` (when the sensor's message was sent), s.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

use crate::error::{DatasetError, Result};
use crate::lines::io_error;

/// A planar pose (x m, y m, θ rad).
pub type Pose2d = [f64; 3];

/// One laser scan of a CARMEN log.
#[derive(Debug, Clone, PartialEq)]
pub struct CarmenScan {
    /// 1-based line in the file.
    pub line: usize,
    /// The message type (`FLASER`, `RAWLASER1`, `ROBOTLASER1`, ...).
    pub kind: String,
    /// ipc_timestamp, s.
    pub stamp_s: f64,
    /// Angle of the first beam in the laser frame, rad.
    pub angle_min_rad: f64,
    /// Angle between beams, rad.
    pub angle_increment_rad: f64,
    /// The laser's maximum range if the line states it, m.
    pub range_max_m: Option<f64>,
    /// Ranges, m (as logged: may hold NaN, negative or maximum values).
    pub ranges: Vec<f32>,
    /// The odometry pose the line carries (FLASER: odom_x/y/θ; ROBOTLASER1: the robot pose), if any.
    pub odometry: Option<Pose2d>,
    /// FLASER's own pose field (x y θ: the robot's pose as the logging system knew it; in the
    /// "corrected" logs, a SLAM-corrected pose).
    pub pose: Option<Pose2d>,
}

/// One `ODOM` line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CarmenOdom {
    /// 1-based line.
    pub line: usize,
    /// ipc_timestamp, s.
    pub stamp_s: f64,
    /// The odometry pose.
    pub pose: Pose2d,
    /// Translational velocity, m/s.
    pub tv_mps: f64,
    /// Rotational velocity, rad/s.
    pub rv_radps: f64,
}

/// What reading found besides the data.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CarmenReport {
    /// Lines read.
    pub lines: usize,
    /// Lines of message types that are not read, by type.
    pub skipped_types: BTreeMap<String, usize>,
    /// Malformed lines skipped.
    pub bad_lines: usize,
    /// The first problems (`file:line: what`), at most [`CarmenReport::MAX_PROBLEMS`].
    pub problems: Vec<String>,
    /// Set when the file ends early (a truncated compressed stream or last line).
    pub truncated: Option<String>,
}

impl CarmenReport {
    /// How many problem messages are kept.
    pub const MAX_PROBLEMS: usize = 20;

    fn problem(&mut self, path: &Path, line: usize, what: String) {
        self.bad_lines += 1;
        if self.problems.len() < Self::MAX_PROBLEMS {
            self.problems.push(format!("{}:{line}: {what}", path.display()));
        }
    }
}

/// A whole CARMEN log.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CarmenLog {
    /// The file.
    pub path: PathBuf,
    /// Laser scans in file order.
    pub scans: Vec<CarmenScan>,
    /// ODOM lines in file order.
    pub odometry: Vec<CarmenOdom>,
    /// `PARAM` lines, name → value as written (a name set twice keeps the later value).
    pub params: BTreeMap<String, String>,
    /// Skipped and malformed lines.
    pub report: CarmenReport,
}

/// Where a scan's odometry comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OdometrySource {
    /// ODOM lines when the log has any, else the laser lines' own pose fields.
    Auto,
    /// ODOM lines, interpolated at each scan's stamp.
    OdomLines,
    /// The pose fields of the laser lines.
    LaserLines,
}

fn open(path: &Path) -> Result<Box<dyn Read>> {
    let file = std::fs::File::open(path).map_err(|e| io_error(path, e))?;
    let ext = path.extension().map(|e| e.to_ascii_lowercase());
    Ok(match ext.as_deref().and_then(|e| e.to_str()) {
        Some("gz") => Box::new(flate2::read::MultiGzDecoder::new(BufReader::new(file))),
        Some("bz2") => Box::new(bzip2::read::MultiBzDecoder::new(BufReader::new(file))),
        _ => Box::new(file),
    })
}

/// Reads a CARMEN log (see the module docs). Fails only when the file cannot be opened.
pub fn read_carmen(path: &Path) -> Result<CarmenLog> {
    let mut reader = BufReader::with_capacity(1 << 16, open(path)?);
    let mut log = CarmenLog { path: path.to_path_buf(), ..Default::default() };
    let mut buf = Vec::with_capacity(8192);
    let mut line_no = 0usize;
    loop {
        buf.clear();
        match reader.read_until(b'\n', &mut buf) {
            Ok(0) => break,
            Ok(_) => {}
            Err(e) => {
                log.report.truncated = Some(format!("{}:{}: stopped reading: {e}", path.display(), line_no + 1));
                break;
            }
        }
        line_no += 1;
        log.report.lines += 1;
        let complete = buf.last() == Some(&b'\n');
        let Ok(text) = std::str::from_utf8(&buf) else {
            log.report.problem(path, line_no, "line is not valid UTF-8".into());
            continue;
        };
        let text = text.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = text.split_whitespace().collect();
        let kind = fields[0];
        let parsed = match kind {
            "FLASER" => parse_flaser(&fields, line_no).map(Parsed::Scan),
            "ROBOTLASER1" | "ROBOTLASER2" => parse_raw(&fields, line_no, true).map(Parsed::Scan),
            k if k.starts_with("RAWLASER") => parse_raw(&fields, line_no, false).map(Parsed::Scan),
            "ODOM" => parse_odom(&fields, line_no).map(Parsed::Odom),
            "PARAM" => {
                *log.report.skipped_types.entry("PARAM".to_string()).or_default() += 1;
                if let [_, name, value, ..] = fields[..] {
                    log.params.insert(name.to_string(), value.to_string());
                }
                continue;
            }
            other => {
                *log.report.skipped_types.entry(other.to_string()).or_default() += 1;
                continue;
            }
        };
        match parsed {
            Ok(Parsed::Scan(s)) => log.scans.push(s),
            Ok(Parsed::Odom(o)) => log.odometry.push(o),
            Err(what) => {
                if !complete {
                    log.report.truncated =
                        Some(format!("{}:{line_no}: the file ends inside this line ({what})", path.display()));
                    log.report.bad_lines += 1;
                } else {
                    log.report.problem(path, line_no, format!("{kind}: {what}"));
                }
            }
        }
    }
    Ok(log)
}

enum Parsed {
    Scan(CarmenScan),
    Odom(CarmenOdom),
}

fn num(fields: &[&str], i: usize) -> std::result::Result<f64, String> {
    let f = fields.get(i).ok_or_else(|| format!("too few fields ({}, needed more than {i})", fields.len()))?;
    f.parse::<f64>().map_err(|_| format!("field {} `{f}` is not a number", i + 1))
}

fn finite(v: f64, what: &str) -> std::result::Result<f64, String> {
    if v.is_finite() { Ok(v) } else { Err(format!("{what} is not finite")) }
}

fn count(fields: &[&str], i: usize) -> std::result::Result<usize, String> {
    let f = fields.get(i).ok_or_else(|| format!("too few fields ({})", fields.len()))?;
    f.parse::<usize>().map_err(|_| format!("field {} `{f}` is not a beam count", i + 1))
}

/// Ranges as logged (NaN and negative values are kept for the consumer to count).
fn ranges(fields: &[&str], from: usize, n: usize) -> std::result::Result<Vec<f32>, String> {
    (from..from + n)
        .map(|i| {
            let f = fields[i];
            f.parse::<f32>().map_err(|_| format!("range {} `{f}` is not a number", i - from + 1))
        })
        .collect()
}

/// The stamp of a line ending `ipc_timestamp ipc_hostname logger_timestamp`.
fn stamp(fields: &[&str]) -> std::result::Result<f64, String> {
    let n = fields.len();
    if n < 4 {
        return Err("too few fields for the timestamps".into());
    }
    finite(num(fields, n - 3)?, "ipc_timestamp")
}

fn parse_flaser(f: &[&str], line: usize) -> std::result::Result<CarmenScan, String> {
    let n = count(f, 1)?;
    // FLASER n r... x y θ ox oy oθ ipc host logger
    let expected = 2 + n + 6 + 3;
    if f.len() != expected {
        return Err(format!("{n} beams need {expected} fields, the line has {}", f.len()));
    }
    if n < 2 {
        return Err(format!("{n} beams"));
    }
    let r = ranges(f, 2, n)?;
    let p = 2 + n;
    let pose = [finite(num(f, p)?, "x")?, finite(num(f, p + 1)?, "y")?, finite(num(f, p + 2)?, "theta")?];
    let o = 2 + n + 3;
    let odom =
        [finite(num(f, o)?, "odom_x")?, finite(num(f, o + 1)?, "odom_y")?, finite(num(f, o + 2)?, "odom_theta")?];
    let inc = if n % 2 == 1 { std::f64::consts::PI / (n - 1) as f64 } else { std::f64::consts::PI / n as f64 };
    Ok(CarmenScan {
        line,
        kind: "FLASER".into(),
        stamp_s: stamp(f)?,
        angle_min_rad: -std::f64::consts::FRAC_PI_2,
        angle_increment_rad: inc,
        range_max_m: None,
        ranges: r,
        odometry: Some(odom),
        pose: Some(pose),
    })
}

fn parse_raw(f: &[&str], line: usize, robot: bool) -> std::result::Result<CarmenScan, String> {
    // KIND type start fov res max acc mode n r... m e... [robot fields] ipc host logger
    let start = finite(num(f, 2)?, "start_angle")?;
    let fov = finite(num(f, 3)?, "field_of_view")?;
    let res = finite(num(f, 4)?, "angular_resolution")?;
    let max = finite(num(f, 5)?, "maximum_range")?;
    let n = count(f, 8)?;
    if n < 2 {
        return Err(format!("{n} beams"));
    }
    let m_at = 9 + n;
    let m = count(f, m_at)?;
    let tail = if robot { 11 } else { 0 };
    let expected = m_at + 1 + m + tail + 3;
    if f.len() != expected {
        return Err(format!("{n} beams and {m} remissions need {expected} fields, the line has {}", f.len()));
    }
    let r = ranges(f, 9, n)?;
    let odometry = if robot {
        let o = m_at + 1 + m + 3;
        Some([
            finite(num(f, o)?, "robot_x")?,
            finite(num(f, o + 1)?, "robot_y")?,
            finite(num(f, o + 2)?, "robot_theta")?,
        ])
    } else {
        None
    };
    let inc = if res > 0.0 { res } else { fov / (n - 1) as f64 };
    Ok(CarmenScan {
        line,
        kind: f[0].to_string(),
        stamp_s: stamp(f)?,
        angle_min_rad: start,
        angle_increment_rad: inc,
        range_max_m: (max > 0.0).then_some(max),
        ranges: r,
        odometry,
        pose: None,
    })
}

fn parse_odom(f: &[&str], line: usize) -> std::result::Result<CarmenOdom, String> {
    if f.len() != 10 {
        return Err(format!("expected 10 fields, the line has {}", f.len()));
    }
    Ok(CarmenOdom {
        line,
        stamp_s: stamp(f)?,
        pose: [finite(num(f, 1)?, "x")?, finite(num(f, 2)?, "y")?, finite(num(f, 3)?, "theta")?],
        tv_mps: finite(num(f, 4)?, "tv")?,
        rv_radps: finite(num(f, 5)?, "rv")?,
    })
}

fn wrap(a: f64) -> f64 {
    let w = a.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI { w - std::f64::consts::TAU } else { w }
}

impl CarmenLog {
    /// Where the front laser sits ahead of the robot's reference point, m (CARMEN's
    /// `robot_frontlaser_offset` parameter: along the robot's x, negative behind it), if the log
    /// states it. The pose fields and the odometry are the robot's; the beams start at the laser.
    /// A value that is not a finite number is reported as an error naming it.
    pub fn front_laser_offset_m(&self) -> std::result::Result<Option<f64>, String> {
        let Some(v) = self.params.get("robot_frontlaser_offset") else { return Ok(None) };
        match v.parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(Some(x)),
            _ => Err(format!("{}: PARAM robot_frontlaser_offset `{v}` is not a finite number", self.path.display())),
        }
    }

    /// The odometry pose at each scan (`None` where there is none: no pose fields, or outside
    /// the span of the ODOM lines in [`CarmenLog::odometry_in_order`]), by `source`.
    pub fn scan_odometry(&self, source: OdometrySource) -> Vec<Option<Pose2d>> {
        if !self.uses_odom_lines(source) {
            return self.scans.iter().map(|s| s.odometry).collect();
        }
        let (odo, _) = self.odometry_in_order();
        self.scans
            .iter()
            .map(|s| {
                let i = odo.partition_point(|o| o.0 < s.stamp_s);
                if let Some(o) = odo.get(i)
                    && o.0 == s.stamp_s
                {
                    return Some(o.1);
                }
                let (a, b) = (odo.get(i.checked_sub(1)?)?, odo.get(i)?);
                let f = (s.stamp_s - a.0) / (b.0 - a.0);
                Some([
                    a.1[0] + f * (b.1[0] - a.1[0]),
                    a.1[1] + f * (b.1[1] - a.1[1]),
                    wrap(a.1[2] + f * wrap(b.1[2] - a.1[2])),
                ])
            })
            .collect()
    }

    /// Whether `source` takes the odometry from the ODOM lines.
    pub fn uses_odom_lines(&self, source: OdometrySource) -> bool {
        match source {
            OdometrySource::Auto => !self.odometry.is_empty(),
            OdometrySource::OdomLines => true,
            OdometrySource::LaserLines => false,
        }
    }

    /// The ODOM lines as (stamp, pose) in file order, each only if its stamp is after the last
    /// one kept, and how many were left out. The Radish corrected logs write, after each scan, an
    /// ODOM line with stamp 0 (the pose reset to the scan's), and a few lines whose stamps are
    /// out of order (fr079 holds a second stream with two-decimal stamps, ~1 m off the robot);
    /// sorting them in would make the path jump back and forth. Whatever the scans' odometry source,
    /// these are the odometry between scans (ingest replays them, grid_slam places poses there).
    pub fn odometry_in_order(&self) -> (Vec<(f64, Pose2d)>, usize) {
        let mut t: Vec<(f64, Pose2d)> = Vec::with_capacity(self.odometry.len());
        for o in &self.odometry {
            if t.last().is_none_or(|l| o.stamp_s > l.0) {
                t.push((o.stamp_s, o.pose));
            }
        }
        let left_out = self.odometry.len() - t.len();
        (t, left_out)
    }
}

/// The error type, for callers that match on it.
pub type CarmenError = DatasetError;

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn flaser(n: usize, r: f32, x: f64, t: f64) -> String {
        let ranges: Vec<String> = (0..n).map(|_| format!("{r}")).collect();
        format!("FLASER {n} {} {x} 0 0 {x} 0 0 {t} host {t}\n", ranges.join(" "))
    }

    #[test]
    fn lines_of_every_kind_are_read_and_others_counted() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = dir.path().join("a.log");
        let mut text = String::from("# comment\nPARAM robot_x 1 1.0 h 1.0\n");
        text += &flaser(361, 2.0, 0.5, 1.0);
        text += "ODOM 0.1 0.2 0.3 0.5 0.1 0 1.5 host 1.5\n";
        text += "RAWLASER1 0 -1.5708 3.1416 0.0174533 81.9 0.01 0 3 1 2 3 0 2.0 host 2.0\n";
        text += "ROBOTLASER1 0 -1.5708 3.1416 0.0174533 81.9 0.01 0 3 1 2 nan 0 0.1 0 0 1 2 0.5 0 0 0.5 0.5 0 3.0 host 3.0\n";
        text += "NEFF 30 1 h 1\nFLASER 3 1 2 x 0 0 0 0 0 0 1 h 1\n";
        std::fs::write(&p, text).expect("write");
        let log = read_carmen(&p).expect("read");
        assert_eq!(log.scans.len(), 3);
        assert_eq!(log.odometry.len(), 1);
        let f = &log.scans[0];
        assert_eq!((f.ranges.len(), f.line), (361, 3));
        assert!((f.angle_increment_rad - 0.5f64.to_radians()).abs() < 1e-12);
        assert_eq!(f.odometry, Some([0.5, 0.0, 0.0]));
        assert_eq!(log.scans[1].odometry, None);
        assert_eq!(log.scans[1].range_max_m, Some(81.9));
        assert_eq!(log.scans[2].odometry, Some([1.0, 2.0, 0.5]));
        assert!(log.scans[2].ranges[2].is_nan(), "NaN ranges are kept for the consumer to count");
        assert_eq!(log.report.skipped_types.get("PARAM"), Some(&1));
        assert_eq!(log.params.get("robot_x").map(String::as_str), Some("1"));
        assert_eq!(log.front_laser_offset_m(), Ok(None));
        assert_eq!(log.report.skipped_types.get("NEFF"), Some(&1));
        assert_eq!(log.report.bad_lines, 1);
        assert!(log.report.problems[0].contains("a.log:8: FLASER"), "{:?}", log.report.problems);
        // ODOM lines win in Auto; the laser lines' own poses otherwise.
        let auto = log.scan_odometry(OdometrySource::Auto);
        assert_eq!(auto[0], None, "before the first ODOM line");
        assert_eq!(log.scan_odometry(OdometrySource::LaserLines)[0], Some([0.5, 0.0, 0.0]));
    }

    #[test]
    fn odom_lines_out_of_order_are_left_out_not_sorted_in() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = dir.path().join("c.log");
        // As the Radish corrected logs write them: a reset to the scan's pose with stamp 0 after
        // each scan, and a stray line whose stamp belongs far back.
        let mut text = String::new();
        for (x, t) in [(0.0, 1.0), (0.1, 1.1), (0.2, 1.2), (0.2, 0.0), (0.3, 1.3), (9.0, 0.71), (0.4, 1.4)] {
            text += &format!("ODOM {x} 0 0 0 0 0 {t} host {t}\n");
        }
        text += &flaser(3, 2.0, 0.25, 1.25);
        std::fs::write(&p, text).expect("write");
        let log = read_carmen(&p).expect("read");
        let (track, left_out) = log.odometry_in_order();
        assert_eq!(left_out, 2);
        assert_eq!(track.iter().map(|o| o.0).collect::<Vec<_>>(), vec![1.0, 1.1, 1.2, 1.3, 1.4]);
        let at = log.scan_odometry(OdometrySource::OdomLines)[0].expect("inside the ODOM lines");
        assert!((at[0] - 0.25).abs() < 1e-12, "interpolated between 1.2 and 1.3 s: {at:?}");
    }

    #[test]
    fn a_truncated_gzip_keeps_what_was_read_and_says_so() {
        let dir = tempfile::tempdir().expect("tmp");
        let p = dir.path().join("b.log.gz");
        let mut text = String::new();
        for k in 0..200 {
            text += &flaser(180, 3.0, k as f64 * 0.1, k as f64);
        }
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        enc.write_all(text.as_bytes()).expect("gz");
        let gz = enc.finish().expect("gz");
        std::fs::write(&p, &gz).expect("write");
        let full = read_carmen(&p).expect("read");
        assert_eq!(full.scans.len(), 200);
        assert_eq!(full.report.truncated, None);
        assert!((full.scans[0].angle_increment_rad - 1f64.to_radians()).abs() < 1e-12);
        std::fs::write(&p, &gz[..gz.len() / 2]).expect("write");
        let cut = read_carmen(&p).expect("read");
        assert!(cut.scans.len() > 10 && cut.scans.len() < 200, "{}", cut.scans.len());
        let why = cut.report.truncated.expect("reported");
        assert!(why.contains("b.log.gz:"), "{why}");
        let missing = read_carmen(&dir.path().join("none.log")).unwrap_err();
        assert!(missing.to_string().contains("none.log"), "{missing}");
    }

    #[test]
    fn the_freiburg_079_log_reads_whole_when_present() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/carmen/freiburg-079-corrected.log.gz");
        if !crate::shared_data_present(&p, "the_freiburg_079_log_reads_whole_when_present") {
            return;
        }
        let log = read_carmen(&p).expect("read");
        assert_eq!(log.scans.len(), 4791);
        assert_eq!(log.odometry.len(), 9725);
        assert_eq!((log.report.bad_lines, log.report.truncated.clone()), (0, None));
        assert_eq!(log.report.skipped_types.get("NEFF"), Some(&4791));
        assert_eq!(log.front_laser_offset_m(), Ok(Some(-0.04)));
        assert!(log.scans.iter().all(|s| s.ranges.len() == 360));
        assert!(log.scan_odometry(OdometrySource::Auto).iter().filter(|o| o.is_some()).count() > 4780);
    }
}

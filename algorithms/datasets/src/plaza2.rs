//! The CMU "Plaza 2" range-only data set (Djugash, Hamner & Roth, JFR 2009), as shipped with
//! GTSAM plus the ground truth and beacon survey extracted from `Plaza2_.mat`.
//!
//! Files (whitespace separated, scientific notation, `#` comment lines allowed everywhere):
//! - `Plaza2_DR.txt`: `t_s delta_dist_m delta_heading_rad` odometry increments, ~10 Hz;
//! - `Plaza2_TD.txt`: `t_s sender_id beacon_id range_m` ranges from the robot (sender 2) to beacons;
//! - `Plaza2_GT.txt`: `t_s x_m y_m heading_rad` ground truth (GPS/INS; heading offset by π from
//!   the direction of travel);
//! - `Plaza2_TL.txt`: `beacon_id x_m y_m` surveyed beacon positions, same frame as the ground truth;
//! - `Plaza2_DRp.txt`: `t_s x_m y_m heading_rad` the dead-reckoned path as shipped (optional).
//!
//! Other runs of the same data set ship the same files under their own prefix (`Plaza1_TD.txt`, ...):
//! [`Plaza2::load`] finds the prefix, [`Plaza2::load_with_prefix`] takes it.
//!
//! Real files have small warts: a line whose time is before an earlier line's (2 of 3,529 in one
//! Plaza range file) is not an error. The readers put such lines into time order (a stable sort,
//! so equal times keep their file order) and report them ([`OutOfOrder`]: how many, the first
//! file:line) so that a replay can count them and warn; only unreadable lines are errors.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use crate::error::{FileErrorKind, LineErrorKind, Result};
use crate::lines::{Line, LineReader};

/// File name of the odometry increments.
pub const ODOMETRY_FILE: &str = "Plaza2_DR.txt";
/// File name of the ranges.
pub const RANGES_FILE: &str = "Plaza2_TD.txt";
/// File name of the ground truth.
pub const GROUND_TRUTH_FILE: &str = "Plaza2_GT.txt";
/// File name of the beacon survey.
pub const BEACONS_FILE: &str = "Plaza2_TL.txt";
/// File name of the dead-reckoned path.
pub const DEAD_RECKONING_FILE: &str = "Plaza2_DRp.txt";
/// The prefix of the Plaza 2 run's files; other runs have their own (`Plaza1_`).
pub const DEFAULT_PREFIX: &str = "Plaza2_";
/// Suffixes of the files after the run's prefix.
const ODOMETRY_SUFFIX: &str = "DR.txt";
const RANGES_SUFFIX: &str = "TD.txt";
const GROUND_TRUTH_SUFFIX: &str = "GT.txt";
const BEACONS_SUFFIX: &str = "TL.txt";

/// Lines of a file whose time was before an earlier line's; the reader sorted them into place.
#[derive(Debug, Clone, PartialEq)]
pub struct OutOfOrder {
    /// The file.
    pub path: PathBuf,
    /// How many data lines had a time before the latest time read above them.
    pub lines: usize,
    /// 1-based number of the first such line.
    pub first_line: usize,
    /// Its time, s.
    pub first_t_s: f64,
    /// The latest time above it, s.
    pub previous_t_s: f64,
}

impl std::fmt::Display for OutOfOrder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}:{}: time {} s is before an earlier line's {} s ({} line(s) out of time order in this file, sorted into place)",
            self.path.display(),
            self.first_line,
            self.first_t_s,
            self.previous_t_s,
            self.lines
        )
    }
}

/// One odometry increment (a line of `Plaza2_DR.txt`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OdometryRow {
    /// Time, s.
    pub t_s: f64,
    /// Distance travelled since the previous row, m.
    pub delta_dist_m: f64,
    /// Heading change since the previous row, rad.
    pub delta_heading_rad: f64,
}

/// One range measurement (a line of `Plaza2_TD.txt`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RangeRow {
    /// Time, s.
    pub t_s: f64,
    /// Id of the radio that measured (2 = the robot).
    pub sender_id: u32,
    /// Id of the beacon ranged to (a [`Beacon::beacon_id`]).
    pub beacon_id: u32,
    /// Measured range, m.
    pub range_m: f64,
}

/// A planar pose at a time (a line of `Plaza2_GT.txt` or `Plaza2_DRp.txt`), in the survey frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PoseRow {
    /// Time, s.
    pub t_s: f64,
    /// x, m.
    pub x_m: f64,
    /// y, m.
    pub y_m: f64,
    /// Heading, rad (for the ground truth: offset by π from the direction of travel).
    pub heading_rad: f64,
}

/// A surveyed beacon (a line of `Plaza2_TL.txt`), in the survey frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Beacon {
    /// Beacon id, as in [`RangeRow::beacon_id`].
    pub beacon_id: u32,
    /// x, m.
    pub x_m: f64,
    /// y, m.
    pub y_m: f64,
}

/// The four files of the data set, loaded and cross-checked.
#[derive(Debug, Clone, PartialEq)]
pub struct Plaza2 {
    /// Odometry increments, in time order.
    pub odometry: Vec<OdometryRow>,
    /// Ranges, in time order; every beacon id is in `beacons`.
    pub ranges: Vec<RangeRow>,
    /// Ground truth, in time order.
    pub ground_truth: Vec<PoseRow>,
    /// Surveyed beacons, in file order, ids unique.
    pub beacons: Vec<Beacon>,
    /// Files that had lines out of time order (sorted into place), at most one entry per file.
    pub out_of_order: Vec<OutOfOrder>,
}

impl Plaza2 {
    /// Loads a run from `dir`: `Plaza2_DR.txt`, `Plaza2_TD.txt`, `Plaza2_GT.txt` and
    /// `Plaza2_TL.txt`, or the same files of another run under the one prefix found in `dir`
    /// (see [`find_prefix`]).
    pub fn load(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref();
        Self::load_with_prefix(dir, &find_prefix(dir)?)
    }

    /// Loads `<prefix>DR.txt`, `<prefix>TD.txt`, `<prefix>GT.txt` and `<prefix>TL.txt` from `dir`,
    /// checking that every range's beacon id is listed in `<prefix>TL.txt`. Lines out of time
    /// order are sorted into place and listed in [`Plaza2::out_of_order`].
    pub fn load_with_prefix(dir: impl AsRef<Path>, prefix: &str) -> Result<Self> {
        let dir = dir.as_ref();
        let file = |suffix: &str| dir.join(format!("{prefix}{suffix}"));
        let beacons_path = file(BEACONS_SUFFIX);
        let beacons = read_beacons(&beacons_path)?;
        let mut out_of_order = vec![];
        let (ranges, o) = parse_ranges(&file(RANGES_SUFFIX), Some((&beacons, &beacons_path)))?;
        out_of_order.extend(o);
        let (odometry, o) = read_timed(&file(ODOMETRY_SUFFIX), odometry_row)?;
        out_of_order.extend(o);
        let (ground_truth, o) = read_timed(&file(GROUND_TRUTH_SUFFIX), pose_row)?;
        out_of_order.extend(o);
        Ok(Self { odometry, ranges, ground_truth, beacons, out_of_order })
    }

    /// The beacon with id `beacon_id`.
    pub fn beacon(&self, beacon_id: u32) -> Option<&Beacon> {
        self.beacons.iter().find(|b| b.beacon_id == beacon_id)
    }
}

/// The prefix of the run's files in `dir`: `Plaza2_` when `Plaza2_TD.txt` is there, else the
/// prefix of the one `*TD.txt` file in `dir` (`Plaza1_TD.txt` → `Plaza1_`). No such file, or
/// several, is an error naming the directory.
pub fn find_prefix(dir: impl AsRef<Path>) -> Result<String> {
    let dir = dir.as_ref();
    if dir.join(RANGES_FILE).is_file() {
        return Ok(DEFAULT_PREFIX.to_string());
    }
    let entries = std::fs::read_dir(dir).map_err(|e| crate::lines::io_error(dir, e))?;
    let mut prefixes: Vec<String> = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().to_str().and_then(|n| n.strip_suffix(RANGES_SUFFIX)).map(str::to_string))
        .collect();
    prefixes.sort();
    match prefixes.len() {
        1 => Ok(prefixes.remove(0)),
        0 => Err(crate::DatasetError::File {
            path: dir.to_path_buf(),
            kind: FileErrorKind::NoRun {
                expected: format!("{RANGES_FILE} (or another run's <prefix>{RANGES_SUFFIX})"),
            },
        }),
        _ => Err(crate::DatasetError::File {
            path: dir.to_path_buf(),
            kind: FileErrorKind::SeveralRuns { prefixes: prefixes.join(", ") },
        }),
    }
}

/// Counts the lines whose time is before the latest time above them.
#[derive(Default)]
struct TimeOrder {
    latest_t_s: Option<f64>,
    lines: usize,
    first: Option<(usize, f64, f64)>,
}

impl TimeOrder {
    fn note(&mut self, line: &Line<'_>, t_s: f64) {
        match self.latest_t_s {
            Some(latest) if t_s < latest => {
                self.lines += 1;
                self.first.get_or_insert((line.no, t_s, latest));
            }
            _ => self.latest_t_s = Some(t_s),
        }
    }

    /// Sorts `rows` by time (stable) when lines were out of order, and says so.
    fn finish<T>(self, path: &Path, rows: &mut [T], time: impl Fn(&T) -> f64) -> Option<OutOfOrder> {
        let (first_line, first_t_s, previous_t_s) = self.first?;
        rows.sort_by(|a, b| time(a).total_cmp(&time(b)));
        Some(OutOfOrder { path: path.to_path_buf(), lines: self.lines, first_line, first_t_s, previous_t_s })
    }
}

/// A timed row type: the time is the first column.
trait Timed {
    fn t_s(&self) -> f64;
}

impl Timed for OdometryRow {
    fn t_s(&self) -> f64 {
        self.t_s
    }
}

impl Timed for PoseRow {
    fn t_s(&self) -> f64 {
        self.t_s
    }
}

fn odometry_row([t_s, delta_dist_m, delta_heading_rad]: [f64; 3]) -> OdometryRow {
    OdometryRow { t_s, delta_dist_m, delta_heading_rad }
}

fn pose_row([t_s, x_m, y_m, heading_rad]: [f64; 4]) -> PoseRow {
    PoseRow { t_s, x_m, y_m, heading_rad }
}

/// Reads rows of `N` numbers with the time in the first column, in time order.
fn read_timed<const N: usize, T: Timed>(
    path: &Path,
    make: impl Fn([f64; N]) -> T,
) -> Result<(Vec<T>, Option<OutOfOrder>)> {
    let mut reader = LineReader::open(path, true)?;
    let mut order = TimeOrder::default();
    let mut rows = Vec::new();
    while let Some(line) = reader.next_line()? {
        let v = line.numbers::<f64, N>()?;
        order.note(&line, v[0]);
        rows.push(make(v));
    }
    let out_of_order = order.finish(path, &mut rows, T::t_s);
    Ok((rows, out_of_order))
}

/// Reads `Plaza2_DR.txt` (odometry increments), in time order (see [`OutOfOrder`]).
pub fn read_odometry(path: impl AsRef<Path>) -> Result<Vec<OdometryRow>> {
    read_timed(path.as_ref(), odometry_row).map(|(rows, _)| rows)
}

/// Reads `Plaza2_GT.txt` (ground truth), in time order (see [`OutOfOrder`]).
pub fn read_ground_truth(path: impl AsRef<Path>) -> Result<Vec<PoseRow>> {
    read_timed(path.as_ref(), pose_row).map(|(rows, _)| rows)
}

/// Reads `Plaza2_DRp.txt` (the dead-reckoned path as shipped; same format as the ground truth).
pub fn read_dead_reckoning(path: impl AsRef<Path>) -> Result<Vec<PoseRow>> {
    read_ground_truth(path)
}

/// Reads `Plaza2_TD.txt` (ranges) without checking beacon ids; see [`read_ranges_checked`].
pub fn read_ranges(path: impl AsRef<Path>) -> Result<Vec<RangeRow>> {
    parse_ranges(path.as_ref(), None).map(|(rows, _)| rows)
}

/// Reads `Plaza2_TD.txt` (ranges); a beacon id not in `beacons` (read from `beacons_path`) is an
/// error on its line.
pub fn read_ranges_checked(
    path: impl AsRef<Path>,
    beacons: &[Beacon],
    beacons_path: impl AsRef<Path>,
) -> Result<Vec<RangeRow>> {
    parse_ranges(path.as_ref(), Some((beacons, beacons_path.as_ref()))).map(|(rows, _)| rows)
}

fn parse_ranges(path: &Path, beacons: Option<(&[Beacon], &Path)>) -> Result<(Vec<RangeRow>, Option<OutOfOrder>)> {
    let mut reader = LineReader::open(path, true)?;
    let mut order = TimeOrder::default();
    let mut rows = Vec::new();
    while let Some(line) = reader.next_line()? {
        let [t, sender, beacon, range] = line.fields_exact::<4>()?;
        let row = RangeRow {
            t_s: line.number(1, t)?,
            sender_id: line.id(2, sender)?,
            beacon_id: line.id(3, beacon)?,
            range_m: line.number(4, range)?,
        };
        order.note(&line, row.t_s);
        if let Some((beacons, beacons_path)) = beacons
            && !beacons.iter().any(|b| b.beacon_id == row.beacon_id)
        {
            return Err(line.error(LineErrorKind::UnknownBeacon {
                beacon_id: row.beacon_id,
                beacon_file: PathBuf::from(beacons_path),
            }));
        }
        rows.push(row);
    }
    let out_of_order = order.finish(path, &mut rows, |r| r.t_s);
    Ok((rows, out_of_order))
}

/// Reads `Plaza2_TL.txt` (beacon survey); ids must be unique and at least one beacon present.
pub fn read_beacons(path: impl AsRef<Path>) -> Result<Vec<Beacon>> {
    let path = path.as_ref();
    let mut reader = LineReader::open(path, true)?;
    let mut first_line = HashMap::new();
    let mut beacons = Vec::new();
    while let Some(line) = reader.next_line()? {
        let [id, x, y] = line.fields_exact::<3>()?;
        let beacon = Beacon { beacon_id: line.id(1, id)?, x_m: line.number(2, x)?, y_m: line.number(3, y)? };
        if let Some(&first) = first_line.get(&beacon.beacon_id) {
            return Err(line.error(LineErrorKind::DuplicateBeacon { beacon_id: beacon.beacon_id, first_line: first }));
        }
        first_line.insert(beacon.beacon_id, line.no);
        beacons.push(beacon);
    }
    if beacons.is_empty() {
        return Err(crate::DatasetError::File { path: path.to_path_buf(), kind: FileErrorKind::NoData });
    }
    Ok(beacons)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

    fn data_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("data/plaza2")
    }

    #[test]
    fn loads_the_committed_data_set() {
        let p = Plaza2::load(data_dir()).unwrap();
        assert_eq!(p.odometry.len(), 4090);
        assert_eq!(p.ranges.len(), 1816);
        assert_eq!(p.ground_truth.len(), 4091);
        let mut ids: Vec<u32> = p.beacons.iter().map(|b| b.beacon_id).collect();
        ids.sort_unstable();
        assert_eq!(ids, [0, 1, 5, 6]);

        // First and last rows, value for value (as the file's text parses).
        let num = |text: &str| text.parse::<f64>().unwrap();
        let dr0 = p.odometry[0];
        assert_eq!(dr0.t_s, num("3.1520999939441681e+003"));
        assert_eq!(dr0.delta_dist_m, num("6.4152145140576101e-004"));
        assert_eq!(dr0.delta_heading_rad, num("-6.7308112020647570e-004"));
        let td_last = *p.ranges.last().unwrap();
        assert_eq!(td_last.t_s, num("3.5613715173983946e+003"));
        assert_eq!((td_last.sender_id, td_last.beacon_id), (2, 5));
        assert_eq!(td_last.range_m, num("5.8662150683311602e+001"));
        assert_eq!(p.ground_truth[0], PoseRow { t_s: 3152.0, x_m: -34.208649, y_m: 45.300764, heading_rad: -2.021089 });
        assert_eq!(*p.beacon(5).unwrap(), Beacon { beacon_id: 5, x_m: 1.709463, y_m: -5.812203 });
        assert!(p.beacon(2).is_none());
        assert!(p.ranges.iter().all(|r| r.sender_id == 2));

        let drp = read_dead_reckoning(data_dir().join(DEAD_RECKONING_FILE)).unwrap();
        assert_eq!(drp.len(), 4091);
    }

    /// Writes the four files into a temp dir, replacing `file` with `contents`.
    fn dir_with(file: &str, contents: &str) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        let good = [
            (ODOMETRY_FILE, "1.0 0.1 0.01\n2.0 0.1 0.01\n"),
            (RANGES_FILE, "1.5e+000\t2.0e+000\t1.0e+000\t1.0e+001\t\r\n"),
            (GROUND_TRUTH_FILE, "# t x y h\n1 0 0 0\n"),
            (BEACONS_FILE, "# id x y\n1 10 0\n0 0 10\n"),
        ];
        for (name, text) in good {
            fs::write(dir.path().join(name), if name == file { contents } else { text }).unwrap();
        }
        dir
    }

    fn load_err(file: &str, contents: &str) -> (String, String) {
        let dir = dir_with(file, contents);
        let e = Plaza2::load(dir.path()).unwrap_err().to_string();
        let prefix = format!("{}:", dir.path().join(file).display());
        let rest = e.strip_prefix(&prefix).unwrap_or_else(|| panic!("`{e}` does not start with `{prefix}`"));
        (e.clone(), rest.to_string())
    }

    #[test]
    fn small_fixture_loads() {
        let dir = dir_with("", "");
        let p = Plaza2::load(dir.path()).unwrap();
        assert_eq!(p.odometry.len(), 2);
        assert_eq!(p.ranges, [RangeRow { t_s: 1.5, sender_id: 2, beacon_id: 1, range_m: 10.0 }]);
        assert_eq!(p.ground_truth.len(), 1);
        assert_eq!(p.beacons.len(), 2);
    }

    #[test]
    fn malformed_lines_name_file_and_line() {
        let cases = [
            (RANGES_FILE, "1 2 1 10\n\n2 2 1\n", "3: expected 4 numbers, got 3"),
            (RANGES_FILE, "1 2 1 abc\n", "1: column 4: `abc` is not a number"),
            (RANGES_FILE, "1 2 1 NaN\n", "1: column 4: `NaN` is not a finite number"),
            (RANGES_FILE, "1 2 1.5 4\n", "1: column 3: `1.5` is not a valid non-negative integer id"),
            (ODOMETRY_FILE, "1 0 0\n2 inf 0\n", "2: column 2: `inf` is not a finite number"),
            (GROUND_TRUTH_FILE, "# c\n1 2 3 4 5\n", "2: expected 4 numbers, got 5"),
            (BEACONS_FILE, "1 0 0\n# c\n1 2 2\n", "3: beacon id 1 is listed twice (first on line 1)"),
        ];
        for (file, contents, expected) in cases {
            let (full, rest) = load_err(file, contents);
            assert_eq!(rest, expected, "{full}");
        }
    }

    #[test]
    fn lines_out_of_time_order_are_sorted_into_place_and_reported() {
        let dir = dir_with(RANGES_FILE, "1 2 1 10\n3 2 1 30\n2 2 0 20\n# c\n4 2 1 40\n2.5 2 1 25\n");
        let p = Plaza2::load(dir.path()).unwrap();
        let t: Vec<f64> = p.ranges.iter().map(|r| r.t_s).collect();
        assert_eq!(t, [1.0, 2.0, 2.5, 3.0, 4.0]);
        assert_eq!(p.ranges[1].range_m, 20.0, "rows move with their time");
        let [o] = &p.out_of_order[..] else { panic!("{:?}", p.out_of_order) };
        assert_eq!((o.lines, o.first_line, o.first_t_s, o.previous_t_s), (2, 3, 2.0, 3.0));
        assert_eq!(o.path, dir.path().join(RANGES_FILE));
        let text = o.to_string();
        assert!(
            text.starts_with(&format!("{}:3: time 2 s is before", dir.path().join(RANGES_FILE).display())),
            "{text}"
        );
        assert!(text.contains("2 line(s) out of time order"), "{text}");
        // Equal times keep their file order; a file in order reports nothing.
        let dir = dir_with(ODOMETRY_FILE, "1 0.1 0\n1 0.2 0\n0.5 0.3 0\n");
        let p = Plaza2::load(dir.path()).unwrap();
        let d: Vec<f64> = p.odometry.iter().map(|r| r.delta_dist_m).collect();
        assert_eq!(d, [0.3, 0.1, 0.2]);
        assert_eq!(p.out_of_order.len(), 1);
        assert!(Plaza2::load(dir_with("", "").path()).unwrap().out_of_order.is_empty());
    }

    #[test]
    fn another_runs_prefix_is_found_or_chosen() {
        let plaza2 = dir_with("", "");
        let dir = tempfile::tempdir().unwrap();
        for f in [ODOMETRY_FILE, RANGES_FILE, GROUND_TRUTH_FILE, BEACONS_FILE] {
            let renamed = f.replace("Plaza2_", "Plaza1_");
            fs::copy(plaza2.path().join(f), dir.path().join(renamed)).unwrap();
        }
        assert_eq!(find_prefix(dir.path()).unwrap(), "Plaza1_");
        assert_eq!(Plaza2::load(dir.path()).unwrap().ranges.len(), 1);
        // Two runs side by side: Plaza2_ wins by name, another pair must be chosen.
        fs::copy(plaza2.path().join(RANGES_FILE), dir.path().join("Other_TD.txt")).unwrap();
        let e = Plaza2::load(dir.path()).unwrap_err().to_string();
        assert!(e.contains("prefixes Other_, Plaza1_") && e.contains("`prefix` setting"), "{e}");
        assert_eq!(Plaza2::load_with_prefix(dir.path(), "Plaza1_").unwrap().beacons.len(), 2);
        let empty = tempfile::tempdir().unwrap();
        let e = Plaza2::load(empty.path()).unwrap_err().to_string();
        assert!(e.contains("no data set run here: expected Plaza2_TD.txt"), "{e}");
    }

    #[test]
    fn unknown_beacon_names_the_range_line() {
        let (full, rest) = load_err(RANGES_FILE, "1 2 1 10\n2 2 7 10\n");
        assert!(rest.starts_with("2: beacon id 7 is not listed in "), "{full}");
        assert!(rest.ends_with(BEACONS_FILE), "{full}");
        // Unchecked reading accepts it.
        let dir = dir_with(RANGES_FILE, "1 2 1 10\n2 2 7 10\n");
        assert_eq!(read_ranges(dir.path().join(RANGES_FILE)).unwrap().len(), 2);
    }

    #[test]
    fn empty_beacon_list_and_missing_file() {
        let (full, rest) = load_err(BEACONS_FILE, "# nothing\n");
        assert_eq!(rest, " no data lines", "{full}");
        let e = read_odometry("/nonexistent/Plaza2_DR.txt").unwrap_err();
        assert!(matches!(e, crate::DatasetError::Io { .. }));
        assert!(e.to_string().starts_with("/nonexistent/Plaza2_DR.txt: "), "{e}");
    }
}

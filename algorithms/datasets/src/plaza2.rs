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
//! Times must not decrease from one data line to the next.

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
}

impl Plaza2 {
    /// Loads `Plaza2_DR.txt`, `Plaza2_TD.txt`, `Plaza2_GT.txt` and `Plaza2_TL.txt` from `dir`,
    /// checking that every range's beacon id is listed in `Plaza2_TL.txt`.
    pub fn load(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref();
        let beacons_path = dir.join(BEACONS_FILE);
        let beacons = read_beacons(&beacons_path)?;
        let ranges = parse_ranges(&dir.join(RANGES_FILE), Some((&beacons, &beacons_path)))?;
        Ok(Self {
            odometry: read_odometry(dir.join(ODOMETRY_FILE))?,
            ranges,
            ground_truth: read_ground_truth(dir.join(GROUND_TRUTH_FILE))?,
            beacons,
        })
    }

    /// The beacon with id `beacon_id`.
    pub fn beacon(&self, beacon_id: u32) -> Option<&Beacon> {
        self.beacons.iter().find(|b| b.beacon_id == beacon_id)
    }
}

/// Checks that times do not decrease.
struct TimeOrder(Option<f64>);

impl TimeOrder {
    fn check(&mut self, line: &Line<'_>, t_s: f64) -> Result<()> {
        if let Some(previous_t_s) = self.0
            && t_s < previous_t_s
        {
            return Err(line.error(LineErrorKind::TimeWentBackwards { t_s, previous_t_s }));
        }
        self.0 = Some(t_s);
        Ok(())
    }
}

/// Reads rows of `N` numbers with the time in the first column.
fn read_timed<const N: usize, T>(path: &Path, mut make: impl FnMut([f64; N]) -> T) -> Result<Vec<T>> {
    let mut reader = LineReader::open(path, true)?;
    let mut order = TimeOrder(None);
    let mut rows = Vec::new();
    while let Some(line) = reader.next_line()? {
        let v = line.numbers::<f64, N>()?;
        order.check(&line, v[0])?;
        rows.push(make(v));
    }
    Ok(rows)
}

/// Reads `Plaza2_DR.txt` (odometry increments).
pub fn read_odometry(path: impl AsRef<Path>) -> Result<Vec<OdometryRow>> {
    read_timed(path.as_ref(), |[t_s, delta_dist_m, delta_heading_rad]| OdometryRow {
        t_s,
        delta_dist_m,
        delta_heading_rad,
    })
}

/// Reads `Plaza2_GT.txt` (ground truth).
pub fn read_ground_truth(path: impl AsRef<Path>) -> Result<Vec<PoseRow>> {
    read_timed(path.as_ref(), |[t_s, x_m, y_m, heading_rad]| PoseRow { t_s, x_m, y_m, heading_rad })
}

/// Reads `Plaza2_DRp.txt` (the dead-reckoned path as shipped; same format as the ground truth).
pub fn read_dead_reckoning(path: impl AsRef<Path>) -> Result<Vec<PoseRow>> {
    read_ground_truth(path)
}

/// Reads `Plaza2_TD.txt` (ranges) without checking beacon ids; see [`read_ranges_checked`].
pub fn read_ranges(path: impl AsRef<Path>) -> Result<Vec<RangeRow>> {
    parse_ranges(path.as_ref(), None)
}

/// Reads `Plaza2_TD.txt` (ranges); a beacon id not in `beacons` (read from `beacons_path`) is an
/// error on its line.
pub fn read_ranges_checked(
    path: impl AsRef<Path>,
    beacons: &[Beacon],
    beacons_path: impl AsRef<Path>,
) -> Result<Vec<RangeRow>> {
    parse_ranges(path.as_ref(), Some((beacons, beacons_path.as_ref())))
}

fn parse_ranges(path: &Path, beacons: Option<(&[Beacon], &Path)>) -> Result<Vec<RangeRow>> {
    let mut reader = LineReader::open(path, true)?;
    let mut order = TimeOrder(None);
    let mut rows = Vec::new();
    while let Some(line) = reader.next_line()? {
        let [t, sender, beacon, range] = line.fields_exact::<4>()?;
        let row = RangeRow {
            t_s: line.number(1, t)?,
            sender_id: line.id(2, sender)?,
            beacon_id: line.id(3, beacon)?,
            range_m: line.number(4, range)?,
        };
        order.check(&line, row.t_s)?;
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
    Ok(rows)
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
            (ODOMETRY_FILE, "1 0 0\n0.5 0 0\n", "2: time 0.5 s is before the previous line's time 1 s"),
            (GROUND_TRUTH_FILE, "# c\n1 2 3 4 5\n", "2: expected 4 numbers, got 5"),
            (BEACONS_FILE, "1 0 0\n# c\n1 2 2\n", "3: beacon id 1 is listed twice (first on line 1)"),
        ];
        for (file, contents, expected) in cases {
            let (full, rest) = load_err(file, contents);
            assert_eq!(rest, expected, "{full}");
        }
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

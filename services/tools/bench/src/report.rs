//! Results: exact nearest-rank percentiles of the raw samples, one [`Row`] per transport, the
//! printed table (with ratios against the iceoryx2 row) and the CSV.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context as _;

/// Name of the no-transport reference row.
pub const GEN_ONLY: &str = "gen-only";
/// Name of the row the ratios are taken against.
pub const IOX: &str = "iox";

/// Percentiles of a set of samples, ns (nearest rank: the smallest sample with at least `q` of
/// the samples at or below it; with fewer than 1000 samples p99.9 is the maximum).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Summary {
    /// Samples.
    pub count: u64,
    /// Median.
    pub p50: u64,
    /// 99th percentile.
    pub p99: u64,
    /// 99.9th percentile.
    pub p999: u64,
    /// Largest sample.
    pub max: u64,
}

impl Summary {
    /// Summary of `samples` (`None` when there are none).
    pub fn of(samples: &[u64]) -> Option<Self> {
        if samples.is_empty() {
            return None;
        }
        let mut s = samples.to_vec();
        s.sort_unstable();
        let rank = |q: f64| s[((q * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1];
        Some(Self { count: s.len() as u64, p50: rank(0.5), p99: rank(0.99), p999: rank(0.999), max: s[s.len() - 1] })
    }
}

/// One transport's results.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Row {
    /// Transport name (`gen-only`, `iox`, `socket-bincode`, `socket-raw`).
    pub transport: String,
    /// Points per cloud.
    pub points: usize,
    /// Configured rate, Hz.
    pub rate_hz: f64,
    /// Measured clouds sent.
    pub frames: u64,
    /// Measured clouds that did not reach the consumer (or were not recorded); 0 for `gen-only`.
    pub lost: u64,
    /// Producer thread CPU per cloud.
    pub cpu: Option<Summary>,
    /// Hop latency (publish → every point read by the consumer); `None` for `gen-only`.
    pub hop: Option<Summary>,
    /// Ready latency (publish → payload usable by the consumer, before its read pass).
    pub ready: Option<Summary>,
    /// Consumer thread CPU per cloud.
    pub consumer_cpu: Option<Summary>,
}

fn us(ns: u64) -> f64 {
    ns as f64 / 1000.0
}

fn ratio(a: Option<u64>, b: Option<u64>) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) if b > 0 => Some(a as f64 / b as f64),
        _ => None,
    }
}

/// Ratios of a row against the iceoryx2 row: hop p50, hop p99, producer CPU p50.
pub fn ratios_vs_iox(row: &Row, rows: &[Row]) -> [Option<f64>; 3] {
    let Some(iox) = rows.iter().find(|r| r.transport == IOX) else { return [None; 3] };
    [
        ratio(row.hop.map(|h| h.p50), iox.hop.map(|h| h.p50)),
        ratio(row.hop.map(|h| h.p99), iox.hop.map(|h| h.p99)),
        ratio(row.cpu.map(|c| c.p50), iox.cpu.map(|c| c.p50)),
    ]
}

/// Producer CPU p50 above the `gen-only` row's p50, ns (the transport's own CPU cost per cloud).
pub fn cpu_over_gen(row: &Row, rows: &[Row]) -> Option<i64> {
    let gen_p50 = rows.iter().find(|r| r.transport == GEN_ONLY)?.cpu?.p50;
    (row.transport != GEN_ONLY).then_some(row.cpu?.p50 as i64 - gen_p50 as i64)
}

/// The table as printed, with ratio lines underneath.
pub fn render_table(rows: &[Row]) -> String {
    let dash = || "-".to_string();
    let f1 = |v: Option<f64>| v.map_or_else(dash, |v| format!("{v:.1}"));
    let fx = |v: Option<f64>| v.map_or_else(dash, |v| format!("{v:.2}x"));
    let mut t = String::new();
    let _ = writeln!(
        t,
        "{:<41} | {:^26} | {:^35} | {:>8} | {:>8} | {:^23}",
        "", "producer CPU µs/frame", "hop latency µs", "ready µs", "cons CPU", "ratio vs iox"
    );
    let _ = writeln!(
        t,
        "{:<15} {:>7} {:>5} {:>6} {:>4} | {:>8} {:>8} {:>8} | {:>8} {:>8} {:>8} {:>8} | {:>8} | {:>8} | {:>7} {:>7} {:>7}",
        "transport",
        "points",
        "Hz",
        "frames",
        "lost",
        "p50",
        "p99",
        "-gen p50",
        "p50",
        "p99",
        "p99.9",
        "max",
        "p50",
        "µs p50",
        "hop p50",
        "hop p99",
        "CPU p50",
    );
    let _ = writeln!(t, "{}", "-".repeat(155));
    for row in rows {
        let gen_row = row.transport == GEN_ONLY;
        let [r50, r99, rcpu] = ratios_vs_iox(row, rows);
        let lat = |f: fn(&Summary) -> u64| f1(row.hop.as_ref().map(|h| us(f(h))));
        let _ = writeln!(
            t,
            "{:<15} {:>7} {:>5} {:>6} {:>4} | {:>8} {:>8} {:>8} | {:>8} {:>8} {:>8} {:>8} | {:>8} | {:>8} | {:>7} {:>7} {:>7}",
            row.transport,
            row.points,
            format!("{}", row.rate_hz),
            row.frames,
            if gen_row { dash() } else { row.lost.to_string() },
            f1(row.cpu.map(|c| us(c.p50))),
            f1(row.cpu.map(|c| us(c.p99))),
            f1(cpu_over_gen(row, rows).map(|d| d as f64 / 1000.0)),
            lat(|h| h.p50),
            lat(|h| h.p99),
            lat(|h| h.p999),
            lat(|h| h.max),
            f1(row.ready.map(|r| us(r.p50))),
            f1(row.consumer_cpu.map(|c| us(c.p50))),
            fx(r50),
            fx(r99),
            fx(rcpu),
        );
    }
    for row in rows.iter().filter(|r| r.transport != IOX && r.transport != GEN_ONLY) {
        if let [Some(r50), Some(r99), Some(rcpu)] = ratios_vs_iox(row, rows) {
            let _ = writeln!(
                t,
                "{}/iox: hop latency p50 {r50:.1}x, p99 {r99:.1}x; producer CPU p50 {rcpu:.1}x",
                row.transport
            );
        }
    }
    t
}

/// CSV header line.
pub const CSV_HEADER: &str = "transport,points,rate_hz,frames,count,lost,cpu_p50_us,cpu_p99_us,cpu_over_gen_p50_us,\
p50_us,p99_us,p999_us,max_us,ready_p50_us,consumer_cpu_p50_us,p50_vs_iox,p99_vs_iox,cpu_p50_vs_iox";

/// The rows as CSV (header included; empty cells where a value does not apply). `count` is the
/// number of latency samples.
pub fn render_csv(rows: &[Row]) -> String {
    let f = |v: Option<f64>| v.map_or_else(String::new, |v| format!("{v:.3}"));
    let mut t = String::from(CSV_HEADER);
    t.push('\n');
    for row in rows {
        let [r50, r99, rcpu] = ratios_vs_iox(row, rows);
        let h = |g: fn(&Summary) -> u64| f(row.hop.as_ref().map(|s| us(g(s))));
        let _ = writeln!(
            t,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            row.transport,
            row.points,
            row.rate_hz,
            row.frames,
            row.hop.map_or(0, |h| h.count),
            row.lost,
            f(row.cpu.map(|c| us(c.p50))),
            f(row.cpu.map(|c| us(c.p99))),
            f(cpu_over_gen(row, rows).map(|d| d as f64 / 1000.0)),
            h(|s| s.p50),
            h(|s| s.p99),
            h(|s| s.p999),
            h(|s| s.max),
            f(row.ready.map(|r| us(r.p50))),
            f(row.consumer_cpu.map(|c| us(c.p50))),
            f(r50),
            f(r99),
            f(rcpu),
        );
    }
    t
}

/// Writes [`render_csv`] to `path`.
pub fn write_csv(path: &Path, rows: &[Row]) -> anyhow::Result<()> {
    std::fs::write(path, render_csv(rows)).with_context(|| format!("cannot write {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_percentiles_are_exact_samples() {
        let s: Vec<u64> = (1..=1000).rev().collect();
        let sum = Summary::of(&s).unwrap();
        assert_eq!((sum.count, sum.p50, sum.p99, sum.p999, sum.max), (1000, 500, 990, 999, 1000));
        let small = Summary::of(&[7, 3, 5]).unwrap();
        assert_eq!((small.p50, small.p99, small.max), (5, 7, 7));
        assert!(Summary::of(&[]).is_none());
    }

    fn row(name: &str, cpu: u64, hop: Option<u64>) -> Row {
        let s = |v: u64| Summary { count: 10, p50: v, p99: 2 * v, p999: 3 * v, max: 4 * v };
        Row {
            transport: name.into(),
            points: 1000,
            rate_hz: 30.0,
            frames: 10,
            cpu: Some(s(cpu)),
            hop: hop.map(s),
            ..Default::default()
        }
    }

    #[test]
    fn ratios_are_taken_against_the_iox_row_and_overhead_against_gen_only() {
        let rows =
            vec![row(GEN_ONLY, 1000, None), row(IOX, 2000, Some(10_000)), row("socket-bincode", 8000, Some(250_000))];
        assert_eq!(ratios_vs_iox(&rows[2], &rows), [Some(25.0), Some(25.0), Some(4.0)]);
        assert_eq!(cpu_over_gen(&rows[1], &rows), Some(1000));
        assert_eq!(cpu_over_gen(&rows[0], &rows), None);
        let table = render_table(&rows);
        assert!(
            table.contains("socket-bincode/iox: hop latency p50 25.0x, p99 25.0x; producer CPU p50 4.0x"),
            "{table}"
        );
        let csv = render_csv(&rows);
        let lines: Vec<_> = csv.lines().collect();
        assert_eq!(lines.len(), 4);
        assert!(lines[3].starts_with("socket-bincode,1000,30,10,10,0,8.000,16.000,7.000,250.000,"), "{csv}");
        assert!(lines[1].starts_with("gen-only,1000,30,10,0,0,1.000,2.000,,,"), "{csv}");
    }
}

//! Results of `pipeline_bench latency`: one [`CaseResult`] per transport × size × chain, the table
//! (end to end and per hop), the ratio lines against the goals, and the CSV.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context as _;

use super::cli::size_label;
use crate::report::Summary;

/// The iceoryx2 row through our runtime (ratios are taken against it).
pub const IOX: &str = "iox";
/// The bare iceoryx2 row.
pub const IOX_BARE: &str = "iox-bare";
/// The raw-socket baseline.
pub const SOCKET_RAW: &str = "socket-raw";
/// The bincode-over-socket baseline.
pub const SOCKET_BINCODE: &str = "socket-bincode";

/// Goal: round trip at 8 MiB at least this many times lower than raw Unix sockets.
pub const GOAL_VS_RAW: f64 = 8.0;
/// Goal: round trip at 8 MiB at least this many times lower than bincode over Unix sockets.
pub const GOAL_VS_BINCODE: f64 = 25.0;
/// Goal: our runtime's hop at most this many times a bare iceoryx2 hop.
pub const GOAL_RUNTIME_OVER_BARE: f64 = 1.2;
/// The payload size the goals are stated for.
pub const GOAL_SIZE: usize = 8 << 20;

/// One case's results.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CaseResult {
    /// Transport name.
    pub transport: String,
    /// Payload bytes.
    pub size_bytes: usize,
    /// Relay processes in the chain (hops = chain + 1).
    pub chain: usize,
    /// Latency of each hop: `hops[k]` is link k (producer → relay 1 is hop 1; the last is back into
    /// the producer). `None` when a hop has no sample.
    pub hops: Vec<Option<Summary>>,
    /// End to end (producer → every relay → producer: a round trip for a chain of 1).
    pub e2e: Option<Summary>,
    /// The raw end-to-end samples, ns (for the histogram).
    pub e2e_ns: Vec<u64>,
    /// Measured messages asked for.
    pub samples_wanted: u64,
    /// Measured messages that did not come back within the timeout.
    pub lost: u64,
    /// Messages with a torn or wrong-size payload, at any receiver.
    pub bad: u64,
    /// Messages that started more than one period late.
    pub late: u64,
    /// The case's time budget ended it before every measured message was sent.
    pub cut_short: bool,
    /// iceoryx2: WaitSet wake-ups with a notification per message received, over all relays.
    pub wakeups_per_message: Option<f64>,
}

impl CaseResult {
    /// Median of the hops' p50 values, ns (the typical single hop of this case).
    pub fn hop_p50(&self) -> Option<u64> {
        let mut v: Vec<u64> = self.hops.iter().flatten().map(|h| h.p50).collect();
        v.sort_unstable();
        (!v.is_empty()).then(|| v[(v.len() - 1) / 2])
    }
}

/// Results of a run.
#[derive(Debug, Clone, Default)]
pub struct LatencyResult {
    /// Every case, in the order run.
    pub cases: Vec<CaseResult>,
    /// The iceoryx2 prefix the run used (nothing with it is left in /dev/shm).
    pub prefix: String,
}

fn us(ns: u64) -> f64 {
    ns as f64 / 1000.0
}

fn find<'a>(cases: &'a [CaseResult], transport: &str, size: usize, chain: usize) -> Option<&'a CaseResult> {
    cases.iter().find(|c| c.transport == transport && c.size_bytes == size && c.chain == chain)
}

fn ratio(a: Option<u64>, b: Option<u64>) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) if b > 0 => Some(a as f64 / b as f64),
        _ => None,
    }
}

/// End-to-end p50 of `case` over the `iox` case of the same size and chain.
pub fn e2e_ratio_vs_iox(case: &CaseResult, cases: &[CaseResult]) -> Option<f64> {
    let iox = find(cases, IOX, case.size_bytes, case.chain)?;
    ratio(case.e2e.map(|e| e.p50), iox.e2e.map(|e| e.p50))
}

/// The table as printed: one row per case (end to end, per-hop p50 values, losses).
pub fn render_table(cases: &[CaseResult]) -> String {
    let dash = || "-".to_string();
    let f1 = |v: Option<f64>| v.map_or_else(dash, |v| format!("{v:.1}"));
    let mut t = String::new();
    let _ = writeln!(
        t,
        "{:<15} {:>8} {:>5} {:>6} {:>4} | {:>9} {:>9} {:>9} {:>9} | {:>9} | {:<32} | {:>6} | {:>8}",
        "transport",
        "size",
        "chain",
        "n",
        "lost",
        "e2e p50",
        "p99",
        "p99.9",
        "max",
        "hop p50",
        "p50 of each hop (µs)",
        "wakes",
        "vs iox"
    );
    let _ = writeln!(t, "{}", "-".repeat(150));
    for c in cases {
        let e = |f: fn(&Summary) -> u64| f1(c.e2e.as_ref().map(|s| us(f(s))));
        let each: Vec<String> = c.hops.iter().map(|h| h.map_or_else(dash, |h| format!("{:.0}", us(h.p50)))).collect();
        let mut each = each.join(" ");
        if each.len() > 32 {
            each.truncate(29);
            each.push_str("...");
        }
        let _ = writeln!(
            t,
            "{:<15} {:>8} {:>5} {:>6} {:>4} | {:>9} {:>9} {:>9} {:>9} | {:>9} | {:<32} | {:>6} | {:>8}",
            c.transport,
            size_label(c.size_bytes),
            c.chain,
            c.e2e.map_or(0, |e| e.count),
            c.lost,
            e(|s| s.p50),
            e(|s| s.p99),
            e(|s| s.p999),
            e(|s| s.max),
            f1(c.hop_p50().map(us)),
            each,
            c.wakeups_per_message.map_or_else(dash, |w| format!("{w:.2}")),
            e2e_ratio_vs_iox(c, cases).map_or_else(dash, |r| format!("{r:.1}x")),
        );
    }
    t
}

/// One comparison against a goal.
#[derive(Debug, Clone, PartialEq)]
pub struct GoalCheck {
    /// What is compared.
    pub what: String,
    /// The measured ratio.
    pub ratio: f64,
    /// The goal.
    pub goal: f64,
    /// Whether higher is better (`ratio >= goal`) or lower (`ratio <= goal`).
    pub higher_is_better: bool,
}

impl GoalCheck {
    /// Whether the goal is met.
    pub fn met(&self) -> bool {
        if self.higher_is_better { self.ratio >= self.goal } else { self.ratio <= self.goal }
    }
}

/// The goals of the benchmark, as far as the run measured them: round trip (chain 1) at 8 MiB
/// against both socket baselines, and the runtime's hop against bare iceoryx2 (median of the hop
/// p50 values, at every size and chain measured).
pub fn goal_checks(cases: &[CaseResult]) -> Vec<GoalCheck> {
    let mut out = Vec::new();
    if let Some(iox) = find(cases, IOX, GOAL_SIZE, 1) {
        for (name, goal) in [(SOCKET_RAW, GOAL_VS_RAW), (SOCKET_BINCODE, GOAL_VS_BINCODE)] {
            if let Some(r) =
                find(cases, name, GOAL_SIZE, 1).and_then(|c| ratio(c.e2e.map(|e| e.p50), iox.e2e.map(|e| e.p50)))
            {
                out.push(GoalCheck {
                    what: format!("round trip at 8 MiB, {name} / iox (p50)"),
                    ratio: r,
                    goal,
                    higher_is_better: true,
                });
            }
        }
    }
    for c in cases.iter().filter(|c| c.transport == IOX) {
        if let Some(r) = find(cases, IOX_BARE, c.size_bytes, c.chain).and_then(|b| ratio(c.hop_p50(), b.hop_p50())) {
            out.push(GoalCheck {
                what: format!("hop at {} through {} relay(s), iox / iox-bare (p50)", size_label(c.size_bytes), c.chain),
                ratio: r,
                goal: GOAL_RUNTIME_OVER_BARE,
                higher_is_better: false,
            });
        }
    }
    out
}

/// Ratio lines (every baseline against iox at every size and chain) and the goal lines.
pub fn render_ratios(cases: &[CaseResult]) -> String {
    let mut t = String::new();
    let mut keys: Vec<(usize, usize)> = cases.iter().map(|c| (c.size_bytes, c.chain)).collect();
    keys.dedup();
    keys.sort_unstable();
    keys.dedup();
    for (size, chain) in keys {
        let parts: Vec<String> = cases
            .iter()
            .filter(|c| c.size_bytes == size && c.chain == chain && c.transport != IOX)
            .filter_map(|c| e2e_ratio_vs_iox(c, cases).map(|r| format!("{} {r:.2}x", c.transport)))
            .collect();
        if !parts.is_empty() {
            let _ = writeln!(
                t,
                "{} through {chain} relay(s), end-to-end p50 / iox: {}",
                size_label(size),
                parts.join(", ")
            );
        }
    }
    for g in goal_checks(cases) {
        let cmp = if g.higher_is_better { ">=" } else { "<=" };
        let verdict = if g.met() { "met" } else { "NOT met" };
        let _ = writeln!(t, "goal: {}: {:.2}x (goal {cmp} {}x): {verdict}", g.what, g.ratio, g.goal);
    }
    t
}

/// CSV header line.
pub const CSV_HEADER: &str =
    "size_bytes,transport,chain,hop,count,p50_us,p99_us,p999_us,max_us,lost,bad,p50_vs_iox,wakeups_per_message";

/// Every case as CSV: one row per hop (`hop` = 1..=chain+1) and one end-to-end row (`hop` = `e2e`).
pub fn render_csv(cases: &[CaseResult]) -> String {
    let f = |v: Option<f64>| v.map_or_else(String::new, |v| format!("{v:.3}"));
    let mut t = String::from(CSV_HEADER);
    t.push('\n');
    for c in cases {
        let iox = find(cases, IOX, c.size_bytes, c.chain);
        let mut row = |hop: String, s: Option<Summary>, vs: Option<f64>| {
            let g = |g: fn(&Summary) -> u64| f(s.as_ref().map(|s| us(g(s))));
            let _ = writeln!(
                t,
                "{},{},{},{},{},{},{},{},{},{},{},{},{}",
                c.size_bytes,
                c.transport,
                c.chain,
                hop,
                s.map_or(0, |s| s.count),
                g(|s| s.p50),
                g(|s| s.p99),
                g(|s| s.p999),
                g(|s| s.max),
                c.lost,
                c.bad,
                f(vs),
                f(c.wakeups_per_message),
            );
        };
        for (k, h) in c.hops.iter().enumerate() {
            let vs =
                iox.and_then(|i| i.hops.get(k).copied().flatten()).and_then(|i| ratio(h.map(|h| h.p50), Some(i.p50)));
            row((k + 1).to_string(), *h, vs);
        }
        row("e2e".into(), c.e2e, e2e_ratio_vs_iox(c, cases));
    }
    t
}

/// Writes [`render_csv`] to `path`.
pub fn write_csv(path: &Path, cases: &[CaseResult]) -> anyhow::Result<()> {
    std::fs::write(path, render_csv(cases)).with_context(|| format!("cannot write {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(p50: u64) -> Summary {
        Summary { count: 100, p50, p99: 2 * p50, p999: 3 * p50, max: 4 * p50 }
    }

    fn case(t: &str, size: usize, hop: u64) -> CaseResult {
        CaseResult {
            transport: t.into(),
            size_bytes: size,
            chain: 1,
            hops: vec![Some(s(hop)), Some(s(hop))],
            e2e: Some(s(2 * hop)),
            samples_wanted: 100,
            ..Default::default()
        }
    }

    #[test]
    fn goals_compare_round_trips_at_8_mib_and_runtime_hops_against_bare_iceoryx2() {
        let cases = vec![
            case(IOX, GOAL_SIZE, 10_000),
            case(IOX_BARE, GOAL_SIZE, 9_000),
            case(SOCKET_RAW, GOAL_SIZE, 50_000),
            case(SOCKET_BINCODE, GOAL_SIZE, 300_000),
        ];
        let goals = goal_checks(&cases);
        assert_eq!(goals.len(), 3);
        assert!(!goals[0].met(), "raw 5x must miss the 8x goal: {goals:?}");
        assert!((goals[0].ratio - 5.0).abs() < 1e-9);
        assert!(goals[1].met(), "bincode 30x meets 25x");
        assert!(goals[2].met() && (goals[2].ratio - 10.0 / 9.0).abs() < 1e-9);
        let text = render_ratios(&cases);
        assert!(text.contains("NOT met") && text.contains("socket-raw 5.00x"), "{text}");

        let csv = render_csv(&cases);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 1 + 4 * 3, "{csv}");
        assert!(
            lines
                .iter()
                .any(|l| l.starts_with("8388608,socket-raw,1,e2e,100,100.000,200.000,300.000,400.000,0,0,5.000,")),
            "{csv}"
        );
        let table = render_table(&cases);
        assert!(table.contains("8 MiB") && table.contains("30.0x"), "{table}");
    }
}

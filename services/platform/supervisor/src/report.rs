//! What a run reports: `summary.json` (processes, latency per hop and end to end, plus the parts
//! other stages write to `<out>/parts/<process>.json`), `latency.csv`, and the printed summary.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::Duration;

use hdrhistogram::Histogram;
use pipeline_runtime::StatsReport;
use pipeline_runtime::stats::{LatencySummary, histogram_from_bytes, new_histogram};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::outcome::{EndReason, ExitInfo, Usage};
use crate::plan::Plan;

/// One process as the report sees it.
pub struct ProcessRow<'a> {
    /// Name.
    pub name: &'a str,
    /// Kind.
    pub kind: &'a str,
    /// Final state.
    pub state: &'a str,
    /// Why it failed, if it did.
    pub failure: Option<&'a str>,
    /// Restarts.
    pub restarts: u32,
    /// How its last instance ended.
    pub last_exit: Option<&'a ExitInfo>,
    /// Latest statistics of each instance (by pid).
    pub reports: Vec<&'a StatsReport>,
    /// CPU time and peak memory of its ended instances.
    pub usage: Usage,
}

/// What each process's outputs did not deliver, summed over its instances: (publisher,
/// service, consumer) → messages.
pub fn undelivered(rows: &[ProcessRow<'_>]) -> BTreeMap<(String, String, String), u64> {
    let mut out = BTreeMap::new();
    for row in rows {
        for report in &row.reports {
            for port in report.ports.iter().filter(|p| !p.input) {
                for (consumer, n) in &port.undelivered_by {
                    if *n > 0 {
                        *out.entry((row.name.to_string(), port.service.clone(), consumer.clone())).or_default() += *n;
                    }
                }
            }
        }
    }
    out
}

/// What each process's stages dropped (of their inputs, or meant for their outputs), summed over its instances: (process,
/// service, reason) → messages.
pub fn dropped(rows: &[ProcessRow<'_>]) -> BTreeMap<(String, String, String), u64> {
    let mut out = BTreeMap::new();
    for row in rows {
        for report in &row.reports {
            for port in &report.ports {
                for (reason, n) in &port.dropped_by {
                    if *n > 0 {
                        *out.entry((row.name.to_string(), port.service.clone(), reason.clone())).or_default() += *n;
                    }
                }
            }
        }
    }
    out
}

/// Hop latency over all inputs of one report.
pub fn hop_summary(report: &StatsReport) -> Option<LatencySummary> {
    let mut h = new_histogram();
    for p in report.ports.iter().filter(|p| p.input) {
        h.add(histogram_from_bytes(&p.hop).ok()?).ok()?;
    }
    Some(LatencySummary::of(&h))
}

/// End-to-end latency (from the oldest sensor input to receive) over all inputs of one report:
/// for the last stages of the pipeline, the latency of the whole chain up to them.
pub fn e2e_summary(report: &StatsReport) -> Option<LatencySummary> {
    let mut h = new_histogram();
    for p in report.ports.iter().filter(|p| p.input) {
        h.add(histogram_from_bytes(&p.e2e).ok()?).ok()?;
    }
    Some(LatencySummary::of(&h))
}

/// Latency tables merged over every instance: key `"<service> -> <process>"`.
pub fn merged_latency(rows: &[ProcessRow<'_>]) -> (BTreeMap<String, LatencySummary>, BTreeMap<String, LatencySummary>) {
    let mut hop: BTreeMap<String, Histogram<u64>> = BTreeMap::new();
    let mut e2e: BTreeMap<String, Histogram<u64>> = BTreeMap::new();
    for row in rows {
        for report in &row.reports {
            for port in report.ports.iter().filter(|p| p.input) {
                let key = format!("{} -> {}", port.service, row.name);
                for (table, bytes) in [(&mut hop, &port.hop), (&mut e2e, &port.e2e)] {
                    match histogram_from_bytes(bytes) {
                        Ok(h) => {
                            let _ = table.entry(key.clone()).or_insert_with(new_histogram).add(h);
                        }
                        Err(e) => tracing::warn!(process = row.name, "{e}"),
                    }
                }
            }
        }
    }
    let f = |t: BTreeMap<String, Histogram<u64>>| t.into_iter().map(|(k, h)| (k, LatencySummary::of(&h))).collect();
    (f(hop), f(e2e))
}

/// What the supervisor itself writes into summary.json; the stages' parts are merged into it.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct SupervisorPart {
    /// The run as a whole.
    pub run: RunInfo,
    /// Each process by name.
    pub processes: BTreeMap<String, ProcessReport>,
    /// Messages a publisher sent that a consumer never received, by (publisher, service, consumer).
    pub undelivered: Vec<Undelivered>,
    /// Messages a process received and dropped, by (process, service, reason).
    pub dropped: Vec<Dropped>,
    /// Latency per hop and end to end, from the processes' histograms, ms.
    pub latency_ms: LatencyTables,
}

/// `run`: how the run went.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RunInfo {
    /// The config file.
    pub config: PathBuf,
    /// Why it ended.
    pub end_reason: EndReason,
    /// The supervisor's exit code.
    pub exit_code: u8,
    /// The run's wall time, from the start to the summary, s.
    pub elapsed_s: f64,
    /// The configured bound `run.duration_s` (0: none), s; not the run's length (`elapsed_s`).
    pub duration_s: f64,
    /// The run's iceoryx2 prefix.
    pub iceoryx_prefix: String,
    /// The run's iceoryx2 root path.
    pub iceoryx_root: PathBuf,
    /// Processes that failed, with why (`name (why)`).
    pub failed_processes: Vec<String>,
    /// Processes whose streams the supervisor ended for them because they failed for good.
    pub streams_ended_for_failure: BTreeSet<String>,
}

/// `processes.<name>`: one process over all its instances.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ProcessReport {
    /// Its kind.
    pub kind: String,
    /// Its final state (`done`, `failed`, `stopped`, ...).
    pub state: String,
    /// Why it failed, if it did.
    pub failure: Option<String>,
    /// How often the supervisor restarted it.
    pub restarts: u32,
    /// Instances that reported statistics (1 + restarts that came up).
    pub instances: usize,
    /// Messages its outputs sent that some consumer never received.
    pub undelivered: u64,
    /// Messages it received and dropped.
    pub dropped: u64,
    /// How its last instance ended.
    pub last_exit: Option<ExitInfo>,
    /// Messages received, over every input.
    pub messages_in: u64,
    /// Messages sent, over every output.
    pub messages_out: u64,
    /// User + system CPU time of its ended instances, s.
    pub cpu_s: f64,
    /// The largest resident set size of any instance, MiB.
    pub peak_rss_mib: f64,
    /// The resident set size when it reported ready, before any data, MiB.
    pub ready_rss_mib: f64,
    /// Upstream processes that failed for good while it ran (written by the process itself).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub upstream_failed: Option<Vec<String>>,
}

/// One (publisher, service, consumer) with messages lost.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Undelivered {
    /// The publishing process.
    pub publisher: String,
    /// The service.
    pub service: String,
    /// The consumer that did not receive them.
    pub consumer: String,
    /// How many.
    pub messages: u64,
}

/// One (process, service, reason) with messages dropped.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Dropped {
    /// The process that dropped them.
    pub process: String,
    /// The service they came on.
    pub service: String,
    /// Why.
    pub reason: String,
    /// How many.
    pub messages: u64,
}

/// `latency_ms`: the processes' latency histograms merged, ms.
#[derive(Debug, Clone, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LatencyTables {
    /// From a message's publication to its reception, by `<service> -> <process>`.
    pub hops: BTreeMap<String, LatencySummary>,
    /// From the origin of the data a message carries to its reception, by `<service> -> <process>`.
    pub end_to_end: BTreeMap<String, LatencySummary>,
}

/// Builds summary.json: the supervisor's part, with every stage's part in `<out>/parts` merged in.
pub fn summary(
    plan: &Plan,
    rows: &[ProcessRow<'_>],
    end: &EndReason,
    exit_code: u8,
    elapsed: Duration,
    failed_streams: &BTreeSet<String>,
) -> Value {
    let part = supervisor_part(plan, rows, end, exit_code, elapsed, failed_streams);
    let mut out = serde_json::to_value(&part).unwrap_or_else(|e| {
        tracing::error!("the supervisor's summary does not serialise: {e}");
        json!({})
    });
    let own_dirs: BTreeSet<String> =
        plan.processes.iter().filter(|p| p.config.out_dir.is_some()).map(|p| p.name.clone()).collect();
    merge_parts(&mut out, &plan.out_dir.join("parts"), &own_dirs);
    out
}

/// The supervisor's own part of summary.json.
pub fn supervisor_part(
    plan: &Plan,
    rows: &[ProcessRow<'_>],
    end: &EndReason,
    exit_code: u8,
    elapsed: Duration,
    failed_streams: &BTreeSet<String>,
) -> SupervisorPart {
    let processes = rows
        .iter()
        .map(|r| {
            let ports = || r.reports.iter().flat_map(|rep| rep.ports.iter());
            let counts: (u64, u64) =
                ports().fold((0, 0), |(i, o), p| if p.input { (i + p.count, o) } else { (i, o + p.count) });
            let report = ProcessReport {
                kind: r.kind.to_string(),
                state: r.state.to_string(),
                failure: r.failure.map(str::to_string),
                restarts: r.restarts,
                instances: r.reports.len(),
                undelivered: ports().map(|p| p.undelivered).sum(),
                dropped: ports().flat_map(|p| p.dropped_by.iter()).map(|(_, n)| n).sum(),
                last_exit: r.last_exit.cloned(),
                messages_in: counts.0,
                messages_out: counts.1,
                cpu_s: r.usage.cpu_s,
                peak_rss_mib: r.usage.peak_rss_mib,
                ready_rss_mib: r.usage.ready_rss_mib,
                upstream_failed: None,
            };
            (r.name.to_string(), report)
        })
        .collect();
    let (hops, end_to_end) = merged_latency(rows);
    let undelivered = undelivered(rows)
        .into_iter()
        .map(|((publisher, service, consumer), messages)| Undelivered { publisher, service, consumer, messages })
        .collect();
    let dropped = dropped(rows)
        .into_iter()
        .map(|((process, service, reason), messages)| Dropped { process, service, reason, messages })
        .collect();
    SupervisorPart {
        run: RunInfo {
            config: plan.config_path.clone(),
            end_reason: end.clone(),
            exit_code,
            elapsed_s: elapsed.as_secs_f64(),
            duration_s: plan.config.run.duration_s,
            iceoryx_prefix: plan.scope.prefix.clone(),
            iceoryx_root: plan.scope.root.clone(),
            failed_processes: rows.iter().filter_map(|r| r.failure.map(|why| format!("{} ({why})", r.name))).collect(),
            streams_ended_for_failure: failed_streams.clone(),
        },
        processes,
        undelivered,
        dropped,
        latency_ms: LatencyTables { hops, end_to_end },
    }
}

/// Merges every `<dir>/*.json` object into `out` (deep merge of objects; later keys win).
/// Merges every part in `dir` into `out`; the part of a process in `instances` (one with an
/// `out_dir` of its own) goes under `instances.<process>`, where it does not overwrite the keys
/// of another process of its kind.
fn merge_parts(out: &mut Value, dir: &Path, instances: &BTreeSet<String>) {
    let Ok(rd) = std::fs::read_dir(dir) else { return };
    let mut files: Vec<_> =
        rd.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| p.extension().is_some_and(|e| e == "json")).collect();
    files.sort();
    for f in files {
        match std::fs::read(&f)
            .map_err(|e| e.to_string())
            .and_then(|b| serde_json::from_slice::<Value>(&b).map_err(|e| e.to_string()))
        {
            Ok(v @ Value::Object(_)) => match f.file_stem().and_then(|n| n.to_str()).filter(|n| instances.contains(*n))
            {
                Some(name) => deep_merge(out, json!({ "instances": { name: v } })),
                None => deep_merge(out, v),
            },
            Ok(_) => tracing::warn!("{}: not a JSON object; not merged into summary.json", f.display()),
            Err(e) => tracing::warn!("{}: {e}; not merged into summary.json", f.display()),
        }
    }
}

fn deep_merge(a: &mut Value, b: Value) {
    match (a, b) {
        (Value::Object(a), Value::Object(b)) => {
            for (k, v) in b {
                deep_merge(a.entry(k).or_insert(Value::Null), v);
            }
        }
        (a, b) => *a = b,
    }
}

/// Writes summary.json and latency.csv into `out_dir`.
pub fn write(out_dir: &Path, summary: &Value) -> std::io::Result<()> {
    std::fs::create_dir_all(out_dir)?;
    std::fs::write(out_dir.join("summary.json"), serde_json::to_vec_pretty(summary)?)?;
    let mut csv = String::from("table,key,count,p50_ms,p99_ms,p999_ms,max_ms\n");
    for table in ["hops", "end_to_end"] {
        if let Some(Value::Object(m)) = summary["latency_ms"].get(table) {
            for (k, v) in m {
                csv.push_str(&format!(
                    "{table},\"{k}\",{},{},{},{},{}\n",
                    v["count"], v["p50"], v["p99"], v["p999"], v["max"]
                ));
            }
        }
    }
    std::fs::write(out_dir.join("latency.csv"), csv)
}

/// The short summary printed at the end of a run watched in a terminal (the live status block):
/// how it ended, the processes, the accuracy (ATE per estimate), what was lost, how many
/// warnings, and what was written where. The latency tables stay in summary.json, latency.csv
/// and run.log (the plain output, [`render`], prints them).
pub fn render_short(summary: &Value, out_dir: &Path, warnings: usize) -> String {
    let full = render(summary);
    // The run line, failures and the process table: everything before the latency tables.
    let mut s: String = full.lines().take_while(|l| !l.starts_with("hop latency")).map(|l| format!("{l}\n")).collect();
    if let Some(Value::Object(ate)) = summary.get("ate_m")
        && !ate.is_empty()
    {
        let parts: Vec<String> = ate.iter().filter_map(|(k, v)| v.as_f64().map(|m| format!("{k} {m:.3}"))).collect();
        s.push_str(&format!("accuracy, ATE m (against ground_truth.tum): {}\n", parts.join(" · ")));
    }
    let sum = |key: &str| -> (u64, usize) {
        let rows = summary[key].as_array().map(Vec::as_slice).unwrap_or_default();
        (rows.iter().filter_map(|r| r["messages"].as_u64()).sum(), rows.len())
    };
    let ((undelivered, u_rows), (dropped, d_rows)) = (sum("undelivered"), sum("dropped"));
    if undelivered + dropped == 0 {
        s.push_str("lost: nothing (no message undelivered or dropped)\n");
    } else {
        s.push_str(&format!(
            "LOST: {undelivered} message(s) undelivered ({u_rows} service/consumer pair(s)), {dropped} dropped \
             ({d_rows} reason(s)): summary.json `undelivered` and `dropped`\n"
        ));
    }
    s.push_str(&match warnings {
        0 => "warnings: none\n".to_string(),
        n => format!("warnings: {n} (WARN lines in run.log)\n"),
    });
    let mut files: Vec<String> = std::fs::read_dir(out_dir)
        .map(|d| {
            d.filter_map(Result::ok)
                .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    files.sort();
    s.push_str(&format!("outputs in {} ({} files): {}\n", out_dir.display(), files.len(), files.join(", ")));
    s
}

/// The human-readable summary printed at the end of a run.
pub fn render(summary: &Value) -> String {
    let mut s = String::new();
    let run = &summary["run"];
    s.push_str(&format!(
        "run ended: {} after {:.1} s (exit code {})\n",
        run["end_reason"].to_string().trim_matches('"'),
        run["elapsed_s"].as_f64().unwrap_or(0.0),
        run["exit_code"]
    ));
    if let Some(Value::Array(failed)) = run.get("failed_processes")
        && !failed.is_empty()
    {
        for f in failed {
            s.push_str(&format!("FAILED: {}\n", f.as_str().unwrap_or("?")));
        }
    }
    s.push_str(&format!(
        "{:<20} {:<9} {:>8} {:>10} {:>10}  last exit\n",
        "process", "state", "restarts", "msgs in", "msgs out"
    ));
    if let Some(Value::Object(ps)) = summary.get("processes") {
        for (name, p) in ps {
            s.push_str(&format!(
                "{:<20} {:<9} {:>8} {:>10} {:>10}  {}\n",
                name,
                p["state"].as_str().unwrap_or("?"),
                p["restarts"].to_string(),
                p["messages_in"].to_string(),
                p["messages_out"].to_string(),
                p["last_exit"]["description"].as_str().unwrap_or("-")
            ));
        }
    }
    if let Some(Value::Object(instances)) = summary.get("instances")
        && !instances.is_empty()
    {
        let names: Vec<&str> = instances.keys().map(String::as_str).collect();
        s.push_str(&format!(
            "processes with an out_dir of their own (their files there, their summaries under summary.json \
             `instances`): {}\n",
            names.join(", ")
        ));
    }
    for (title, table) in
        [("hop latency (service -> process)", "hops"), ("end-to-end latency (since sensor input)", "end_to_end")]
    {
        if let Some(Value::Object(m)) = summary["latency_ms"].get(table)
            && !m.is_empty()
        {
            s.push_str(&format!("{title:<44} {:>9} {:>9} {:>9} {:>9}\n", "count", "p50 ms", "p99 ms", "max ms"));
            for (k, v) in m {
                s.push_str(&format!(
                    "  {:<42} {:>9} {:>9.3} {:>9.3} {:>9.3}\n",
                    k,
                    v["count"].to_string(),
                    v["p50"].as_f64().unwrap_or(0.0),
                    v["p99"].as_f64().unwrap_or(0.0),
                    v["max"].as_f64().unwrap_or(0.0)
                ));
            }
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_of_processes_with_their_own_out_dir_go_under_instances() {
        let dir = tempfile::tempdir().unwrap();
        let part = |name: &str, clouds: u64| {
            let v = json!({ "octree_mapper": { "counters": { "clouds_inserted": clouds } } });
            std::fs::write(dir.path().join(format!("{name}.json")), v.to_string()).unwrap();
        };
        part("map", 7);
        part("map_r1", 3);
        part("map_r2", 4);
        let mut out = json!({ "run": {} });
        let instances: BTreeSet<String> = ["map_r1".to_string(), "map_r2".to_string()].into();
        merge_parts(&mut out, dir.path(), &instances);
        assert_eq!(out["octree_mapper"]["counters"]["clouds_inserted"], 7, "{out}");
        assert_eq!(out["instances"]["map_r1"]["octree_mapper"]["counters"]["clouds_inserted"], 3, "{out}");
        assert_eq!(out["instances"]["map_r2"]["octree_mapper"]["counters"]["clouds_inserted"], 4, "{out}");
        for s in [render_short(&out, dir.path(), 0), render(&out)] {
            assert!(s.contains("their summaries under summary.json `instances`): map_r1, map_r2"), "{s}");
        }
    }

    #[test]
    fn the_short_summary_gives_the_accuracy_what_was_lost_and_the_files_but_no_latency_tables() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("map.bt"), b"x").unwrap();
        std::fs::create_dir(dir.path().join("parts")).unwrap();
        let summary = serde_json::json!({
            "run": { "end_reason": "end_of_stream", "elapsed_s": 42.0, "duration_s": 600.0, "exit_code": 0 },
            "processes": {},
            "ate_m": { "fused": 0.16036, "buoy": 0.2093 },
            "undelivered": [ { "publisher": "a", "service": "s", "consumer": "b", "messages": 3 } ],
            "dropped": [],
            "latency_ms": { "hops": { "s -> b": { "count": 1, "p50": 1.0, "p99": 1.0, "max": 1.0 } } },
        });
        let s = render_short(&summary, dir.path(), 2);
        assert!(s.contains("buoy 0.209 · fused 0.160"), "{s}");
        assert!(s.contains("LOST: 3 message(s) undelivered"), "{s}");
        assert!(s.contains("warnings: 2"), "{s}");
        assert!(s.contains("(1 files): map.bt"), "{s}");
        assert!(!s.contains("hop latency") && render(&summary).contains("hop latency"), "{s}");
    }
}

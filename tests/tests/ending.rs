//! Runs that end cleanly whatever happens: a source that fails for good ends the run (its
//! consumers finish with what they got, exit code 1 naming it), and a real data file with a few
//! lines out of time order (under another run's prefix) is replayed, not refused.

use std::path::Path;
use std::time::Duration;

use crate::summary_schema::part;
use pipeline_tests::TestRun;

const LONG: Duration = Duration::from_secs(150);

fn plaza2_dir() -> String {
    format!("{}/../algorithms/datasets/data/plaza2", env!("CARGO_MANIFEST_DIR"))
}

/// The buoy EKF on a Plaza replay from `dir` (files under `prefix`), ingest restarted on failure.
fn buoy_on_replay(dir: &Path, restart: &str) -> String {
    format!(
        r#"
[processes.buoy]
kind = "buoy_ekf"
[processes.buoy.settings.ekf]
mode = "planar"
buoys = [
    {{ id = 0, position_m = [-33.620537, 26.967797, 0.0] }},
    {{ id = 1, position_m = [-68.926537, 18.377797, 0.0] }},
    {{ id = 5, position_m = [1.709463, -5.812203, 0.0] }},
    {{ id = 6, position_m = [-37.580537, 69.227797, 0.0] }},
]

[processes.ingest]
kind = "ingest"
after = ["buoy"]
{restart}
[processes.ingest.settings]
source = "plaza2"
real_time_factor = 0.0
[processes.ingest.settings.plaza2]
dir = "{}"
"#,
        dir.display()
    )
}

/// Copies the Plaza 2 files into `to` under `prefix`, passing each file's text through `edit`.
fn copy_run(to: &Path, prefix: &str, edit: impl Fn(&str, String) -> String) {
    for suffix in ["DR.txt", "TD.txt", "GT.txt", "TL.txt"] {
        let text = std::fs::read_to_string(format!("{}/Plaza2_{suffix}", plaza2_dir())).unwrap();
        std::fs::write(to.join(format!("{prefix}{suffix}")), edit(suffix, text)).unwrap();
    }
}

#[test]
fn a_source_that_fails_for_good_ends_the_run_and_its_consumers_finish_with_what_they_got() {
    let mut run = TestRun::new("srcfail");
    let data = tempfile::tempdir().unwrap();
    // An unreadable line: the replay refuses the file (only unreadable data is an error).
    copy_run(data.path(), "Plaza2_", |suffix, text| {
        if suffix == "TD.txt" { text.replacen('\n', "\n3152.5 2 1 abc\n", 1) } else { text }
    });
    let procs = buoy_on_replay(data.path(), "restart = \"on-failure\"\nmax_restarts = 1\nbackoff_initial_s = 0.05");
    let cfg = run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"buoy\"]\nduration_s = 120", &procs);
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(LONG).expect("the run ends although its source failed for good");
    let log = run.log();
    assert_eq!(status.code(), Some(1), "a failed process makes the run fail:\n{log}");
    assert!(log.contains("Plaza2_TD.txt:2: column 4: `abc` is not a number"), "the error names file:line:\n{log}");
    assert!(log.contains("`ingest` failed for good"), "the consumer says why its input ended:\n{log}");
    let s = run.summary();
    let sup: supervisor::report::SupervisorPart = part(&s);
    assert_eq!(sup.run.end_reason, supervisor::outcome::EndReason::EndOfStream, "{s:#}");
    assert_eq!(sup.processes["ingest"].state, "FAILED", "{s:#}");
    assert_eq!(sup.processes["ingest"].restarts, 1, "{s:#}");
    let failed = &sup.run.failed_processes;
    assert!(failed.len() == 1 && failed[0].starts_with("ingest ("), "{s:#}");
    assert_eq!(sup.run.streams_ended_for_failure.iter().collect::<Vec<_>>(), ["ingest"], "{s:#}");
    // The consumer finished normally and wrote its part (no fixes: nothing came).
    assert_eq!(sup.processes["buoy"].last_exit.as_ref().and_then(|e| e.code), Some(0), "{s:#}");
    assert_eq!(part::<buoy_ekf_stage::summary::BuoyEkfPart>(&s).buoy_ekf.fixes, 0, "{s:#}");
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn a_replay_with_lines_out_of_time_order_under_another_prefix_runs_counts_and_warns_once() {
    let mut run = TestRun::new("warts");
    let data = tempfile::tempdir().unwrap();
    // Two range lines swapped (as in a second CMU Plaza run's file): one line is out of order.
    copy_run(data.path(), "Plaza1_", |suffix, text| {
        if suffix != "TD.txt" {
            return text;
        }
        let mut lines: Vec<&str> = text.lines().collect();
        lines.swap(100, 101);
        lines.join("\n") + "\n"
    });
    let procs = buoy_on_replay(data.path(), "restart = \"never\"");
    let s = run.run_to_end("end = \"end_of_stream\"\nend_of_stream_from = [\"buoy\"]\nduration_s = 200", &procs, LONG);
    let log = run.log();
    let ingest: ingest_stage::summary::IngestPart = part(&s);
    assert_eq!(ingest.ingest.data_warts.get("lines_out_of_time_order"), Some(&1), "{s:#}");
    let warnings: Vec<&str> = log.lines().filter(|l| l.contains("out of time order")).collect();
    assert_eq!(warnings.len(), 1, "one warning per file:\n{log}");
    assert!(warnings[0].contains("Plaza1_TD.txt:102: time"), "{}", warnings[0]);
    // Nothing else is lost: every range is replayed and the filter meets its goal as on the
    // original file.
    assert_eq!(ingest.ingest.messages.buoy_ranges, 1816, "{s:#}");
    let buoy: buoy_ekf_stage::summary::BuoyEkfPart = part(&s);
    let ate = buoy.ate_m.and_then(|a| a.buoy_ekf).expect("ate_m.buoy_ekf");
    assert!(ate <= 0.5, "buoy EKF ATE {ate} m: {s:#}");
}

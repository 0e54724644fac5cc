//! The supervisor with real processes: data flow, stop on signal, restarts, crash loops,
//! heartbeat deadline, orphans and stale resources. Each test has its own prefix and root path.

use std::time::Duration;

use nix::sys::signal::Signal;
use pipeline_tests::{TestRun, process_alive};
use supervisor::outcome::EndReason;

const PAIR: &str = r#"
[processes.consumer]
kind = "test_consumer"
[processes.consumer.settings]
expect_points = 20000

[processes.producer]
kind = "test_producer"
after = ["consumer"]
backoff_initial_s = 0.05
[processes.producer.settings]
points = 20000
rate_hz = 50.0
"#;

const LONG: Duration = Duration::from_secs(20);

fn consumer_counters(run: &TestRun) -> testkit::ConsumerCounters {
    crate::summary_schema::part::<testkit::ConsumerPart>(&run.summary()).test_consumer
}

/// The supervisor's part of summary.json, as the supervisor wrote it.
fn report(summary: &serde_json::Value) -> supervisor::report::SupervisorPart {
    crate::summary_schema::part(summary)
}

#[test]
fn data_flows_and_sigterm_stops_everything_leaving_no_shared_memory() {
    let mut run = TestRun::new("sigterm");
    let cfg = run.write_config("end = \"signal\"", PAIR);
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("ready after", 2, LONG);
    run.wait_for_log("hop p50", 1, LONG); // the consumer reports latency: data is flowing
    let pids: Vec<i32> = ["consumer", "producer"].iter().flat_map(|n| run.started_pids(n)).collect();
    assert_eq!(pids.len(), 2, "{}", run.log());
    run.signal_supervisor(Signal::SIGTERM);
    let status = run.wait_supervisor(LONG).expect("supervisor stops after SIGTERM");
    assert_eq!(status.code(), Some(143), "SIGTERM exit code; log:\n{}", run.log());
    for pid in pids {
        assert!(!process_alive(pid), "child {pid} survived the stop");
    }
    let s = run.summary();
    let sup = report(&s);
    for p in ["consumer", "producer"] {
        let process = &sup.processes[p];
        assert_eq!(process.restarts, 0);
        assert_eq!(process.last_exit.as_ref().and_then(|e| e.code), Some(0), "{p} stops cleanly on SIGTERM: {s:#}");
    }
    let c = consumer_counters(&run);
    assert!(c.frames_ok >= 5, "{c:?}");
    assert_eq!(c.frames_bad, 0, "{c:?}");
    let hop = &sup.latency_ms.hops["pipeline/sensors/cloud -> consumer"];
    assert!(hop.count >= 5, "{s:#}");
    assert!(hop.p50 > 0.0 && hop.p50 <= hop.max, "{hop:?}");
    assert!(sup.latency_ms.end_to_end["pipeline/sensors/cloud -> consumer"].count >= 5);
    assert!(run.out_dir().join("latency.csv").exists());
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");
}

#[test]
fn end_of_stream_ends_the_run_with_every_frame_verified() {
    let mut run = TestRun::new("eos");
    let procs = PAIR.replace("rate_hz = 50.0", "rate_hz = 100.0\nframes = 30");
    let cfg = run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"consumer\"]\nduration_s = 60", &procs);
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(LONG).expect("run ends on end of stream");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    let s = run.summary();
    let sup = report(&s);
    assert_eq!(sup.run.end_reason, EndReason::EndOfStream);
    // The configured bound as in the config, and the run's own wall time (30 frames at 100 Hz).
    assert_eq!(sup.run.duration_s, 60.0, "{:?}", sup.run);
    assert!(sup.run.elapsed_s > 0.2 && sup.run.elapsed_s < 60.0, "{:?}", sup.run);
    let c = consumer_counters(&run);
    assert_eq!(c.frames_ok, 30, "{c:?}");
    assert_eq!(c.frames_missed, 0, "{c:?}");
    assert_eq!(sup.processes["producer"].messages_out, 31, "30 clouds + end of stream: {s:#}");
    // The kernel's accounting of each reaped child: some CPU time, a resident set of a real
    // process (more than 1 MiB, less than 1 GiB for this pair).
    for p in ["producer", "consumer"] {
        let (cpu, rss) = (sup.processes[p].cpu_s, sup.processes[p].peak_rss_mib);
        assert!(cpu > 0.0 && cpu < 60.0, "{p} cpu_s {cpu}");
        assert!(rss > 1.0 && rss < 1024.0, "{p} peak_rss_mib {rss}");
        // Its memory when it reported ready, before any data: a real process's, at most the peak.
        let ready = sup.processes[p].ready_rss_mib;
        assert!(ready > 1.0 && ready <= rss, "{p} ready_rss_mib {ready}, peak {rss}");
    }
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn a_child_killed_with_sigkill_is_restarted_its_stale_resources_cleaned_and_data_flows_again() {
    let mut run = TestRun::new("kill9");
    let cfg = run.write_config("end = \"signal\"", PAIR);
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("ready after", 2, LONG);
    run.wait_for_log("hop p50", 1, LONG);
    let first = run.started_pids("producer")[0];
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(first), Signal::SIGKILL).unwrap();
    run.wait_for_log("restart 1/3", 1, LONG);
    run.wait_for_log("cleaned the iceoryx2 resources of 1 dead node", 1, LONG);
    run.wait_for_log("ready after", 3, LONG);
    let census = run.scope.node_census().unwrap();
    assert_eq!(census.dead, 0, "a dead node was left uncleaned");
    std::thread::sleep(Duration::from_millis(600)); // new frames after the restart
    run.signal_supervisor(Signal::SIGTERM);
    run.wait_supervisor(LONG).expect("stops");
    let s = run.summary();
    let producer = &report(&s).processes["producer"];
    assert_eq!((producer.restarts, producer.instances), (1, 2), "{s:#}");
    let c = consumer_counters(&run);
    let (ok, last) = (c.frames_ok, c.last_seq.expect("a sequence number was seen"));
    // The new instance numbers its clouds from 0 again: more good frames than the last sequence
    // number explains means frames of both instances arrived and verified.
    assert!(last >= 3 && ok > last + 1, "no data after the restart: {c:?}");
    assert_eq!(c.frames_bad, 0);
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn a_crash_looping_required_child_is_given_up_after_max_restarts_and_ends_the_run() {
    let mut run = TestRun::new("crashloop");
    let procs = PAIR
        .replace("backoff_initial_s = 0.05", "backoff_initial_s = 0.05\nmax_restarts = 2\nrequired = true")
        .replace("rate_hz = 50.0", "rate_hz = 50.0\nabort_after_frames = 2");
    let cfg = run.write_config("end = \"signal\"", &procs);
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(LONG).expect("the run ends once the required process is given up");
    assert_eq!(status.code(), Some(1), "{}", run.log());
    let s = run.summary();
    let sup = report(&s);
    let p = &sup.processes["producer"];
    assert_eq!(p.state, "FAILED", "{s:#}");
    assert_eq!(p.restarts, 2);
    assert_eq!(p.last_exit.as_ref().and_then(|e| e.signal), Some(6), "SIGABRT: {p:?}");
    assert!(p.failure.as_deref().unwrap_or_default().contains("gave up after 2 restart(s)"), "{p:?}");
    assert_eq!(sup.run.end_reason, EndReason::RequiredProcessFailed("producer".into()));
    assert_eq!(run.started_pids("producer").len(), 3);
    assert!(run.log().contains("gave up after 2 restart(s)"));
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn a_child_that_stops_heartbeating_is_killed_and_reported() {
    let mut run = TestRun::new("stall");
    let procs = PAIR
        .replace("backoff_initial_s = 0.05", "restart = \"never\"")
        .replace("rate_hz = 50.0", "rate_hz = 50.0\nstall_after_frames = 3");
    let cfg = run.write_config("end = \"signal\"\nheartbeat_timeout_s = 0.8", &procs);
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("no heartbeat for", 1, LONG);
    run.wait_for_log("not restarted", 1, LONG);
    run.signal_supervisor(Signal::SIGINT);
    let status = run.wait_supervisor(LONG).expect("stops on SIGINT");
    assert_eq!(status.code(), Some(130));
    let sup = report(&run.summary());
    let p = &sup.processes["producer"];
    assert_eq!(p.state, "FAILED", "{p:?}");
    let exit = p.last_exit.as_ref().expect("its exit");
    assert_eq!(exit.signal, Some(9), "{p:?}");
    assert!(exit.killed_because.as_deref().unwrap_or_default().starts_with("no heartbeat"), "{p:?}");
}

#[test]
fn sigkill_of_the_supervisor_leaves_no_orphan_and_the_next_run_cleans_the_stale_files() {
    let mut run = TestRun::new("orphans");
    let cfg = run.write_config("end = \"signal\"", PAIR);
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("ready after", 2, LONG);
    run.wait_for_log("hop p50", 1, LONG);
    let pids: Vec<i32> = ["consumer", "producer"].iter().flat_map(|n| run.started_pids(n)).collect();
    run.signal_supervisor(Signal::SIGKILL);
    run.wait_supervisor(LONG).expect("killed");
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    while pids.iter().any(|&p| process_alive(p)) && std::time::Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    for pid in &pids {
        assert!(!process_alive(*pid), "child {pid} outlived the killed supervisor");
    }
    assert!(!run.leftovers().is_empty(), "a killed run leaves stale files for the next one to clean");

    // A new run with the same prefix removes them at start and ends clean.
    let procs = PAIR.replace("rate_hz = 50.0", "rate_hz = 100.0\nframes = 5");
    let cfg = run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"consumer\"]", &procs);
    run.start_supervisor(&cfg, &[]);
    let status = run.wait_supervisor(LONG).expect("second run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    assert!(run.log().contains("stale iceoryx2 file(s)"), "{}", run.log());
    assert_eq!(consumer_counters(&run).frames_ok, 5);
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn a_child_restarted_after_its_upstream_ended_gets_the_end_of_stream_again() {
    // The consumer hangs (SIGSTOP) while the producer sends its clouds and its end of stream;
    // the supervisor kills it for missing heartbeats and restarts it. The dead instance never
    // read the end of stream, so the new one only ends the run if the supervisor replays it.
    let mut run = TestRun::new("eosreplay");
    let procs = PAIR.replace("rate_hz = 50.0", "rate_hz = 20.0\nframes = 30").replace(
        "[processes.consumer]\nkind = \"test_consumer\"",
        "[processes.consumer]\nkind = \"test_consumer\"\nrestart = \"on-failure\"\nbackoff_initial_s = 0.05",
    );
    let cfg = run.write_config(
        "end = \"end_of_stream\"\nend_of_stream_from = [\"consumer\"]\nduration_s = 60\nheartbeat_timeout_s = 2.0",
        &procs,
    );
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("ready after", 2, LONG);
    let consumer = run.started_pids("consumer")[0];
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(consumer), Signal::SIGSTOP).unwrap();
    run.wait_for_log("process=producer last_seq", 1, LONG); // the producer's end of stream
    let status = run.wait_supervisor(Duration::from_secs(40)).expect("the run ends");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    assert!(run.log().contains("replaying end of stream to the restarted process"), "{}", run.log());
    let s = run.summary();
    let sup = report(&s);
    assert_eq!(sup.run.end_reason, EndReason::EndOfStream, "{s:#}");
    assert_eq!(sup.processes["consumer"].restarts, 1, "{s:#}");
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new());
}

#[test]
fn status_shows_a_running_pipeline_and_then_that_it_ended() {
    let mut run = TestRun::new("status");
    let cfg = run.write_config("end = \"signal\"", PAIR);
    let status = |cfg: &std::path::Path| {
        std::process::Command::new(pipeline_tests::bin("supervisor"))
            .args(["status", "--config"])
            .arg(cfg)
            .output()
            .unwrap()
    };
    run.start_supervisor(&cfg, &[]);
    run.wait_for_log("ready after", 2, LONG);
    run.wait_for_log("hop p50", 1, LONG); // a status line with latency: status.json follows it
    let deadline = std::time::Instant::now() + LONG;
    let out = loop {
        let out = status(&cfg);
        if out.status.code() == Some(0) || std::time::Instant::now() > deadline {
            break out;
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(0), "{text}");
    assert!(text.contains(": running"), "{text}");
    for name in ["consumer", "producer"] {
        let line = text.lines().find(|l| l.starts_with(name)).unwrap_or_else(|| panic!("{name} missing:\n{text}"));
        assert!(line.contains("ready"), "{line}");
    }
    run.signal_supervisor(Signal::SIGTERM);
    run.wait_supervisor(LONG).expect("stops");
    let out = status(&cfg);
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(text.contains(": ended"), "{text}");
}

#[test]
fn a_closed_stdout_and_stderr_neither_kill_the_supervisor_nor_leave_shared_memory() {
    // As in `supervisor ... 2>&1 | head -3`: the reader of the log goes away at once. A failed log
    // write used to panic the supervisor (tracing-subscriber reported it with `eprintln!`), which
    // left the run's shared memory behind.
    let mut run = TestRun::new("closedpipe");
    let procs = PAIR.replace("rate_hz = 50.0", "rate_hz = 100.0\nframes = 30");
    let cfg = run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"consumer\"]\nduration_s = 60", &procs);
    let mut cmd = std::process::Command::new(pipeline_tests::bin("supervisor"));
    cmd.arg("--config")
        .arg(&cfg)
        .env("RUST_LOG", "info")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
    let child = run.spawn(&mut cmd);
    drop(child.stdout.take());
    drop(child.stderr.take());
    let end = std::time::Instant::now() + LONG;
    let status = loop {
        if let Some(s) = child.try_wait().expect("try_wait") {
            break s;
        }
        assert!(std::time::Instant::now() < end, "the supervisor did not end");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(status.code(), Some(0), "exit status {status}");
    assert_eq!(run.summary()["run"]["end_reason"], "end_of_stream");
    assert!(run.leftovers().is_empty(), "left behind: {:?}", run.leftovers());
}

/// In a terminal (a pseudo-terminal made by util-linux `script`), the run shows one live block:
/// the sources' progress as a bar, a row per process; the full log goes to `<out>/run.log`
/// (the supervisor's lines and every process's), not to the terminal; the summary follows.
#[test]
fn in_a_terminal_the_run_is_a_live_block_and_the_full_log_goes_to_run_log() {
    let run = TestRun::new("live");
    let procs = PAIR.replace("rate_hz = 50.0", "rate_hz = 40.0\nframes = 80");
    let cfg = run.write_config("end = \"end_of_stream\"\nend_of_stream_from = [\"consumer\"]\nduration_s = 60", &procs);
    // A narrow terminal (60 columns): every line of the block must fit, or the redraw in place
    // breaks (a wrapped line is not erased).
    let cmd =
        format!("stty cols 60 rows 30; {} --config {}", pipeline_tests::bin("supervisor").display(), cfg.display());
    let mut child = std::process::Command::new("script")
        .args(["-qefc", &cmd, "/dev/null"])
        .env("RUST_LOG", "info")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("util-linux `script` (package bsdutils) runs");
    let mut terminal = String::new();
    let reader = {
        let mut out = child.stdout.take().expect("stdout");
        std::thread::spawn(move || {
            let mut s = String::new();
            let _ = std::io::Read::read_to_string(&mut out, &mut s);
            s
        })
    };
    let end = std::time::Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(s) = child.try_wait().expect("try_wait") {
            break s;
        }
        if std::time::Instant::now() > end {
            let _ = child.kill();
            panic!("the run under `script` did not end in 60 s; log:\n{}", run.log());
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    terminal.push_str(&reader.join().expect("reader"));
    assert!(status.success(), "exit {status:?}; terminal:\n{terminal}");
    // The block: header, a row per process, the bar at 100 % of the producer's frames.
    for needle in ["process", "msg/s", "backlog", "dropped", "restarts", "producer", "consumer", "100% of the data"] {
        assert!(terminal.contains(needle), "`{needle}` not on the terminal:\n{terminal}");
    }
    let strip = |l: &str| {
        let mut out = String::new();
        let mut chars = l.chars();
        while let Some(c) = chars.next() {
            if c == '\x1b' {
                // An escape sequence, up to its final letter: a cursor move (not a colour, `m`)
                // ends the line.
                for c in chars.by_ref() {
                    if c.is_ascii_alphabetic() {
                        if c != 'm' {
                            out.push('\n');
                        }
                        break;
                    }
                }
            } else {
                out.push(c);
            }
        }
        out
    };
    // indicatif writes a line as wide as the terminal without a newline after it (the terminal
    // wraps): the bar's line is from its `[` to its ETA, the header from `process` to `restarts`.
    let mut bar_lines = 0;
    for line in terminal.split(['\n', '\r']).map(strip).flat_map(|l| l.lines().map(String::from).collect::<Vec<_>>()) {
        if let Some(end) = line.find("ETA ")
            && let Some(start) = line[..end].rfind('[')
        {
            let bar = &line[start..(end + 12).min(line.len())];
            assert!(bar.chars().count() <= 60, "the bar is wider than the 60-column terminal: {bar:?}");
            bar_lines += 1;
        }
        if let Some(start) = line.find("process")
            && let Some(end) = line.find("restarts")
        {
            assert!(line[start..end + 8].chars().count() <= 60, "the header is wider than 60 columns: {line:?}");
        }
    }
    assert!(bar_lines > 0, "no progress bar drawn:\n{terminal}");
    // The summary after it, and where the log is.
    let log_path = run.out_dir().join("run.log");
    assert!(terminal.contains(&format!("full log in {}", log_path.display())), "{terminal}");
    assert!(terminal.contains("outputs in"), "{terminal}");
    // The short summary: nothing lost, no warnings, the files written; the latency tables only
    // in run.log.
    for needle in ["lost: nothing", "warnings: none", "summary.json", "run.log"] {
        assert!(terminal.contains(needle), "`{needle}` not in the summary on the terminal:\n{terminal}");
    }
    assert!(!terminal.contains("hop latency"), "the latency tables on the terminal:\n{terminal}");
    // Log lines are not on the terminal (no warnings in this run) but in run.log, with the
    // processes' own lines.
    assert!(!terminal.contains(" INFO "), "log lines on the terminal:\n{terminal}");
    let log = std::fs::read_to_string(&log_path).expect("run.log");
    for needle in ["[supervisor]", "starting pipeline", "[producer]", "[consumer]", "end of stream", "hop latency"] {
        assert!(log.contains(needle), "`{needle}` not in run.log:\n{log}");
    }
    assert_eq!(report(&run.summary()).run.end_reason, EndReason::EndOfStream);
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new());
}

//! Reliability (issue #8): `kill -9` of each stage once during a run of the default pipeline. Every
//! stage is restarted by the supervisor, the run completes, the outputs are complete and valid, and
//! no iceoryx2 file of the run is left behind.
//!
//! The processes are exactly those of `config/default.toml`; the kills are spread over the run and
//! each waits for observable conditions (status.json: the previous victim restarted, ready and
//! working again), never for fixed times, so a slow or noisy machine only makes the test longer.

use std::path::Path;
use std::time::{Duration, Instant};

use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;
use pipeline_tests::TestRun;

/// The stages, in the order they are killed: the source first (its restart must resume, not
/// replay the mission), then each consumer.
const VICTIMS: [&str; 7] = ["ingest", "slam", "buoy", "sync", "fusion", "map", "monitor"];

/// One process's row of status.json.
#[derive(Debug, Clone)]
struct Row {
    state: String,
    restarts: u64,
    pid: Option<i32>,
    messages: u64,
}

fn status(run: &TestRun, name: &str) -> Option<Row> {
    let bytes = std::fs::read(run.out_dir().join("status.json")).ok()?;
    let s: serde_json::Value = serde_json::from_slice(&bytes).ok()?;
    let p = s["processes"].as_array()?.iter().find(|p| p["name"] == name)?;
    Some(Row {
        state: p["state"].as_str()?.to_string(),
        restarts: p["restarts"].as_u64()?,
        pid: p["pid"].as_i64().map(|p| p as i32),
        messages: p["messages"].as_u64().unwrap_or(0),
    })
}

/// Polls `cond` every 50 ms until it holds; panics with the log after `timeout`.
fn wait_until(run: &TestRun, what: &str, timeout: Duration, mut cond: impl FnMut() -> bool) {
    let end = Instant::now() + timeout;
    while Instant::now() < end {
        if cond() {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    panic!("timed out waiting for {what}; log:\n{}", run.log());
}

/// The mission's progress, %: the highest `progress N%` ingest logged (a restarted ingest goes on
/// from where the killed one was).
fn progress(run: &TestRun) -> u32 {
    run.log()
        .lines()
        .filter(|l| l.contains("[ingest] progress "))
        .filter_map(|l| l.split("progress ").nth(1)?.split('%').next()?.parse().ok())
        .max()
        .unwrap_or(0)
}

/// True once the supervisor logged an end of stream from `name`.
fn ended(run: &TestRun, name: &str) -> bool {
    let needle = format!("process={name} ");
    run.log().lines().any(|l| l.contains("[supervisor]") && l.contains("end of stream") && l.contains(&needle))
}

/// A TUM trajectory (read by the one reader, `geometry::tum::read_tum`) whose stamps never go
/// back (and strictly increase when `strict`; `buoy_ekf.tum` has an estimate after an odometry
/// input and after a range message of the same stamp).
fn read_tum(path: &Path, strict: bool) -> Vec<(f64, nalgebra::Isometry3<f64>)> {
    let rows = geometry::tum::read_tum(path).unwrap_or_else(|e| panic!("{e}"));
    for (i, w) in rows.windows(2).enumerate() {
        let (prev, t) = (w[0].0, w[1].0);
        assert!(
            t > prev || (!strict && t == prev),
            "{}: pose {}: stamp {t} after {prev} (replayed data?)",
            path.display(),
            i + 2
        );
    }
    rows
}

#[test]
fn kill_9_of_each_stage_once_is_survived_with_complete_outputs() {
    let _heavy = pipeline_tests::heavy();
    let path = format!("{}/../config/default.toml", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).expect("config/default.toml");
    let config: toml::Table = text.parse().expect("valid TOML");
    let run_table = config["run"].as_table().expect("[run]");
    let mut processes = config["processes"].as_table().expect("[processes]").clone();
    for name in VICTIMS {
        assert!(processes.contains_key(name), "config/default.toml has no process `{name}`");
    }
    // Every stage is restarted after a kill (SIGKILL is a failure for "on-failure" too).
    for (_, p) in processes.iter_mut() {
        p.as_table_mut().expect("process table").insert("restart".into(), "on-failure".into());
    }
    // Progress every second, to spread the kills finely over the mission.
    let ingest = processes["ingest"].as_table_mut().expect("ingest table");
    let settings = ingest.entry("settings").or_insert_with(|| toml::Table::new().into());
    let settings = settings.as_table_mut().expect("settings table");
    settings.insert("progress_interval_s".into(), 1.0.into());
    // Two of the mission's four survey legs: every kill still lands mid-run, in half the time.
    let sim = settings.entry("sim").or_insert_with(|| toml::Table::new().into());
    let mission = sim.as_table_mut().expect("sim table").entry("mission").or_insert_with(|| toml::Table::new().into());
    mission.as_table_mut().expect("mission table").insert("legs".into(), 2.into());
    let processes = toml::to_string(&toml::Table::from_iter([("processes".to_string(), processes.into())]))
        .expect("processes as TOML");
    let run_extra = format!(
        "end = {}\nend_of_stream_from = {}\nduration_s = 1200",
        run_table["end"], run_table["end_of_stream_from"]
    );
    let mut run = TestRun::new("kill9");
    let cfg = run.write_config(&run_extra, &processes);
    let t0 = Instant::now();
    run.start_supervisor(&cfg, &[]);
    let minute = Duration::from_secs(60);
    wait_until(&run, "every process ready", 3 * minute, || {
        VICTIMS.iter().all(|n| status(&run, n).is_some_and(|r| r.state == "ready"))
    });
    // Data flows through the whole pipeline before the first kill.
    wait_until(&run, "fused poses", 3 * minute, || status(&run, "fusion").is_some_and(|r| r.messages > 200));

    let mut kills = vec![];
    for (i, name) in VICTIMS.into_iter().enumerate() {
        // Spread over the mission: the i-th kill once ingest is past 8 + 9·i % of it.
        let at = 8 + 9 * i as u32;
        wait_until(&run, &format!("{at}% of the mission"), 5 * minute, || progress(&run) >= at);
        let before = status(&run, name).expect("status row");
        assert_eq!(before.restarts, 0, "{name} restarted before it was killed: {before:?}\n{}", run.log());
        assert!(
            !ended(&run, name),
            "{name} already ended before its kill ({:.0} s into the run): the mission is too short for the test",
            t0.elapsed().as_secs_f64()
        );
        let pid = before.pid.expect("a running process has a pid");
        kill(Pid::from_raw(pid), Signal::SIGKILL).expect("SIGKILL");
        kills.push((name, at, t0.elapsed().as_secs_f64().round()));
        // Restarted (a new pid), ready, and working again (messages in or out since the restart).
        wait_until(&run, &format!("{name} restarted and working"), 2 * minute, || {
            status(&run, name).is_some_and(|r| {
                r.restarts == 1 && r.state == "ready" && r.pid.is_some_and(|p| p != pid) && r.messages > 0
            })
        });
    }
    eprintln!("kills (process, mission %, s into the run): {kills:?}");
    let exit = run.wait_supervisor(15 * minute).expect("the run ends");
    eprintln!("run took {:.0} s", t0.elapsed().as_secs_f64());
    assert_eq!(exit.code(), Some(0), "{}", run.log());
    assert_eq!(run.leftovers(), Vec::<std::path::PathBuf>::new(), "iceoryx2 files left behind");

    // Each restarted stage took over what its killed instance had done (see docs/stages.md, Restarts):
    // ingest resumed where the killed one was instead of replaying the mission (and held back
    // while a consumer of its services restarted), SLAM kept its trajectory, the buoy EKF and
    // fusion replayed their inputs, the mapper loaded its checkpoint.
    let log = run.log();
    for (stage, line) in [
        ("ingest", "resumed after the"),
        ("ingest", "the lost subscriber is back"),
        ("slam", "kept the killed instance's trajectory; its local maps are lost"),
        ("buoy", "replayed the inputs the killed instance's filter took; it goes on from there"),
        ("fusion", "replayed the killed instance's inputs"),
        ("map", "the map starts from the killed instance's last checkpoint"),
    ] {
        assert!(log.contains(&format!("[{stage}]")) && log.contains(line), "{stage}: no `{line}` in the log:\n{log}");
    }
    let s = run.summary();
    // What sat in a killed process's queues (or its own, unprocessed) is counted by its restarted
    // instance, nothing is lost silently; only killed processes lose anything that way.
    let lost: Vec<&serde_json::Value> = s["dropped"]
        .as_array()
        .expect("dropped rows")
        .iter()
        .filter(|r| r["reason"] == pipeline_runtime::stats::LOST_IN_RESTART)
        .collect();
    assert!(!lost.is_empty(), "nothing counted as lost in the restarts: {:#}", s["dropped"]);
    for r in &lost {
        let process = r["process"].as_str().unwrap_or_default();
        assert!(VICTIMS.contains(&process) && r["messages"].as_u64().unwrap_or(0) > 0, "{r:#}");
    }
    use crate::summary_schema::part;
    let sup: supervisor::report::SupervisorPart = part(&s);
    assert_eq!(sup.run.end_reason, supervisor::outcome::EndReason::EndOfStream, "{:?}", sup.run);
    for name in VICTIMS {
        let p = &sup.processes[name];
        assert_eq!(p.restarts, 1, "{name}: {p:?}");
        let code = p.last_exit.as_ref().and_then(|e| e.code);
        assert_eq!(code, Some(0), "{name}: the restarted instance must end cleanly: {p:?}");
    }

    // Outputs: every file exists and parses.
    let out = run.out_dir();
    let truth = read_tum(&out.join("ground_truth.tum"), true);
    let (t_first, t_last) = (truth[0].0, truth[truth.len() - 1].0);
    // The two-leg mission is ~260 s of data (2026-12-04): the restarted ingest wrote all of it.
    assert!(t_last - t_first > 250.0, "ground truth covers {:.0} s of the mission", t_last - t_first);
    for f in [
        "slam_local.tum",
        "buoy_ekf.tum",
        "dead_reckoning.tum",
        "buoy.tum",
        "fused_global.tum",
        "fused_live.tum",
        "slam_global.tum",
    ] {
        let rows = read_tum(&out.join(f), f != "buoy_ekf.tum");
        assert!(!rows.is_empty(), "{f} is empty");
        // The restarted stages kept what their killed instances had done: the trajectories
        // cover the mission, not only the part after a restart.
        let (a, b) = (rows[0].0, rows[rows.len() - 1].0);
        assert!(
            a - t_first < 0.05 * (t_last - t_first) && t_last - b < 0.05 * (t_last - t_first),
            "{f} covers {a:.1}..{b:.1} s of the mission's {t_first:.1}..{t_last:.1} s"
        );
    }
    let bt = std::fs::read(out.join("map.bt")).expect("map.bt");
    assert!(bt.starts_with(b"# Octomap OcTree binary file"), "map.bt is not an OctoMap file");
    let tree = octree::OcTree::read_binary(bt.as_slice()).expect("map.bt parses");
    let (occupied, _) = tree.num_occupied_free_leaves();
    assert!(occupied > 10_000, "map.bt has {occupied} occupied leaves");
    for f in ["global_map.ply", "navigable.ply", "obstacles.ply"] {
        let ply = std::fs::read(out.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        assert!(ply.starts_with(b"ply\n") && ply.windows(10).any(|w| w == b"end_header"), "{f} is not a PLY file");
    }
    let transforms: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("segment_transforms.json")).expect("segment_transforms.json"))
            .expect("segment_transforms.json is JSON");
    assert!(!transforms.is_null());
    // Accuracy within loose bounds (a quiet run: fused 0.2 m, buoy 0.23 m, SLAM 0.3 m).
    let ate = &s["ate_m"];
    eprintln!("ate_m after the kills: {ate}");
    let fused = part::<fusion_stage::summary::FusionPart>(&s).ate_m.expect("fusion's ATEs");
    let slam = part::<fastslam_stage::summary::FastSlamPart>(&s).ate_m.and_then(|a| a.slam);
    let buoy_ekf = part::<buoy_ekf_stage::summary::BuoyEkfPart>(&s).ate_m.and_then(|a| a.buoy_ekf);
    let ates = [
        ("fused", fused.fused, 1.5),
        ("buoy", fused.buoy, 1.5),
        ("buoy_ekf", buoy_ekf, 1.5),
        ("slam", slam, 2.0),
        ("slam_global", fused.slam_global, 3.0),
    ];
    for (k, v, bound) in ates {
        let v = v.unwrap_or(f64::NAN);
        assert!(v.is_finite() && v > 0.0 && v < bound, "ate_m.{k} = {v} (bound {bound} m): {ate:#}");
    }
    let m = part::<octree_mapper_stage::summary::OctreeMapperPart>(&s).octree_mapper;
    assert!(m.counters.clouds_inserted > 100, "{m:?}");
}

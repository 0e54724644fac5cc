//! Invalid configs: each error names the offending key, the exit code is 2, and nothing starts
//! (no process, no shared memory, no outputs).

use std::time::Duration;

use pipeline_tests::TestRun;

const CONSUMER: &str = "[processes.c]\nkind = \"test_consumer\"\n";

/// (case, processes TOML, the key the error must name)
const CASES: &[(&str, &str, &str)] = &[
    ("unknown key", "[processes.c]\nkind = \"test_consumer\"\nrestrat = \"never\"\n", "processes.c.restrat"),
    ("wrong type", "[processes.c]\nkind = \"test_consumer\"\nmax_restarts = \"three\"\n", "processes.c.max_restarts"),
    ("unknown enum value", "[processes.c]\nkind = \"test_consumer\"\nrestart = \"sometimes\"\n", "processes.c.restart"),
    ("missing binary", "[processes.x]\nkind = \"external\"\nbinary = \"/nonexistent/driver\"\n", "processes.x.binary"),
    ("external without binary", "[processes.x]\nkind = \"external\"\n", "processes.x.binary"),
    ("unknown kind", "[processes.x]\nkind = \"teleporter\"\n", "processes.x.kind"),
    ("unknown dependency", "[processes.c]\nkind = \"test_consumer\"\nafter = [\"ghost\"]\n", "processes.c.after"),
    (
        "cyclic dependency",
        "[processes.a]\nkind = \"test_consumer\"\nafter = [\"b\"]\n[processes.b]\nkind = \"test_producer\"\nafter = [\"a\"]\n",
        "processes.a.after",
    ),
    (
        "bad setting value",
        "[processes.p]\nkind = \"test_producer\"\n[processes.p.settings]\nrate_hz = -1.0\n",
        "processes.p.settings.rate_hz",
    ),
    (
        "unknown setting",
        "[processes.p]\nkind = \"test_producer\"\n[processes.p.settings]\npointz = 5\n",
        "processes.p.settings.pointz",
    ),
    (
        "setting of wrong type",
        "[processes.p]\nkind = \"test_producer\"\n[processes.p.settings]\npoints = \"many\"\n",
        "processes.p.settings.points",
    ),
];

#[test]
fn every_invalid_config_names_its_key_and_starts_nothing() {
    for (case, processes, key) in CASES {
        let mut run = TestRun::new("badcfg");
        let cfg = run.write_config("end = \"signal\"", processes);
        run.start_supervisor(&cfg, &[]);
        let status =
            run.wait_supervisor(Duration::from_secs(20)).unwrap_or_else(|| panic!("{case}: supervisor did not exit"));
        let log = run.log();
        assert_eq!(status.code(), Some(2), "{case}: exit code; log:\n{log}");
        assert!(log.contains(&format!("`{key}`")), "{case}: the error must name `{key}`; log:\n{log}");
        assert!(!log.contains("started process="), "{case}: a process was started:\n{log}");
        assert!(run.scope.shm_files().is_empty(), "{case}: shared memory was created");
        assert!(!run.out_dir().join("summary.json").exists(), "{case}: outputs were written");
    }
}

#[test]
fn unknown_run_key_and_bad_run_value_are_named() {
    for (run_extra, key) in [
        ("ende = \"signal\"", "run.ende"),
        ("end = \"duration\"", "run.duration_s"),
        ("heartbeat_timeout_s = 0", "run.heartbeat_timeout_s"),
    ] {
        let mut run = TestRun::new("badrun");
        let cfg = run.write_config(run_extra, CONSUMER);
        run.start_supervisor(&cfg, &[]);
        let status = run.wait_supervisor(Duration::from_secs(20)).expect("exits");
        assert_eq!(status.code(), Some(2), "{}", run.log());
        assert!(run.log().contains(&format!("`{key}`")), "must name `{key}`:\n{}", run.log());
    }
}

#[test]
fn check_flag_validates_without_starting_anything() {
    let mut run = TestRun::new("check");
    let cfg = run.write_config("end = \"signal\"", CONSUMER);
    run.start_supervisor(&cfg, &["--check"]);
    let status = run.wait_supervisor(Duration::from_secs(20)).expect("exits");
    assert_eq!(status.code(), Some(0), "{}", run.log());
    assert!(run.log().contains("config ok: 1 process(es)"), "{}", run.log());
    assert!(!run.log().contains("started process="));
    assert!(run.scope.shm_files().is_empty());
}

#[test]
fn doctor_reports_the_machine_against_a_config_and_fails_on_a_bad_one() {
    let default = format!("{}/../config/default.toml", env!("CARGO_MANIFEST_DIR"));
    let out = std::process::Command::new(pipeline_tests::bin("supervisor"))
        .args(["doctor", "--config", &default])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(0), "{text}");
    for topic in ["iceoryx2", "/dev/shm", "config", "shm needs", "open files", "other runs"] {
        assert!(text.contains(topic), "{topic} missing:\n{text}");
    }
    let run = pipeline_tests::TestRun::new("doctorbad");
    let cfg = run.write_config("end = \"signal\"", "[processes.p]\nkind = \"no_such_kind\"\n");
    let out = std::process::Command::new(pipeline_tests::bin("supervisor"))
        .args(["doctor", "--config"])
        .arg(&cfg)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(2), "{text}");
    assert!(text.contains("PROBLEM") && text.contains("no_such_kind"), "{text}");
}

#[test]
fn every_shipped_config_passes_the_check() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../config");
    let mut checked = vec![];
    for e in std::fs::read_dir(&dir).expect("config/") {
        let path = e.expect("entry").path();
        if path.extension().is_none_or(|x| x != "toml") {
            continue;
        }
        // The two-host configs name certificates under certs/ in the working directory, made by
        // `supervisor certs` as their comments say: made here in a directory of their own (and
        // first checked without them: the error names the file and the command).
        let text = std::fs::read_to_string(&path).expect("config");
        let cwd = if text.contains("\"certs/") {
            let tmp = tempfile::tempdir().expect("tmp").keep();
            let check = |cwd: &std::path::Path| {
                std::process::Command::new(pipeline_tests::bin("supervisor"))
                    .arg("--config")
                    .arg(std::path::absolute(&path).expect("path"))
                    .arg("--check")
                    .current_dir(cwd)
                    .output()
                    .expect("supervisor runs")
            };
            let without = check(&tmp);
            let err = String::from_utf8_lossy(&without.stderr).to_string() + &String::from_utf8_lossy(&without.stdout);
            assert_eq!(without.status.code(), Some(2), "{}: checked without certificates: {err}", path.display());
            assert!(err.contains("certs/ca.pem") && err.contains("supervisor certs"), "{}: {err}", path.display());
            let made = std::process::Command::new(pipeline_tests::bin("supervisor"))
                .args(["certs", "--name", "base", "--name", "auv1", "--name", "auv2"])
                .current_dir(&tmp)
                .output()
                .expect("supervisor certs runs");
            assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
            tmp
        } else {
            dir.parent().expect("repo").to_path_buf()
        };
        let out = std::process::Command::new(pipeline_tests::bin("supervisor"))
            .arg("--config")
            .arg(std::path::absolute(&path).expect("path"))
            .arg("--check")
            .current_dir(&cwd)
            .output()
            .expect("supervisor runs");
        assert_eq!(
            out.status.code(),
            Some(0),
            "{}: {}{}",
            path.display(),
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        if cwd.starts_with(std::env::temp_dir()) {
            // This host's own certificate revoked: the check names the list and the host.
            let cn = ["base", "auv2", "auv1"]
                .into_iter()
                .find(|cn| text.contains(&format!("certs/{cn}.pem")))
                .expect("a host certificate");
            let revoked = std::process::Command::new(pipeline_tests::bin("supervisor"))
                .args(["certs", "--revoke", cn])
                .current_dir(&cwd)
                .output()
                .expect("supervisor certs --revoke runs");
            assert!(revoked.status.success(), "{}", String::from_utf8_lossy(&revoked.stderr));
            let again = std::process::Command::new(pipeline_tests::bin("supervisor"))
                .arg("--config")
                .arg(std::path::absolute(&path).expect("path"))
                .arg("--check")
                .current_dir(&cwd)
                .output()
                .expect("supervisor runs");
            let err = String::from_utf8_lossy(&again.stderr).to_string() + &String::from_utf8_lossy(&again.stdout);
            assert_eq!(again.status.code(), Some(2), "{}: own certificate revoked: {err}", path.display());
            assert!(err.contains("revoked.txt") && err.contains(&format!("CN {cn}) is revoked")), "{err}");
            let _ = std::fs::remove_dir_all(&cwd);
        }
        checked.push(path.file_name().expect("name").to_string_lossy().to_string());
    }
    assert!(checked.len() >= 8 && checked.contains(&"robot.toml".to_string()), "{checked:?}");
}

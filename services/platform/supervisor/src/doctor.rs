//! `supervisor doctor [--config F]`: a pre-flight report of this machine for the pipeline —
//! cores and load, the iceoryx2 version, /dev/shm free against what the config's services
//! reserve, open-file limits, the config's processes and binaries, and iceoryx2 files of other
//! runs left in /dev/shm. Nothing is started or removed.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::path::Path;

use crate::plan;

/// The iceoryx2 version the pipeline is pinned to (Cargo.toml `=0.10.0`).
pub const ICEORYX2_VERSION: &str = "0.10.0";

/// One line of the report.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    /// Fine.
    Ok,
    /// Worth knowing, not fatal.
    Note,
    /// The pipeline will not start (or not well) until this is fixed.
    Problem,
}

/// The report: lines with verdicts; [`Report::exit_code`] is 2 with any problem.
#[derive(Debug, Default)]
pub struct Report {
    /// (verdict, topic, text).
    pub lines: Vec<(Verdict, String, String)>,
}

impl Report {
    fn add(&mut self, v: Verdict, topic: &str, text: impl Into<String>) {
        self.lines.push((v, topic.to_string(), text.into()));
    }

    /// 0 when nothing is a problem, 2 otherwise.
    pub fn exit_code(&self) -> u8 {
        if self.lines.iter().any(|(v, _, _)| *v == Verdict::Problem) { crate::EXIT_CONFIG } else { 0 }
    }

    /// The report as text.
    pub fn render(&self) -> String {
        let mut s = String::from("slam_pipeline doctor\n");
        for (v, topic, text) in &self.lines {
            let tag = match v {
                Verdict::Ok => "ok     ",
                Verdict::Note => "note   ",
                Verdict::Problem => "PROBLEM",
            };
            let _ = writeln!(s, "  {tag} {topic:<12} {text}");
        }
        s
    }
}

/// Groups the files in `dir` by their prefix up to and including the first `_` (iceoryx2 files of
/// a run start with the run's `iceoryx_prefix`): prefix → (files, bytes).
pub fn shm_groups(dir: &Path) -> std::io::Result<BTreeMap<String, (usize, u64)>> {
    let mut groups: BTreeMap<String, (usize, u64)> = BTreeMap::new();
    for e in std::fs::read_dir(dir)? {
        let e = e?;
        let name = e.file_name().to_string_lossy().to_string();
        let prefix = match name.find('_') {
            Some(i) => name[..=i].to_string(),
            None => name.clone(),
        };
        let g = groups.entry(prefix).or_default();
        g.0 += 1;
        g.1 += e.metadata().map(|m| m.len()).unwrap_or(0);
    }
    Ok(groups)
}

/// Builds the report (with the config's needs when one is given).
pub fn report(config: Option<&Path>) -> Report {
    let mut r = Report::default();
    let mib = |b: u64| b as f64 / 1048576.0;
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let load: Vec<&str> = load.split_whitespace().take(3).collect();
    r.add(Verdict::Ok, "machine", format!("{cores} core(s), load average {}", load.join(" ")));
    r.add(
        Verdict::Ok,
        "iceoryx2",
        format!("{ICEORYX2_VERSION} (pinned; Python producers need iceoryx2=={ICEORYX2_VERSION})"),
    );
    let shm = nix::sys::statvfs::statvfs("/dev/shm");
    let shm_free = match &shm {
        Ok(st) => {
            let free = st.blocks_available() * st.fragment_size();
            let total = st.blocks() * st.fragment_size();
            r.add(Verdict::Ok, "/dev/shm", format!("{:.0} MiB free of {:.0} MiB", mib(free), mib(total)));
            Some(free)
        }
        Err(e) => {
            r.add(Verdict::Problem, "/dev/shm", format!("cannot inspect: {e}"));
            None
        }
    };
    use nix::sys::resource::{Resource, getrlimit};
    let (soft, hard) = getrlimit(Resource::RLIMIT_NOFILE).unwrap_or((0, 0));
    if let Some(path) = config {
        match plan::make_plan(path, &plan::Overrides::default(), &plan::default_bin_dir()) {
            Err(e) => r.add(Verdict::Problem, "config", format!("{}: {e}", path.display())),
            Ok(p) => {
                r.add(
                    Verdict::Ok,
                    "config",
                    format!(
                        "{}: {} process(es), start order {:?}, binaries found",
                        path.display(),
                        p.processes.len(),
                        p.processes.iter().map(|x| x.name.as_str()).collect::<Vec<_>>()
                    ),
                );
                let needs: Vec<(&str, u64)> = p.processes.iter().map(|x| (x.name.as_str(), x.shm_bytes)).collect();
                match shm_free.map(|free| plan::check_shm(free, &needs)) {
                    Some(Ok(need)) => {
                        r.add(Verdict::Ok, "shm needs", format!("~{:.0} MiB for this config: fits", mib(need)))
                    }
                    Some(Err(e)) => r.add(Verdict::Problem, "shm needs", e.to_string()),
                    None => {}
                }
                let need = 256 + 64 * p.processes.len() as u64;
                let v = if soft >= need {
                    Verdict::Ok
                } else if hard >= need {
                    Verdict::Note
                } else {
                    Verdict::Problem
                };
                let hint = match v {
                    Verdict::Ok => "",
                    Verdict::Note => " (the supervisor raises the soft limit itself)",
                    Verdict::Problem => " (raise the hard limit: ulimit -Hn, LimitNOFILE=)",
                };
                r.add(v, "open files", format!("soft {soft}, hard {hard}, this config needs {need}{hint}"));
                let prefix = &p.scope.prefix;
                if let Ok(groups) = shm_groups(Path::new("/dev/shm"))
                    && let Some((n, b)) = groups.get(prefix.as_str())
                {
                    r.add(
                        Verdict::Note,
                        "this prefix",
                        format!(
                            "{n} file(s), {:.1} MiB in /dev/shm under `{prefix}`: a live run (the supervisor refuses to start) or a dead one (it cleans them up)",
                            mib(*b)
                        ),
                    );
                }
            }
        }
    } else {
        r.add(Verdict::Ok, "open files", format!("soft {soft}, hard {hard} (give --config for the needs of a config)"));
    }
    match shm_groups(Path::new("/dev/shm")) {
        Ok(groups) if groups.is_empty() => r.add(Verdict::Ok, "other runs", "no files in /dev/shm"),
        Ok(groups) => {
            let list: Vec<String> =
                groups.iter().map(|(p, (n, b))| format!("`{p}` {n} file(s) {:.1} MiB", mib(*b))).collect();
            r.add(Verdict::Note, "other runs", format!("files in /dev/shm by prefix: {}", list.join(", ")));
        }
        Err(e) => r.add(Verdict::Note, "other runs", format!("cannot list /dev/shm: {e}")),
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_are_grouped_by_their_prefix() {
        let dir = std::env::temp_dir().join(format!("doctor-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (name, len) in [("slam_a", 10usize), ("slam_b", 5), ("pt1_x", 1), ("loose", 2)] {
            std::fs::write(dir.join(name), vec![0u8; len]).unwrap();
        }
        let g = shm_groups(&dir).unwrap();
        assert_eq!(g["slam_"], (2, 15));
        assert_eq!(g["pt1_"], (1, 1));
        assert_eq!(g["loose"], (1, 2));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_problem_makes_the_exit_code_2() {
        let mut r = Report::default();
        r.add(Verdict::Ok, "a", "fine");
        assert_eq!(r.exit_code(), 0);
        r.add(Verdict::Problem, "b", "broken");
        assert_eq!(r.exit_code(), 2);
        assert!(r.render().contains("PROBLEM b"));
    }
}

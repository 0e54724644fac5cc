//! `supervisor status --config F`: the state of the pipeline the config runs, from the
//! `status.json` the running supervisor rewrites in the output directory every
//! `run.status_interval_s` — per process state, restarts, pid, message rate and hop latency.

use std::fmt::Write;
use std::path::Path;

/// What `status` found.
#[derive(Debug)]
pub struct StatusView {
    /// The table to print.
    pub text: String,
    /// 0 running, 1 not running (ended, or its supervisor is gone), 2 no status at all.
    pub exit_code: u8,
}

fn alive(pid: i32) -> bool {
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), None).is_ok()
}

/// Reads `<out_dir>/status.json` and renders it.
pub fn view(out_dir: &Path) -> StatusView {
    let path = out_dir.join("status.json");
    let text = match std::fs::read(&path) {
        Ok(t) => t,
        Err(e) => {
            return StatusView {
                text: format!(
                    "no status at {} ({e}): the pipeline has not run with this output directory\n",
                    path.display()
                ),
                exit_code: 2,
            };
        }
    };
    let s: serde_json::Value = match serde_json::from_slice(&text) {
        Ok(v) => v,
        Err(e) => return StatusView { text: format!("{}: unreadable ({e})\n", path.display()), exit_code: 2 },
    };
    let pid = s["supervisor_pid"].as_i64().unwrap_or(0) as i32;
    let ended = s["ended"].as_bool().unwrap_or(false);
    let age_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as f64 / 1e3)
        .unwrap_or(0.0)
        - s["updated_unix_ms"].as_f64().unwrap_or(0.0) / 1e3;
    let running = !ended && pid > 0 && alive(pid);
    let mut out = String::new();
    let _ = writeln!(
        out,
        "pipeline `{}`: {} (supervisor pid {pid}, up {:.1} s, status {:.1} s old)",
        s["prefix"].as_str().unwrap_or("?"),
        if running {
            "running"
        } else if ended {
            "ended"
        } else {
            "not running (its supervisor is gone)"
        },
        s["uptime_s"].as_f64().unwrap_or(0.0),
        age_s
    );
    let _ = writeln!(
        out,
        "{:<16} {:<18} {:<9} {:>8} {:>8} {:>10} {:>10} {:>10}",
        "process", "kind", "state", "restarts", "pid", "msg/s", "hop p50 ms", "hop p99 ms"
    );
    let f = |v: &serde_json::Value| v.as_f64().map_or("-".to_string(), |x| format!("{x:.3}"));
    for p in s["processes"].as_array().map(Vec::as_slice).unwrap_or_default() {
        let _ = writeln!(
            out,
            "{:<16} {:<18} {:<9} {:>8} {:>8} {:>10.1} {:>10} {:>10}",
            p["name"].as_str().unwrap_or("?"),
            p["kind"].as_str().unwrap_or("?"),
            p["state"].as_str().unwrap_or("?"),
            p["restarts"].as_u64().unwrap_or(0),
            p["pid"].as_i64().map_or("-".to_string(), |x| x.to_string()),
            p["messages_per_s"].as_f64().unwrap_or(0.0),
            f(&p["hop_p50_ms"]),
            f(&p["hop_p99_ms"]),
        );
    }
    StatusView { text: out, exit_code: if running { 0 } else { 1 } }
}

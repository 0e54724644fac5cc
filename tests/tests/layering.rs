//! The layering rules of the docs/ARCHITECTURE.md ("What may depend on what"), checked on `cargo metadata`:
//! - an algorithm crate (algorithms/) depends on no iceoryx2, shared_types or anything under
//!   services/ (the maths stays pure and testable without IPC);
//! - every crate under services/ stands in one of its four rooms: platform/ (the runtime, the
//!   supervisor), libraries/ (no process: ROS 2 messages, the byte topics), stages/ (one process
//!   kind each), tools/ (benches, test processes);
//! - a stage crate (services/stages/) depends on no other stage; the platform and the libraries
//!   depend on no stage and no tool;
//! - the supervisor depends on the runtime and shared_types only among the workspace's crates
//!   (kinds are plug-ins it finds by name);
//! - no crate's modules import each other in a loop (read from the sources).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

struct Package {
    name: String,
    dir: PathBuf,
    /// (dependency name, kind: "normal", "dev" or "build").
    deps: Vec<(String, String)>,
}

fn workspace() -> (PathBuf, Vec<Package>) {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf();
    let out = std::process::Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--no-deps", "--offline"])
        .current_dir(&root)
        .output()
        .expect("cargo metadata runs");
    assert!(out.status.success(), "cargo metadata: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let packages = v["packages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| Package {
            name: p["name"].as_str().unwrap().to_string(),
            dir: Path::new(p["manifest_path"].as_str().unwrap()).parent().unwrap().to_path_buf(),
            deps: p["dependencies"]
                .as_array()
                .unwrap()
                .iter()
                .map(|d| (d["name"].as_str().unwrap().to_string(), d["kind"].as_str().unwrap_or("normal").to_string()))
                .collect(),
        })
        .collect();
    (root, packages)
}

#[test]
fn algorithms_stages_and_the_supervisor_depend_only_on_what_the_readme_allows() {
    let (root, packages) = workspace();
    let under = |p: &Package, dir: &str| p.dir.starts_with(root.join(dir));
    let by_name: BTreeMap<&str, &Package> = packages.iter().map(|p| (p.name.as_str(), p)).collect();
    let is_stage = |name: &str| by_name.get(name).is_some_and(|p| under(p, "services/stages"));
    let is_tool = |name: &str| by_name.get(name).is_some_and(|p| under(p, "services/tools"));
    let is_service = |name: &str| by_name.get(name).is_some_and(|p| under(p, "services"));
    let mut violations = vec![];
    let rooms = ["services/platform", "services/libraries", "services/stages", "services/tools"];
    for p in packages.iter().filter(|p| under(p, "services")) {
        if !rooms.iter().any(|r| under(p, r)) {
            violations.push(format!("{} ({}) stands in none of {rooms:?}", p.name, p.dir.display()));
        }
        if under(p, "services/platform") || under(p, "services/libraries") {
            for (d, kind) in p.deps.iter().filter(|(_, k)| k == "normal") {
                if is_stage(d) || is_tool(d) {
                    violations.push(format!("{} (platform or library) depends on {d} ({kind})", p.name));
                }
            }
        }
    }
    let stages: Vec<&str> = packages.iter().filter(|p| is_stage(&p.name)).map(|p| p.name.as_str()).collect();
    assert!(stages.len() >= 6, "stage crates not recognised: {stages:?}");
    let algorithms: Vec<&Package> = packages.iter().filter(|p| under(p, "algorithms")).collect();
    assert!(algorithms.len() >= 6, "algorithm crates not found under {}", root.join("algorithms").display());
    for p in &algorithms {
        for (d, kind) in &p.deps {
            if d == "iceoryx2" || d.starts_with("iceoryx2-") || d == "shared_types" || is_service(d) {
                violations.push(format!("algorithm crate {} depends on {d} ({kind})", p.name));
            }
        }
    }
    for s in &stages {
        for (d, kind) in &by_name[s].deps {
            if is_stage(d) {
                violations.push(format!("stage {s} depends on stage {d} ({kind})"));
            }
        }
    }
    let supervisor = by_name.get("supervisor").expect("the supervisor crate");
    for (d, kind) in &supervisor.deps {
        let workspace_crate = by_name.contains_key(d.as_str());
        if kind == "normal" && workspace_crate && d != "pipeline_runtime" && d != "shared_types" {
            violations
                .push(format!("the supervisor depends on {d}: it may use only pipeline_runtime and shared_types"));
        }
    }
    assert!(
        violations.is_empty(),
        "layering rules broken (docs/ARCHITECTURE.md, What may depend on what):\n{}",
        violations.join("\n")
    );
}

/// Binaries and libraries that `cargo test` skips (`test = false`, `doctest = false` in their
/// Cargo.toml, to save a compile and a link each: docs/benchmarks.md, Test time) must hold no test
/// that would then never run.
#[test]
fn targets_that_cargo_test_skips_hold_no_tests() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf();
    let out = std::process::Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--no-deps", "--offline"])
        .current_dir(&root)
        .output()
        .expect("cargo metadata runs");
    assert!(out.status.success(), "cargo metadata: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let mut skipped = 0;
    let mut violations = vec![];
    for p in v["packages"].as_array().unwrap() {
        for t in p["targets"].as_array().unwrap() {
            let kinds: Vec<&str> = t["kind"].as_array().unwrap().iter().filter_map(|k| k.as_str()).collect();
            let src = Path::new(t["src_path"].as_str().unwrap());
            let name = t["name"].as_str().unwrap();
            if kinds.contains(&"bin") && t["test"] == false {
                skipped += 1;
                // A binary's tests live in its own file (these declare no modules: checked too).
                let text = std::fs::read_to_string(src).expect("a binary's source");
                for needle in ["#[test]", "#[cfg(test)]", "\nmod ", "\npub mod "] {
                    if text.contains(needle) {
                        violations.push(format!(
                            "bin {name} ({}) has test = false but contains `{}`",
                            src.display(),
                            needle.trim()
                        ));
                    }
                }
            }
            if kinds.iter().any(|k| k.ends_with("lib")) && t["doctest"] == false {
                skipped += 1;
                // Every file of the library: a fenced example in a doc comment would be a doc test.
                let dir = src.parent().unwrap();
                let mut stack = vec![dir.to_path_buf()];
                while let Some(d) = stack.pop() {
                    for e in std::fs::read_dir(&d).expect("a source directory").flatten() {
                        let path = e.path();
                        if path.is_dir() {
                            stack.push(path);
                        } else if path.extension().is_some_and(|x| x == "rs") {
                            let text = std::fs::read_to_string(&path).expect("a source file");
                            if has_doc_test(&text) {
                                violations.push(format!(
                                    "lib {name} has doctest = false but {} has a fenced block in its docs",
                                    path.display()
                                ));
                            }
                        }
                    }
                }
            }
        }
    }
    assert!(skipped > 10, "expected the stage binaries to be marked test = false, found {skipped} skipped targets");
    assert!(violations.is_empty(), "tests that `cargo test` would never run:\n{}", violations.join("\n"));
}

/// Whether a file's doc comments hold a fenced block that rustdoc runs as a test: one whose info
/// string is empty or names only Rust attributes (```` ```text ````, ```` ```json ```` are not run).
fn has_doc_test(text: &str) -> bool {
    let mut open = false;
    for l in text.lines() {
        let l = l.trim_start();
        let Some(doc) = l.strip_prefix("///").or_else(|| l.strip_prefix("//!")) else { continue };
        let Some(info) = doc.trim_start().strip_prefix("```") else { continue };
        if open {
            open = false;
            continue;
        }
        open = true;
        let rust = info.split(',').map(str::trim).all(|a| {
            a.is_empty()
                || ["rust", "no_run", "should_panic", "ignore", "compile_fail"].contains(&a)
                || a.starts_with("edition")
        });
        if rust {
            return true;
        }
    }
    false
}

/// The code, the configs and the docs cite the papers and docs/EQUATIONS.md, not the steering
/// repository's SPEC.md (which a user of this repository does not have).
#[test]
fn nothing_cites_the_steering_spec() {
    let (root, _) = workspace();
    let mut found = vec![];
    let mut stack: Vec<PathBuf> = ["algorithms", "services", "shared_types", "config", "docs", "tests", "scripts"]
        .iter()
        .map(|d| root.join(d))
        .collect();
    stack.push(root.join("README.md"));
    stack.push(root.join("Cargo.toml"));
    while let Some(p) = stack.pop() {
        if p.is_dir() {
            for e in std::fs::read_dir(&p).expect("a readable directory").flatten() {
                stack.push(e.path());
            }
            continue;
        }
        let ext = p.extension().and_then(|e| e.to_str()).unwrap_or("");
        if !["rs", "toml", "md", "py", "sh"].contains(&ext) || p.ends_with(file!().rsplit('/').next().unwrap_or("")) {
            continue;
        }
        let Ok(text) = std::fs::read_to_string(&p) else { continue };
        for (i, line) in text.lines().enumerate() {
            if line.contains(concat!("SPEC ", "§")) || line.contains(concat!("SPEC", ".md")) {
                found.push(format!("{}:{}: {}", p.strip_prefix(&root).unwrap_or(&p).display(), i + 1, line.trim()));
            }
        }
    }
    assert!(found.is_empty(), "cite the papers or docs/EQUATIONS.md instead:\n{}", found.join("\n"));
}

/// The modules a crate's file `text` names: `crate::m` paths and `use crate::{a, b::c}` groups,
/// where `m` is one of the crate's top-level modules or a name its lib.rs re-exports from one
/// (`reexports`: name → module). Comment lines are skipped (doc links are not imports).
fn named_modules(text: &str, modules: &[String], reexports: &BTreeMap<String, String>) -> Vec<String> {
    let resolve = |name: &str| -> Option<String> {
        if modules.iter().any(|m| m == name) { Some(name.to_string()) } else { reexports.get(name).cloned() }
    };
    let code: String = text.lines().filter(|l| !l.trim_start().starts_with("//")).map(|l| format!("{l}\n")).collect();
    let mut out = vec![];
    let mut rest = code.as_str();
    while let Some(i) = rest.find("crate::") {
        rest = &rest[i + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            // The group's top-level items, up to its closing brace.
            let (mut depth, mut item, mut end) = (0, String::new(), group.len());
            for (k, ch) in group.char_indices() {
                match ch {
                    '{' => depth += 1,
                    '}' if depth == 0 => {
                        end = k;
                        break;
                    }
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        out.extend(resolve(item.trim().split("::").next().unwrap_or("").trim()));
                        item.clear();
                        continue;
                    }
                    _ => {}
                }
                if depth == 0 {
                    item.push(ch);
                }
            }
            out.extend(resolve(item.trim().split("::").next().unwrap_or("").trim()));
            rest = &group[end..];
        } else {
            let name: String = rest.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
            out.extend(resolve(&name));
        }
    }
    out
}

/// No crate's modules import each other in a loop (a module above all it imports makes the
/// crate readable from the bottom up; docs/ARCHITECTURE.md). Modules are the files and folders
/// under `src/`; an import is a `crate::` path to one of them or to a name lib.rs re-exports
/// from one.
#[test]
fn no_crate_has_modules_that_import_each_other_in_a_loop() {
    let (_, packages) = workspace();
    let mut circles = vec![];
    let mut crates_seen = 0;
    for p in &packages {
        let src = p.dir.join("src");
        let Ok(entries) = std::fs::read_dir(&src) else { continue };
        crates_seen += 1;
        // Top-level modules and their files.
        let mut files: BTreeMap<String, Vec<PathBuf>> = BTreeMap::new();
        for e in entries.flatten() {
            let path = e.path();
            let name = path.file_stem().and_then(|s| s.to_str()).unwrap_or("").to_string();
            if path.is_dir() {
                let mut stack = vec![path.clone()];
                while let Some(d) = stack.pop() {
                    for f in std::fs::read_dir(&d).into_iter().flatten().flatten() {
                        let fp = f.path();
                        if fp.is_dir() {
                            stack.push(fp);
                        } else if fp.extension().is_some_and(|x| x == "rs") {
                            files.entry(name.clone()).or_default().push(fp);
                        }
                    }
                }
            } else if path.extension().is_some_and(|x| x == "rs") && !["lib", "main"].contains(&name.as_str()) {
                files.entry(name).or_default().push(path);
            }
        }
        let modules: Vec<String> = files.keys().filter(|m| m.as_str() != "bin").cloned().collect();
        // Names lib.rs re-exports: `pub use module::{A, B}` / `pub use module::A`.
        let mut reexports = BTreeMap::new();
        let lib = std::fs::read_to_string(src.join("lib.rs")).unwrap_or_default();
        for stmt in lib.split(';') {
            let Some(u) = stmt.trim().strip_prefix("pub use ") else { continue };
            let u = u.trim_start_matches("crate::").trim_start_matches("self::");
            let Some((module, names)) = u.split_once("::") else { continue };
            if !modules.iter().any(|m| m == module) {
                continue;
            }
            for n in names.trim_matches(|c| c == '{' || c == '}' || char::is_whitespace(c)).split(',') {
                let n = n.trim();
                let n = n.rsplit(" as ").next().unwrap_or(n).rsplit("::").next().unwrap_or(n).trim();
                if !n.is_empty() && n != "*" {
                    reexports.insert(n.to_string(), module.to_string());
                }
            }
        }
        let mut edges: BTreeMap<String, std::collections::BTreeSet<String>> = BTreeMap::new();
        for m in &modules {
            for f in &files[m] {
                let text = std::fs::read_to_string(f).unwrap_or_default();
                for to in named_modules(&text, &modules, &reexports) {
                    if &to != m {
                        edges.entry(m.clone()).or_default().insert(to);
                    }
                }
            }
        }
        // A loop: a module that reaches itself.
        for start in &modules {
            let mut stack: Vec<(String, Vec<String>)> = vec![(start.clone(), vec![start.clone()])];
            let mut seen = std::collections::BTreeSet::new();
            while let Some((at, path)) = stack.pop() {
                for next in edges.get(&at).into_iter().flatten() {
                    if next == start {
                        let mut ring = path.clone();
                        ring.push(start.clone());
                        // Reported once, from its smallest module.
                        if path.iter().all(|m| m >= start) {
                            circles.push(format!("{}: {}", p.name, ring.join(" -> ")));
                        }
                    } else if seen.insert(next.clone()) {
                        let mut more = path.clone();
                        more.push(next.clone());
                        stack.push((next.clone(), more));
                    }
                }
            }
        }
    }
    assert!(crates_seen >= 20, "crates not found: {crates_seen}");
    assert!(circles.is_empty(), "modules that import each other in a loop:\n{}", circles.join("\n"));
}

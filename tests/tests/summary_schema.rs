//! summary.json's keys, declared: docs/summary.schema.json is the JSON Schema of the supervisor's
//! part and of every stage's part (the structs each stage returns from `Stage::finish`), merged
//! as the supervisor merges the parts. This module checks that the committed file is what the
//! code generates, and gives the other tests [`undeclared`], which lists every key of a real
//! summary.json that the schema does not declare (tests/tests/fusion.rs runs it on the main job).
//!
//! Regenerate the file after changing a summary struct:
//! `UPDATE_SUMMARY_SCHEMA=1 cargo test --workspace --test pipeline -- summary_schema::`

use serde_json::{Map, Value, json};

/// The committed schema's path.
fn committed_path() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/summary.schema.json")
}

fn schema_of<T: schemars::JsonSchema>() -> Value {
    serde_json::to_value(schemars::schema_for!(T)).expect("a schema is JSON")
}

/// summary.json as one struct, and the list of parts its schema merges, from one table: the
/// kind, the struct the kind's stage returns from `finish`, and the top-level key whose presence
/// says a process of that kind ran.
macro_rules! run_summary {
    ($($field:ident: $ty:ty = $key:literal),* $(,)?) => {
        /// A run's summary.json: the supervisor's part, and the part of every stage kind that
        /// ran (`None`: no process of that kind wrote its key). Each part is read from the whole
        /// file (parts share `ate_m`, `nees` and `pipeline_latency_ms`), strictly: a part whose
        /// key is there but whose content does not fit its struct is an error.
        #[derive(Debug, Clone)]
        pub struct RunSummary {
            /// The supervisor's own part (`run`, `processes`, `undelivered`, `dropped`, `latency_ms`).
            pub supervisor: supervisor::report::SupervisorPart,
            $(
                #[doc = concat!("The `", stringify!($field), "` kind's part (key `", $key, "`).")]
                pub $field: Option<$ty>,
            )*
        }

        impl RunSummary {
            /// Reads `summary` (a whole summary.json) into its parts.
            pub fn from_value(summary: &Value) -> Result<Self, String> {
                fn read<T: serde::de::DeserializeOwned>(v: &Value) -> Result<T, String> {
                    serde_json::from_value(v.clone()).map_err(|e| format!("{}: {e}", std::any::type_name::<T>()))
                }
                Ok(Self {
                    supervisor: read(summary)?,
                    $($field: if summary.get($key).is_some() { Some(read(summary)?) } else { None },)*
                })
            }

            /// The stage kinds whose part is there.
            pub fn kinds(&self) -> Vec<&'static str> {
                let mut out = vec![];
                $(if self.$field.is_some() { out.push(stringify!($field)); })*
                out
            }
        }

        /// The parts of summary.json with a typed struct, by the kind that writes them.
        fn parts() -> Vec<(&'static str, Value)> {
            vec![$((stringify!($field), schema_of::<$ty>()),)*]
        }
    };
}

run_summary! {
    sensor_monitor: sensor_monitor_stage::summary::SensorMonitorPart = "sensor_monitor",
    ingest: ingest_stage::summary::IngestPart = "ingest",
    fastslam: fastslam_stage::summary::FastSlamPart = "slam",
    buoy_ekf: buoy_ekf_stage::summary::BuoyEkfPart = "buoy_ekf",
    synchronizer: synchronizer_stage::summary::SynchronizerPart = "synchronizer",
    fusion: fusion_stage::summary::FusionPart = "fusion",
    octree_mapper: octree_mapper_stage::summary::OctreeMapperPart = "octree_mapper",
    grid_slam: grid_slam_stage::summary::GridSlamPart = "grid_slam",
    viewer: viewer_stage::summary::ViewerPart = "viewer",
    recorder: recorder_stage::summary::RecorderPart = "recorder",
    replayer: recorder_stage::summary::ReplayerPart = "replayer",
    bridge: bridge_stage::summary::BridgePart = "bridge",
    ros2: ros2_stage::summary::Ros2Part = "ros2",
}

/// A run's summary.json read as [`RunSummary`]; panics naming the part that does not fit.
pub fn run_summary(summary: &Value) -> RunSummary {
    RunSummary::from_value(summary).unwrap_or_else(|e| panic!("summary.json does not read as its parts: {e}"))
}

/// The merged schema of summary.json.
pub fn schema() -> Value {
    let mut root = schema_of::<supervisor::report::SupervisorPart>();
    root["title"] = json!("summary.json");
    root["additionalProperties"] = json!(false);
    root["description"] = json!(
        "What a run reports: the supervisor's part (run, processes, undelivered, dropped, latency_ms) and the parts \
         of the stages that ran, merged key by key. Generated from the summary structs by \
         tests/tests/summary_schema.rs; units are in the key names (_m, _s, _ms, _mib) or the descriptions. \
         A real number (format double) may be null: it was not finite (NaN: nothing to measure; JSON has no NaN)."
    );
    for (kind, part) in parts() {
        merge_defs(&mut root, &part, kind);
        let props = part["properties"].as_object().cloned().unwrap_or_default();
        for (key, sub) in props {
            let merged = match root["properties"].get(&key) {
                None => sub,
                Some(existing) => merge_objects(&root, existing.clone(), sub, &format!("{kind}: {key}")),
            };
            root["properties"][&key] = merged;
        }
    }
    root["properties"]["instances"] = json!({
        "type": "object",
        "description": "The parts of the processes with an out_dir of their own (`[processes.<name>] out_dir`), by \
                        process name: each is the part its kind writes at the top level otherwise (e.g. \
                        `instances.map_r1.octree_mapper`), kept apart so that two processes of one kind do not \
                        overwrite each other's keys.",
        "additionalProperties": { "type": "object" }
    });
    nullable_reals(&mut root);
    root
}

/// Every real number (an `f64`, `"format": "double"`) declared `number` or `null`: serde_json
/// writes a NaN or an infinity as `null`, so that is what a reader must take.
fn nullable_reals(s: &mut Value) {
    match s {
        Value::Object(m) => {
            let real = m.get("format").is_some_and(|f| f == "double" || f == "float");
            if real && m.get("type") == Some(&json!("number")) {
                m.insert("type".into(), json!(["number", "null"]));
            }
            m.values_mut().for_each(nullable_reals);
        }
        Value::Array(a) => a.iter_mut().for_each(nullable_reals),
        _ => {}
    }
}

fn merge_defs(root: &mut Value, part: &Value, kind: &str) {
    let Some(defs) = part.get("$defs").and_then(Value::as_object) else { return };
    let target = root.as_object_mut().unwrap().entry("$defs").or_insert_with(|| json!({}));
    for (name, def) in defs {
        match target.get(name) {
            Some(old) if old != def => panic!("{kind}: the summary type `{name}` differs from another of that name"),
            _ => {
                target[name] = def.clone();
            }
        }
    }
}

/// `$ref` resolved against the root's `$defs`.
fn resolve<'a>(root: &'a Value, s: &'a Value) -> &'a Value {
    match s.get("$ref").and_then(Value::as_str).and_then(|r| r.strip_prefix("#/$defs/")) {
        Some(name) => &root["$defs"][name],
        None => s,
    }
}

/// An `Option<T>`'s schema (`anyOf: [T, null]`) as T's, resolved.
fn unwrap_option<'a>(root: &'a Value, s: &'a Value) -> &'a Value {
    let s = resolve(root, s);
    match s.get("anyOf").and_then(Value::as_array).map(Vec::as_slice) {
        Some([t, n]) | Some([n, t]) if n.get("type") == Some(&json!("null")) => resolve(root, t),
        _ => s,
    }
}

/// Two object schemas for one key written by two parts: their properties together.
fn merge_objects(root: &Value, a: Value, b: Value, what: &str) -> Value {
    let (a, b) = (unwrap_option(root, &a).clone(), unwrap_option(root, &b).clone());
    let (Some(pa), Some(pb)) = (a["properties"].as_object(), b["properties"].as_object()) else {
        panic!("{what}: two parts write this key and one of them is not an object")
    };
    let mut props: Map<String, Value> = pa.clone();
    for (k, v) in pb {
        let merged = match props.get(k) {
            Some(old) if old == v => v.clone(),
            Some(old) => merge_objects(root, old.clone(), v.clone(), &format!("{what}.{k}")),
            None => v.clone(),
        };
        props.insert(k.clone(), merged);
    }
    let mut out = json!({ "type": "object", "properties": props, "additionalProperties": false });
    if let Some(d) = a.get("description").or(b.get("description")) {
        out["description"] = d.clone();
    }
    out
}

/// Every key of `value` (a summary.json) the schema does not declare, as dotted paths; and every
/// value whose JSON type the schema does not allow.
pub fn undeclared(schema: &Value, value: &Value) -> Vec<String> {
    let mut out = vec![];
    check(schema, schema, value, "", &mut out);
    out
}

fn allows(s: &Value, ty: &str) -> bool {
    match &s["type"] {
        Value::String(t) => t == ty || (ty == "integer" && t == "number"),
        Value::Array(ts) => ts.iter().any(|t| t == ty || (ty == "integer" && t == "number")),
        _ => true,
    }
}

fn check(root: &Value, s: &Value, v: &Value, path: &str, out: &mut Vec<String>) {
    let s = resolve(root, s);
    if let Some(alts) = s.get("anyOf").or(s.get("oneOf")).and_then(Value::as_array) {
        // An Option<T> or an enum: one alternative must take it without complaint.
        let fits = alts.iter().any(|alt| {
            let mut o = vec![];
            check(root, alt, v, path, &mut o);
            o.is_empty()
        });
        if !fits {
            out.push(format!("{path}: {v} fits none of the declared alternatives"));
        }
        return;
    }
    if s.as_bool() == Some(true) || s.as_object().is_some_and(|o| o.is_empty()) {
        return; // anything (an untyped value)
    }
    let ty = match v {
        Value::Null => "null",
        Value::Bool(_) => "boolean",
        Value::Number(n) if n.is_i64() || n.is_u64() => "integer",
        Value::Number(_) => "number",
        Value::String(_) => "string",
        Value::Array(_) => "array",
        Value::Object(_) => "object",
    };
    let ok = allows(s, ty)
        || s.get("const") == Some(v)
        || s.get("enum").and_then(Value::as_array).is_some_and(|e| e.contains(v));
    if !ok {
        out.push(format!("{path}: a {ty} where the schema says {}", s["type"]));
        return;
    }
    match v {
        Value::Object(m) => {
            let props = s.get("properties").and_then(Value::as_object);
            for (k, x) in m {
                let p = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
                match (props.and_then(|ps| ps.get(k)), s.get("additionalProperties")) {
                    (Some(sub), _) => check(root, sub, x, &p, out),
                    (None, Some(Value::Bool(false))) => out.push(format!("{p}: not declared")),
                    (None, Some(extra)) if extra.is_object() => check(root, extra, x, &p, out),
                    (None, _) if props.is_some() => out.push(format!("{p}: not declared")),
                    (None, _) => {}
                }
            }
        }
        Value::Array(items) => {
            if let Some(item) = s.get("items") {
                for (i, x) in items.iter().enumerate() {
                    check(root, item, x, &format!("{path}[{i}]"), out);
                }
            }
        }
        _ => {}
    }
}

/// The dotted keys of `summary`, three levels deep (`latency_ms` two: its tables' keys are the
/// hops); arrays are not entered. What tests/main_job_summary_keys.txt lists for the main job.
pub fn key_paths(summary: &Value) -> std::collections::BTreeSet<String> {
    fn walk(v: &Value, prefix: &str, depth: usize, out: &mut std::collections::BTreeSet<String>) {
        let Value::Object(m) = v else { return };
        for (k, x) in m {
            let path = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
            if depth + 1 < 3 && !path.starts_with("latency_ms.") {
                walk(x, &path, depth + 1, out);
            }
            out.insert(path);
        }
    }
    let mut out = std::collections::BTreeSet::new();
    walk(summary, "", 0, &mut out);
    out
}

/// A stage's part of `summary` as the struct the stage wrote it from (e.g.
/// `part::<grid_slam_stage::summary::GridSlamPart>(&summary)`); panics naming what does not fit.
pub fn part<T: serde::de::DeserializeOwned>(summary: &Value) -> T {
    serde_json::from_value(summary.clone())
        .unwrap_or_else(|e| panic!("summary.json does not hold a {}: {e}", std::any::type_name::<T>()))
}

/// Panics with the keys of `summary` (a whole summary.json) that docs/summary.schema.json does
/// not declare, or with the part that does not read as its struct; else the summary as its parts.
pub fn assert_declared(summary: &Value) -> RunSummary {
    let undeclared = undeclared(&schema(), summary);
    assert!(undeclared.is_empty(), "summary.json keys not in docs/summary.schema.json: {undeclared:#?}");
    run_summary(summary)
}

/// Validates the summary.json at `path` against the committed docs/summary.schema.json with
/// Python's `jsonschema` (PyPI: an implementation no one here wrote; scripts/test.sh installs it),
/// which also checks the schema itself against draft 2020-12.
pub fn assert_valid_by_jsonschema(path: &std::path::Path) {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = std::process::Command::new("python3")
        .arg(root.join("python/check_summary_schema.py"))
        .arg(committed_path())
        .arg(path)
        .output()
        .expect("python3 is needed for this test");
    assert!(
        out.status.success(),
        "{} does not validate against docs/summary.schema.json (Python jsonschema; install it with \
         `python3 -m pip install jsonschema`, as scripts/test.sh does):\n{}{}",
        path.display(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn the_committed_summary_schema_is_the_one_the_code_generates() {
    let text = serde_json::to_string_pretty(&schema()).unwrap() + "\n";
    let path = committed_path();
    if std::env::var_os("UPDATE_SUMMARY_SCHEMA").is_some() {
        std::fs::write(&path, &text).unwrap();
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == text,
        "{} is not what the summary structs generate; regenerate it with \
         `UPDATE_SUMMARY_SCHEMA=1 cargo test --workspace --test pipeline -- summary_schema::`",
        path.display()
    );
}

#[test]
fn the_checker_finds_undeclared_keys_and_wrong_types() {
    let s = schema();
    let ok =
        json!({ "run": { "exit_code": 0, "elapsed_s": 1.5 }, "synchronizer": { "pairs": 3, "max_latency_ms": null } });
    assert_eq!(undeclared(&s, &ok), Vec::<String>::new());
    let bad = json!({ "run": { "exit_code": "zero", "elapsed": 1.0 }, "synchronizer": { "pears": 3 }, "mystery": {} });
    let found = undeclared(&s, &bad);
    for key in ["run.exit_code", "run.elapsed:", "synchronizer.pears", "mystery"] {
        assert!(found.iter().any(|f| f.starts_with(key)), "{key} in {found:?}");
    }
    // A real may be null (it was NaN), a count may not.
    let nan = json!({ "run": { "exit_code": 0, "elapsed_s": null } });
    assert_eq!(undeclared(&s, &nan), Vec::<String>::new());
    let found = undeclared(&s, &json!({ "run": { "exit_code": null, "elapsed_s": 1.0 } }));
    assert!(found.iter().any(|f| f.starts_with("run.exit_code")), "{found:?}");
}

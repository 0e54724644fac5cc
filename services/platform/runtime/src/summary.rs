//! Pieces of summary.json that several stages use. Each stage's part is a struct of its own
//! ([`crate::Stage::Summary`]) deriving `Serialize`, `Deserialize` and `JsonSchema`; the
//! supervisor merges the parts, and docs/summary.schema.json (generated from these structs,
//! checked by `tests/tests/summary_schema.rs`) says which keys exist and in which unit.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Median, 99th percentile and maximum of a set of samples, in the unit the field's name gives
/// (`..._ms`: milliseconds). `null` when there were no samples.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize, JsonSchema)]
pub struct Percentiles {
    /// Median.
    pub p50: Option<f64>,
    /// 99th percentile.
    pub p99: Option<f64>,
    /// Maximum.
    pub max: Option<f64>,
}

impl Percentiles {
    /// Of `samples` (any order; non-finite values are left out).
    pub fn of(samples: &[f64]) -> Self {
        let mut s: Vec<f64> = samples.iter().copied().filter(|v| v.is_finite()).collect();
        s.sort_by(f64::total_cmp);
        let at = |q: f64| {
            if s.is_empty() { None } else { Some(s[((q * (s.len() - 1) as f64).round() as usize).min(s.len() - 1)]) }
        };
        Self { p50: at(0.5), p99: at(0.99), max: at(1.0) }
    }
}

/// [`Percentiles`] with the number of samples (latency tables: `count`, `p50`, `p99`, `max`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize, JsonSchema)]
pub struct CountedPercentiles {
    /// Samples.
    pub count: usize,
    /// Median.
    pub p50: Option<f64>,
    /// 99th percentile.
    pub p99: Option<f64>,
    /// Maximum.
    pub max: Option<f64>,
}

impl CountedPercentiles {
    /// Of `samples` (any order; non-finite values are left out of the percentiles, not the count).
    pub fn of(samples: &[f64]) -> Self {
        let p = Percentiles::of(samples);
        Self { count: samples.len(), p50: p.p50, p99: p.p99, max: p.max }
    }
}

/// Reads a `#[serde(flatten)]` `Option<T>` strictly: `None` when none of `T`'s own keys (its
/// schema's properties) is there, else `T`, whose errors propagate. serde alone reads a
/// flattened `Option` whose keys do not fit `T` as `None`, which would hide a broken or renamed
/// key. Use it as `#[serde(flatten, deserialize_with = "pipeline_runtime::summary::flattened_option")]`
/// in a struct without `deny_unknown_fields` (serde does not support that next to `flatten`, and
/// `T`'s keys stay in the map the outer struct sees).
pub fn flattened_option<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::de::DeserializeOwned + JsonSchema,
{
    use serde::de::Error;
    let map = serde_json::Map::<String, serde_json::Value>::deserialize(d)?;
    let schema = schemars::schema_for!(T);
    let own: Vec<&str> = schema
        .get("properties")
        .and_then(serde_json::Value::as_object)
        .map(|p| p.keys().map(String::as_str).collect())
        .unwrap_or_default();
    if !own.iter().any(|k| map.contains_key(*k)) {
        return Ok(None);
    }
    let fields: serde_json::Map<String, serde_json::Value> =
        map.into_iter().filter(|(k, _)| own.contains(&k.as_str())).collect();
    T::deserialize(serde_json::Value::Object(fields)).map(Some).map_err(D::Error::custom)
}

/// A number that may be undefined: serialised as the number, or `null` (JSON has no NaN).
pub fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
    struct Outer {
        always: u32,
        #[serde(flatten, deserialize_with = "flattened_option")]
        more: Option<Inner>,
    }

    #[derive(Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
    struct Inner {
        count: u32,
        mean_m: f64,
    }

    #[test]
    fn a_flattened_option_reads_strictly() {
        let read = |v: serde_json::Value| serde_json::from_value::<Outer>(v);
        let some = Outer { always: 1, more: Some(Inner { count: 2, mean_m: 0.5 }) };
        assert_eq!(read(serde_json::to_value(&some).unwrap()).unwrap(), some);
        assert_eq!(read(serde_json::json!({"always": 1, "other": 3})).unwrap(), Outer { always: 1, more: None });
        // Half of Inner (a key renamed or lost) is an error, not None.
        let err = read(serde_json::json!({"always": 1, "count": 2, "mean": 0.5})).unwrap_err();
        assert!(err.to_string().contains("mean_m"), "{err}");
        let err = read(serde_json::json!({"always": 1, "count": "two", "mean_m": 0.5})).unwrap_err();
        assert!(err.to_string().contains("invalid type"), "{err}");
    }

    #[test]
    fn percentiles_of_samples_and_of_none() {
        let p = Percentiles::of(&[3.0, 1.0, f64::NAN, 2.0, 100.0]);
        assert_eq!((p.p50, p.max), (Some(3.0), Some(100.0))); // rank round((n - 1) q), as geometry::stats
        assert_eq!(Percentiles::of(&[]), Percentiles::default());
        assert_eq!(
            serde_json::to_value(Percentiles::default()).unwrap(),
            serde_json::json!({"p50": null, "p99": null, "max": null})
        );
    }
}

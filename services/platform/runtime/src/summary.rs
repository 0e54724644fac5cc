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

/// The mean position NEES of an estimator's estimates against the ground truth (`nees.<estimator>`
/// with a position covariance: docs/EQUATIONS.md §8a), with Bar-Shalom's 95 % interval for that
/// mean. The estimator computes it (`geometry::trajectory::position_nees`); this is its summary.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
pub struct PositionNees {
    /// Mean NEES of the position (`dof` when consistent).
    pub position: Option<f64>,
    /// Degrees of freedom of one sample: 3, or 2 in planar mode (x and y).
    pub dof: usize,
    /// Estimates scored.
    pub samples: usize,
    /// Mean of eₖ² / Pₖₖ per axis, [x, y, z] (1 each when consistent; z is 0 in planar mode).
    pub per_axis: [f64; 3],
    /// Estimates not scored (outside the ground truth, or a covariance not positive definite).
    pub skipped: usize,
    /// The 95 % interval of the mean for a consistent estimator, [low, high].
    pub interval_95: [f64; 2],
    /// Whether the mean lies in the interval (below: covariances too large; above: too small).
    pub consistent: bool,
}

impl PositionNees {
    /// From the estimator's numbers: `mean` NEES over `samples` estimates of `dof` degrees of
    /// freedom each, its `per_axis` means, the estimates `skipped` and the 95 % interval of the
    /// mean; `consistent` is whether the mean lies in that interval.
    pub fn new(
        mean: f64,
        dof: usize,
        samples: usize,
        per_axis: [f64; 3],
        skipped: usize,
        interval_95: (f64, f64),
    ) -> Self {
        Self {
            position: finite(mean),
            dof,
            samples,
            per_axis,
            skipped,
            interval_95: [interval_95.0, interval_95.1],
            consistent: mean >= interval_95.0 && mean <= interval_95.1,
        }
    }

    /// The verdict in words, for the log: "yes", or which way the covariance is off.
    pub fn verdict(&self) -> &'static str {
        match self.position {
            _ if self.consistent => "yes",
            Some(m) if m < self.interval_95[0] => "no, the covariance is too large",
            _ => "no, the covariance is too small",
        }
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

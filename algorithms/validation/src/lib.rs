//! One way to check settings, for the algorithm crates and the pipeline's stages alike.
//!
//! A settings struct implements [`Validate`]: it checks its own fields with [`Issues::check`]
//! under their own names, and hands a nested struct its table with [`Issues::nested`]. The key
//! path is built once, by [`Issues`]: a problem found in `range.gate_probability` of the buoy
//! filter's settings reads `processes.buoy.settings.ekf.range.gate_probability` when the runtime
//! checks a config file, and `range.gate_probability` when a library user checks the struct alone.
//! Every problem is collected (not only the first), so a user fixes a config in one pass.
//!
//! ```
//! use validation::{Issues, Validate};
//!
//! struct Range { sigma_m: f64 }
//! struct Filter { particles: usize, range: Range }
//!
//! impl Validate for Range {
//!     fn validate(&self, issues: &mut Issues) {
//!         issues.check(self.sigma_m > 0.0, "sigma_m", "must be > 0");
//!     }
//! }
//! impl Validate for Filter {
//!     fn validate(&self, issues: &mut Issues) {
//!         issues.check(self.particles > 0, "particles", "must be at least 1");
//!         issues.nested("range", &self.range);
//!     }
//! }
//!
//! let bad = Filter { particles: 0, range: Range { sigma_m: -1.0 } };
//! let keys: Vec<String> = bad.issues().iter().map(|i| i.key.clone()).collect();
//! assert_eq!(keys, ["particles", "range.sigma_m"]);
//! let mut under = Issues::at("processes.slam.settings.filter");
//! bad.validate(&mut under);
//! assert_eq!(under.iter().nth(1).unwrap().key, "processes.slam.settings.filter.range.sigma_m");
//! ```

use std::fmt;

/// One problem found in settings: the dotted key and what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ConfigIssue {
    /// Dotted key, e.g. `processes.consumer.after` or `range.gate_probability`.
    pub key: String,
    /// What is wrong.
    pub message: String,
}

/// Collects [`ConfigIssue`]s under a key path.
#[derive(Debug, Default, Clone)]
pub struct Issues {
    found: Vec<ConfigIssue>,
    path: String,
}

impl Issues {
    /// Issues with keys relative to the settings being checked.
    pub fn new() -> Self {
        Self::default()
    }

    /// Issues whose keys start with `root` (e.g. `processes.slam.settings`).
    pub fn at(root: impl Into<String>) -> Self {
        Self { found: vec![], path: root.into() }
    }

    /// The full key of `field` under the current path (`field` may start with `[i]`).
    pub fn key(&self, field: &str) -> String {
        join(&self.path, field)
    }

    /// Records a problem with `field` (relative to the current path; "" names the path itself).
    pub fn push(&mut self, field: impl AsRef<str>, message: impl Into<String>) {
        let key = self.key(field.as_ref());
        self.found.push(ConfigIssue { key, message: message.into() });
    }

    /// Records a problem with `field` unless `ok`.
    pub fn check(&mut self, ok: bool, field: impl AsRef<str>, message: impl Into<String>) {
        if !ok {
            self.push(field, message);
        }
    }

    /// Runs `f` with the path extended by `field`.
    pub fn within<R>(&mut self, field: impl AsRef<str>, f: impl FnOnce(&mut Self) -> R) -> R {
        let len = self.path.len();
        self.path = join(&self.path, field.as_ref());
        let r = f(self);
        self.path.truncate(len);
        r
    }

    /// Checks `settings` as the table `field` under the current path.
    pub fn nested(&mut self, field: impl AsRef<str>, settings: &(impl Validate + ?Sized)) {
        self.within(field, |issues| settings.validate(issues));
    }

    /// Adds issues whose keys are already complete (e.g. from a check that knows the whole config).
    pub fn extend_absolute(&mut self, issues: impl IntoIterator<Item = ConfigIssue>) {
        self.found.extend(issues);
    }

    /// True when nothing was recorded.
    pub fn is_empty(&self) -> bool {
        self.found.is_empty()
    }

    /// How many problems were recorded.
    pub fn len(&self) -> usize {
        self.found.len()
    }

    /// The problems, in the order found.
    pub fn iter(&self) -> std::slice::Iter<'_, ConfigIssue> {
        self.found.iter()
    }

    /// True when a problem was recorded under exactly `key` (the full key).
    pub fn has(&self, key: &str) -> bool {
        self.found.iter().any(|i| i.key == key)
    }

    /// The problems, in the order found.
    pub fn into_vec(self) -> Vec<ConfigIssue> {
        self.found
    }

    /// `Ok(())` when nothing was recorded, else every problem.
    pub fn into_result(self) -> Result<(), Vec<ConfigIssue>> {
        if self.found.is_empty() { Ok(()) } else { Err(self.found) }
    }
}

impl IntoIterator for Issues {
    type Item = ConfigIssue;
    type IntoIter = std::vec::IntoIter<ConfigIssue>;
    fn into_iter(self) -> Self::IntoIter {
        self.found.into_iter()
    }
}

/// `key \`a.b\`: message; key \`c\`: message`.
impl fmt::Display for Issues {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (n, i) in self.found.iter().enumerate() {
            if n > 0 {
                f.write_str("; ")?;
            }
            write!(f, "key `{}`: {}", i.key, i.message)?;
        }
        Ok(())
    }
}

fn join(path: &str, field: &str) -> String {
    if path.is_empty() {
        field.to_string()
    } else if field.is_empty() {
        path.to_string()
    } else if field.starts_with('[') {
        format!("{path}{field}")
    } else {
        format!("{path}.{field}")
    }
}

/// Settings that can say what is wrong with their values.
pub trait Validate {
    /// Records every problem in `issues`, each under its field's name relative to `self`.
    fn validate(&self, issues: &mut Issues);

    /// Every problem, with keys relative to `self`.
    fn issues(&self) -> Issues {
        let mut issues = Issues::new();
        self.validate(&mut issues);
        issues
    }
}

/// Helpers for the checks that recur: finite and positive, finite and non-negative.
pub mod num {
    /// Finite and > 0.
    pub fn positive(v: f64) -> bool {
        v.is_finite() && v > 0.0
    }

    /// Finite and >= 0.
    pub fn non_negative(v: f64) -> bool {
        v.is_finite() && v >= 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Leaf(f64);
    impl Validate for Leaf {
        fn validate(&self, issues: &mut Issues) {
            issues.check(num::positive(self.0), "v", "must be > 0");
        }
    }

    #[test]
    fn keys_are_joined_once_under_any_root_and_index() {
        let leaves = [Leaf(1.0), Leaf(-1.0)];
        let mut issues = Issues::at("processes.x.settings");
        for (i, l) in leaves.iter().enumerate() {
            issues.nested(format!("leaves[{i}]"), l);
        }
        issues.within("a", |i| i.nested("[3]", &Leaf(0.0)));
        issues.push("", "whole table");
        let keys: Vec<&str> = issues.iter().map(|i| i.key.as_str()).collect();
        assert_eq!(keys, ["processes.x.settings.leaves[1].v", "processes.x.settings.a[3].v", "processes.x.settings"]);
        assert!(issues.has("processes.x.settings.a[3].v"));
        assert_eq!(issues.len(), 3);
        assert!(Leaf(2.0).issues().is_empty());
        assert_eq!(Leaf(f64::NAN).issues().to_string(), "key `v`: must be > 0");
        assert!(Leaf(f64::NAN).issues().into_result().is_err());
    }
}

//! `odometer`, an example of a user's own stage (`kind = "odometer"`): it integrates the
//! distance travelled from the odometry service (`pipeline/sensor/odometry`, speed `v_mps` over
//! `dt_s`), refuses implausible messages (speed above `max_speed_mps`, or a non-positive or
//! non-finite interval) and counts them, and writes `{"odometer": {...}}` into summary.json.
//!
//! It is here to show what makes a binary a process kind: it is built on the runtime
//! (`pipeline_runtime::process_main`), so the supervisor finds it next to itself by its name,
//! validates its settings through `odometer --check` before the run, and runs it like any stage;
//! nothing in the supervisor names it. Its state is plain data with a function per message,
//! tested without iceoryx2 below; `main.rs` only wires it to the ports.

use pipeline_runtime::config::{Issues, ProcessSettings, Validate};
use serde::{Deserialize, Serialize};

/// Settings (`[processes.<name>.settings]`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct OdometerSettings {
    /// Fastest plausible speed, m/s; faster messages are dropped and counted.
    pub max_speed_mps: f64,
}

impl Default for OdometerSettings {
    fn default() -> Self {
        Self { max_speed_mps: 10.0 }
    }
}

impl Validate for OdometerSettings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(
            self.max_speed_mps.is_finite() && self.max_speed_mps > 0.0,
            "max_speed_mps",
            format!("must be a positive speed in m/s, got {}", self.max_speed_mps),
        );
    }
}

impl ProcessSettings for OdometerSettings {}

/// What the `odometer` stage adds to summary.json: a struct, so that its keys and units are
/// declared (`schemars::JsonSchema`), as every stage's part is (docs/summary.schema.json).
#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
pub struct OdometerPart {
    /// The distance travelled and the messages counted.
    pub odometer: Odometer,
}

/// Why a message was not counted.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum Implausible {
    /// |v| above the configured maximum.
    #[error("speed {speed_mps} m/s above max_speed_mps {max_mps}")]
    TooFast {
        /// The message's speed, m/s.
        speed_mps: f64,
        /// The limit, m/s.
        max_mps: f64,
    },
    /// dt not positive, or a value not finite.
    #[error("interval {dt_s} s or speed {speed_mps} m/s is not a positive finite number")]
    BadValues {
        /// The message's interval, s.
        dt_s: f64,
        /// The message's speed, m/s.
        speed_mps: f64,
    },
}

/// The stage's state: distance so far and counts.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Odometer {
    /// Distance travelled, m (the integral of |v| dt).
    pub distance_m: f64,
    /// Odometry time integrated, s.
    pub duration_s: f64,
    /// Messages counted.
    pub messages: u64,
    /// Messages refused as implausible.
    pub implausible: u64,
}

impl Odometer {
    /// Takes one odometry message (`v_mps` over `dt_s`).
    pub fn on_odometry(&mut self, v_mps: f64, dt_s: f64, settings: &OdometerSettings) -> Result<(), Implausible> {
        if !(v_mps.is_finite() && dt_s.is_finite() && dt_s > 0.0) {
            self.implausible += 1;
            return Err(Implausible::BadValues { dt_s, speed_mps: v_mps });
        }
        if v_mps.abs() > settings.max_speed_mps {
            self.implausible += 1;
            return Err(Implausible::TooFast { speed_mps: v_mps, max_mps: settings.max_speed_mps });
        }
        self.distance_m += v_mps.abs() * dt_s;
        self.duration_s += dt_s;
        self.messages += 1;
        Ok(())
    }

    /// This stage's part of summary.json.
    pub fn summary_part(&self) -> OdometerPart {
        OdometerPart { odometer: self.clone() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integrates_speed_and_refuses_implausible_messages() {
        let s = OdometerSettings { max_speed_mps: 2.0 };
        let mut o = Odometer::default();
        o.on_odometry(1.5, 0.1, &s).unwrap();
        o.on_odometry(-1.0, 0.2, &s).unwrap(); // backwards still travels
        assert!(matches!(o.on_odometry(3.0, 0.1, &s), Err(Implausible::TooFast { .. })));
        assert!(matches!(o.on_odometry(1.0, 0.0, &s), Err(Implausible::BadValues { .. })));
        assert!(matches!(o.on_odometry(f64::NAN, 0.1, &s), Err(Implausible::BadValues { .. })));
        assert!((o.distance_m - 0.35).abs() < 1e-12 && (o.duration_s - 0.3).abs() < 1e-12);
        assert_eq!((o.messages, o.implausible), (2, 3));
        assert_eq!(serde_json::to_value(o.summary_part()).unwrap()["odometer"]["messages"], 2);
    }

    #[test]
    fn settings_name_their_key() {
        let mut issues = Issues::at("processes.odo.settings");
        OdometerSettings { max_speed_mps: -1.0 }.validate(&mut issues);
        assert_eq!(issues.len(), 1);
        assert_eq!(issues.iter().next().unwrap().key, "processes.odo.settings.max_speed_mps");
    }
}

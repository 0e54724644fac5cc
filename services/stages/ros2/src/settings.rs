//! The gateway's settings (`[processes.<name>.settings]` with `kind = "ros2"`).

use std::net::IpAddr;

use pipeline_runtime::Validate;
use pipeline_runtime::config::{Issues, ProcessSettings};
pub use ros2_interop::out::{
    Durability, Frames, OutKind, OutRoute as GatewayOut, Reliability, StaticTransform, TfFrom, TfOdom, TopicQos,
};
use ros2_interop::route::InRoute;
use serde::Deserialize;

/// The `ros2` gateway's settings.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2Settings {
    /// Run on plain DDS, as ROS 2 does without SROS2: anyone on the network can read the
    /// gateway's topics and publish into its routes. Required (DDS-Security is not supported
    /// yet): the gateway refuses to start without it. Confine it with `only_networks` or a
    /// network namespace.
    #[serde(default)]
    pub insecure: bool,
    /// The DDS domain (`ROS_DOMAIN_ID`); default: the environment's `ROS_DOMAIN_ID`, else 0.
    #[serde(default)]
    pub domain_id: Option<u16>,
    /// The ROS node's name.
    #[serde(default = "default_node")]
    pub node_name: String,
    /// The node's namespace (`/`: none); relative topic names are resolved in it.
    #[serde(default = "default_namespace")]
    pub namespace: String,
    /// Advertise only these local addresses in DDS discovery (e.g. `["127.0.0.1"]` for one
    /// host); empty: every interface, as any ROS 2 node.
    #[serde(default)]
    pub only_networks: Vec<IpAddr>,
    /// Frame ids of what the gateway publishes.
    #[serde(default)]
    pub frames: Frames,
    /// ROS 2 topics into the pipeline.
    #[serde(default, rename = "in")]
    pub inbound: Vec<GatewayIn>,
    /// Pipeline outputs to ROS 2 topics.
    #[serde(default)]
    pub out: Vec<GatewayOut>,
    /// Fixed transforms published once on `/tf_static` (the sensor mounts).
    #[serde(default)]
    pub static_transforms: Vec<StaticTransform>,
    /// Processes whose end ends the gateway's `out` direction (empty: the first upstream process
    /// to end). A gateway with only `in` routes runs until it is stopped.
    #[serde(default)]
    pub end_after: Vec<String>,
    /// A gateway with only `in` routes ends its stream when nothing has come for this long
    /// after the first message, s (0: never; it runs until it is stopped, as for a live robot).
    #[serde(default)]
    pub end_when_idle_s: f64,
    /// Also write every `out` route's messages (the bytes published) into a rosbag2 MCAP bag
    /// directory of this name under the run's output directory, which `ros2 bag info / play` and
    /// Python `rosbags` read; empty: no bag.
    #[serde(default)]
    pub record_bag: String,
    /// The bag's chunk compression: "zstd" (level 1, as `ros2 bag record`), "lz4" (faster, larger)
    /// or "none".
    #[serde(default)]
    pub record_bag_compression: ros2_interop::BagCompression,
    /// At the end, keep the node up this long so that reliable subscribers get the last
    /// messages, s.
    #[serde(default = "default_linger")]
    pub linger_s: f64,
}

fn default_linger() -> f64 {
    1.0
}

fn default_node() -> String {
    "slam_pipeline".into()
}
fn default_namespace() -> String {
    "/".into()
}

/// A ROS 2 topic into the pipeline: the route (topic, pipeline input and its options, as in a
/// bag replay) and the subscription's QoS (default: the sensor-data profile).
#[derive(Debug, Clone)]
pub struct GatewayIn {
    /// QoS of the subscription.
    pub qos: Option<TopicQos>,
    /// When the pipeline input's subscriber queue is full: `drop` (default: a live sensor never
    /// holds the gateway back; what is dropped is counted) or `wait` (lossless: the gateway
    /// waits, and a reliable ROS publisher is slowed down through DDS).
    pub when_full: WhenFull,
    /// The route.
    pub route: InRoute,
}

/// The gateway's own keys (`qos`, `when_full`), then the route's (an unknown key is refused by
/// the route: serde's `flatten` would let it through).
impl<'de> Deserialize<'de> for GatewayIn {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let mut m = serde_json::Map::<String, serde_json::Value>::deserialize(d)?;
        let qos = m
            .remove("qos")
            .map(serde_json::from_value)
            .transpose()
            .map_err(|e| D::Error::custom(format!("qos: {e}")))?;
        let when_full = m
            .remove("when_full")
            .map(serde_json::from_value)
            .transpose()
            .map_err(|e| D::Error::custom(format!("when_full: {e}")))?
            .unwrap_or_default();
        let route = serde_json::from_value(serde_json::Value::Object(m)).map_err(D::Error::custom)?;
        Ok(Self { qos, when_full, route })
    }
}

/// What an `in` route does when the pipeline input is full.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum WhenFull {
    /// Drop the message for that subscriber (counted).
    #[default]
    Drop,
    /// Wait for room.
    Wait,
}

impl Validate for Ros2Settings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(
            self.insecure,
            "insecure",
            "the gateway speaks plain DDS (DDS-Security / SROS2 is not supported yet): anyone on the network can \
             read its topics and publish into its routes; set `insecure = true` to run it anyway (and confine it \
             with `only_networks` or a network namespace)",
        );
        issues.check(
            ros2_client::NodeName::new(&self.namespace, &self.node_name).is_ok(),
            "node_name",
            format!("`{}` in namespace `{}` is not a ROS 2 node name", self.node_name, self.namespace),
        );
        if let Some(d) = self.domain_id {
            issues.check(d <= 232, "domain_id", format!("{d}: a ROS 2 domain id is 0-232"));
        }
        issues.check(
            !self.inbound.is_empty() || !self.out.is_empty() || !self.static_transforms.is_empty(),
            "in",
            "no routes: give `in` or `out` routes",
        );
        let mut topics = std::collections::BTreeSet::new();
        for (i, r) in self.inbound.iter().enumerate() {
            issues.nested(format!("in[{i}]"), &r.route);
            issues.check(topics.insert(r.route.topic.clone()), format!("in[{i}].topic"), "routed twice");
            if let Some(q) = r.qos {
                issues.check(q.depth >= 1, format!("in[{i}].qos.depth"), "must be >= 1");
            }
        }
        ros2_interop::out::validate(&self.out, &self.frames, &self.static_transforms, &mut topics, issues);
        for (k, v) in [("end_when_idle_s", self.end_when_idle_s), ("linger_s", self.linger_s)] {
            issues.check(v.is_finite() && v >= 0.0, k, "must be >= 0 s");
        }
    }
}

impl ProcessSettings for Ros2Settings {}

impl Ros2Settings {
    /// The DDS domain: the setting, else `ROS_DOMAIN_ID`, else 0.
    pub fn domain(&self) -> Result<u16, String> {
        if let Some(d) = self.domain_id {
            return Ok(d);
        }
        match std::env::var("ROS_DOMAIN_ID") {
            Ok(v) if !v.trim().is_empty() => v
                .trim()
                .parse::<u16>()
                .ok()
                .filter(|d| *d <= 232)
                .ok_or_else(|| format!("ROS_DOMAIN_ID `{v}` is not 0-232")),
            _ => Ok(0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Ros2Settings, String> {
        toml::from_str(text).map_err(|e| e.to_string())
    }

    #[test]
    fn routes_parse_with_their_defaults_and_a_misspelt_key_is_refused() {
        let s = parse(
            r#"
insecure = true
[[in]]
topic = "/scan"
service = "laser"
body_from_laser = [0.1, 0.0, 0.0]
qos = { reliability = "reliable", durability = "volatile", depth = 10 }
[[out]]
what = "map"
[[out]]
what = "tf"
from = "grid_slam"
odom = "planar_odometry"
"#,
        )
        .unwrap();
        assert_eq!(s.inbound[0].route.body_from_laser, [0.1, 0.0, 0.0]);
        assert_eq!(s.inbound[0].qos.unwrap().depth, 10);
        assert_eq!(s.out[0].topic(), "/map");
        assert_eq!(s.out[0].qos(), TopicQos::MAP);
        assert_eq!((s.out[1].from, s.out[1].odom), (TfFrom::GridSlam, TfOdom::PlanarOdometry));
        let mut issues = Issues::at("s");
        s.validate(&mut issues);
        assert!(issues.is_empty(), "{issues:?}");
        let e = parse("[[in]]\ntopic = \"/scan\"\nservice = \"laser\"\nbody_from_lasr = [0, 0, 0]\n").unwrap_err();
        assert!(e.contains("body_from_lasr"), "{e}");
        let e = parse("[[out]]\nwhat = \"maps\"\n").unwrap_err();
        assert!(e.contains("maps"), "{e}");
    }

    #[test]
    fn bad_values_are_named_by_key() {
        let s = parse(
            "insecure = true\ndomain_id = 300\n[[in]]\ntopic = \"scan\"\nservice = \"laser\"\n[[out]]\nwhat = \"map\"\ntopic = \"/my map\"\n",
        )
        .unwrap();
        let mut issues = Issues::at("s");
        s.validate(&mut issues);
        let keys: Vec<&str> = issues.iter().map(|i| i.key.as_str()).collect();
        assert!(
            keys.contains(&"s.domain_id") && keys.contains(&"s.in[0].topic") && keys.contains(&"s.out[0].topic"),
            "{keys:?}"
        );
    }
}

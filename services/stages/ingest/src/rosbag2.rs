//! Replay of a ROS 2 bag (`source = "rosbag2"`): a rosbag2 directory in MCAP storage or one
//! `.mcap` file, read in file order by [`ros2_interop::BagReader`], each routed topic's messages
//! decoded ([`ros2_interop::route`]) and published on the route's pipeline input. Stamps are the
//! messages' `header.stamp` (or the bag's receive times with `stamps = "log_time"`), so a
//! real-time replay keeps the bag's own clock.
//!
//! Nothing is lost silently: damaged chunks and a truncated file (named with their byte offset),
//! messages of another type than their route expects, messages that do not decode or break what
//! the pipeline input needs (named with topic, file and offset, warned once per route and kind)
//! are counted in summary.json (`data_warts`, and per route in `rosbag2`); topics without a route
//! are counted there too and named in the log once.

use crate::summary::{Rosbag2Details, RouteCounts, SourceDetails};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use pipeline_runtime::Issues;
use pipeline_runtime::Validate;
use ros2_interop::Message;
use ros2_interop::msgs::CameraInfo;
use ros2_interop::route::{Decoded, InRoute, InService, RouteDecoder};
use ros2_interop::{BagMessage, BagReader};
use serde::{Deserialize, Serialize};

use crate::{Item, Source, SourceError};

/// Which clock stamps the replayed messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum BagStamps {
    /// Each message's `header.stamp` (its measurement time).
    #[default]
    Header,
    /// The time the recorder received it (the bag's log time).
    LogTime,
}

/// rosbag2 replay settings (`[processes.<name>.settings.rosbag2]`).
#[derive(Debug, Clone, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct Rosbag2Settings {
    /// The bag: a directory with `metadata.yaml`, or one `.mcap` file; relative to the config's
    /// directory.
    pub path: PathBuf,
    /// Which clock stamps the messages.
    pub stamps: BagStamps,
    /// Topic → pipeline input (`[[processes.<name>.settings.rosbag2.routes]]`).
    pub routes: Vec<InRoute>,
}

impl Validate for Rosbag2Settings {
    fn validate(&self, issues: &mut Issues) {
        issues.check(!self.path.as_os_str().is_empty(), "path", "no bag given");
        issues.check(!self.routes.is_empty(), "routes", "no routes: nothing of the bag would be replayed");
        let mut topics = BTreeSet::new();
        for (i, r) in self.routes.iter().enumerate() {
            issues.nested(format!("routes[{i}]"), r);
            issues.check(
                topics.insert(r.topic.clone()),
                format!("routes[{i}].topic"),
                format!("`{}` is routed twice", r.topic),
            );
        }
    }
}

/// The `rosbag2` source.
pub struct Rosbag2Source {
    path: PathBuf,
    reader: BagReader,
    stamps: BagStamps,
    routes: BTreeMap<String, (RouteDecoder, RouteCounts)>,
    unrouted: BTreeMap<String, u64>,
    warned: BTreeSet<(String, &'static str)>,
    done: bool,
}

impl Rosbag2Source {
    /// Opens the bag named in `settings` (relative to `config_dir`).
    pub fn open(config_dir: &Path, settings: &Rosbag2Settings) -> Result<Self, SourceError> {
        let path = crate::resolve(config_dir, &settings.path);
        let reader = BagReader::open(&path).map_err(|e| SourceError::Settings(format!("rosbag2: {e}")))?;
        let routes = settings
            .routes
            .iter()
            .map(|r| {
                let counts = RouteCounts { service: r.service.service().to_string(), ..Default::default() };
                (r.topic.clone(), (RouteDecoder::new(r.clone()), counts))
            })
            .collect();
        Ok(Self {
            path,
            reader,
            stamps: settings.stamps,
            routes,
            unrouted: BTreeMap::new(),
            warned: BTreeSet::new(),
            done: false,
        })
    }

    fn warn_once(&mut self, topic: &str, kind: &'static str, msg: &BagMessage, what: &str) {
        if self.warned.insert((topic.to_string(), kind)) {
            tracing::warn!(
                topic,
                kind,
                "rosbag2 {}@{}: {what} (skipped; counted in summary.json, warned once per topic and kind)",
                msg.file.display(),
                msg.offset
            );
        }
    }

    fn log_problems(&mut self) {
        for p in self.reader.take_problems() {
            tracing::warn!("rosbag2 {p}");
        }
    }

    /// The item of one bag message, or `None` when it is skipped (and counted).
    fn item(&mut self, msg: &BagMessage) -> Option<Item> {
        let topic: &str = &msg.topic;
        // A depth-image route's CameraInfo: kept by that route's decoder.
        if let Some((decoder, counts)) = self
            .routes
            .values_mut()
            .find(|(d, _)| d.route.service == InService::DepthImage && d.route.camera_info == topic)
        {
            match ros2_interop::cdr::decode::<CameraInfo>(&msg.data, CameraInfo::TYPE_NAME) {
                Ok(info) => {
                    counts.camera_infos += 1;
                    decoder.set_camera_info(info);
                }
                Err(e) => {
                    counts.undecodable += 1;
                    let what = format!("`{topic}`: {e}");
                    self.warn_once(topic, "undecodable", msg, &what);
                }
            }
            return None;
        }
        let Some((decoder, counts)) = self.routes.get_mut(topic) else {
            let n = self.unrouted.entry(topic.to_string()).or_default();
            *n += 1;
            if *n == 1 {
                tracing::info!(topic, type_name = %msg.type_name, "rosbag2: a topic without a route: its messages are skipped (counted in summary.json)");
            }
            return None;
        };
        let want = decoder.route.service.ros_type();
        if !msg.type_name.is_empty() && &*msg.type_name != want {
            counts.wrong_type += 1;
            let what = format!("`{topic}` is {} in the bag; its route needs {want}", msg.type_name);
            self.warn_once(topic, "wrong_type", msg, &what);
            return None;
        }
        match decoder.decode(&msg.data) {
            Ok(d) => {
                let item = to_item(d, self.stamps, msg.log_time_ns, counts);
                if item.is_some() {
                    counts.published += 1;
                }
                item
            }
            Err(e) => {
                let kind = e.kind();
                if kind == "undecodable" {
                    counts.undecodable += 1;
                } else {
                    counts.invalid += 1;
                }
                let what = format!("`{topic}`: {e}");
                self.warn_once(topic, kind, msg, &what);
                None
            }
        }
    }
}

fn to_item(d: Decoded, stamps: BagStamps, log_time_ns: u64, counts: &mut RouteCounts) -> Option<Item> {
    let s = |header_ns: u64| if stamps == BagStamps::LogTime { log_time_ns } else { header_ns };
    Some(match d {
        Decoded::Laser { stamp_ns, header, ranges } => Item::Laser { stamp_ns: s(stamp_ns), header, ranges },
        Decoded::PlanarOdometry { stamp_ns, odometry } => Item::PlanarOdometry { stamp_ns: s(stamp_ns), odometry },
        Decoded::Odometry { stamp_ns, input } => Item::Odometry { stamp_ns: s(stamp_ns), input },
        Decoded::Cloud { stamp_ns, points, non_finite } => {
            counts.non_finite_points += non_finite as u64;
            Item::Cloud { stamp_ns: s(stamp_ns), world_from_sensor: None, points }
        }
        Decoded::Heading { stamp_ns, reading } => Item::Heading { stamp_ns: s(stamp_ns), reading },
        Decoded::Depth { stamp_ns, reading } => Item::Depth { stamp_ns: s(stamp_ns), reading },
        Decoded::BuoyRange { stamp_ns, range } => Item::BuoyRanges { stamp_ns: s(stamp_ns), ranges: vec![range] },
        Decoded::Nothing => return None,
    })
}

impl Source for Rosbag2Source {
    fn next_item(&mut self) -> Result<Option<Item>, SourceError> {
        loop {
            let next = self.reader.next_message().map_err(|e| SourceError::Settings(format!("rosbag2: {e}")));
            self.log_problems();
            let Some(msg) = next? else {
                if !self.done {
                    self.done = true;
                    let never: Vec<&String> = self
                        .routes
                        .iter()
                        .filter(|(_, (_, c))| c.published + c.wrong_type == 0)
                        .map(|(t, _)| t)
                        .collect();
                    if !never.is_empty() {
                        tracing::warn!(
                            "rosbag2: routed topics with no message in the bag: {never:?} (the bag has {:?})",
                            self.reader.topics()
                        );
                    }
                }
                return Ok(None);
            };
            if let Some(item) = self.item(&msg) {
                return Ok(Some(item));
            }
        }
    }

    fn progress(&self) -> Option<f64> {
        Some(self.reader.progress())
    }

    fn finish(&mut self, _out_dir: &Path) -> Result<(), SourceError> {
        Ok(())
    }

    fn describe(&self) -> String {
        let routes: Vec<String> =
            self.routes.iter().map(|(t, (d, _))| format!("{t} → {}", d.route.service.service())).collect();
        format!(
            "rosbag2 {} ({} file(s)); routes: {}",
            self.path.display(),
            self.reader.files().len(),
            routes.join(", ")
        )
    }

    fn warts(&self) -> BTreeMap<&'static str, u64> {
        let w = self.reader.warts();
        let mut m = BTreeMap::new();
        let sum = |f: fn(&RouteCounts) -> u64| self.routes.values().map(|(_, c)| f(c)).sum::<u64>();
        for (k, v) in [
            ("corrupt_chunks", w.corrupt_chunks),
            ("file_truncated", w.truncated_files),
            ("unknown_channel_messages", w.unknown_channel_messages),
            ("not_cdr_messages", w.not_cdr_messages),
            ("wrong_type_messages", sum(|c| c.wrong_type)),
            ("undecodable_messages", sum(|c| c.undecodable)),
            ("invalid_messages", sum(|c| c.invalid)),
        ] {
            if v > 0 {
                m.insert(k, v);
            }
        }
        m
    }

    fn details(&self) -> SourceDetails {
        SourceDetails {
            rosbag2: Some(Rosbag2Details {
                path: self.path.clone(),
                files: self.reader.files().to_vec(),
                routes: self.routes.iter().map(|(t, (_, c))| (t.clone(), c.clone())).collect(),
                unrouted_messages: self.unrouted.clone(),
                bag: self.reader.warts().clone(),
            }),
        }
    }
}

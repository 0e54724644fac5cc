//! ROS 2 → pipeline: each `in` route's DDS reader is read in the stage's loop with a serde seed
//! that decodes the message straight from RustDDS's buffer and writes the wire values into a
//! loaned iceoryx2 sample (a `PointCloud2`'s points are copied once, from the DDS buffer into
//! shared memory).

use std::cell::RefCell;
use std::collections::HashMap;
use std::fmt;

use pipeline_runtime::{Delivery, Output, PortError, Runtime, StageError};
use ros2_client::Subscription;
use ros2_interop::convert::{self, CloudLayout, ConvertError};
use ros2_interop::msgs::{CameraInfo, PointCloud2};
use ros2_interop::route::{Decoded, InService, RouteDecoder};
use serde::de::{DeserializeSeed, Deserializer};
use serde::{Deserialize, Serialize};
use shared_types::services::{self, *};
use shared_types::{
    BuoyRange, CloudHeader, CloudPoint, DepthReading, FRAME_SENSOR, HeadingReading, LaserRange, LaserScanHeader,
    MsgHeader, OdometryInput, PlanarOdometry,
};

use crate::settings::GatewayIn;

/// What taking one DDS sample did (the value ros2-client's reader returns through the seed).
#[derive(Debug)]
pub enum Taken {
    /// Published into the pipeline at `sent_unix_ns` (CLOCK_REALTIME, to compare with DDS's).
    Sent {
        /// When the sample was sent into shared memory, ns since the Unix epoch.
        sent_unix_ns: i64,
        /// Cloud points left out (NaN / Inf).
        non_finite_points: usize,
    },
    /// The message breaks what the pipeline input needs.
    Invalid(ConvertError),
    /// The first message of an increments route: nothing to publish yet.
    Nothing,
    /// The pipeline port failed.
    PortFailed(String),
}

/// Never used directly: samples are always taken with the route's seed.
impl<'de> Deserialize<'de> for Taken {
    fn deserialize<D: Deserializer<'de>>(_d: D) -> Result<Self, D::Error> {
        Err(serde::de::Error::custom("a gateway sample is taken with its route's seed"))
    }
}

fn unix_ns() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as i64).unwrap_or(0)
}

/// The pipeline outputs the `in` routes feed (only those some route uses are opened).
#[derive(Default)]
pub struct InPorts {
    laser: Option<Output<[LaserRange], LaserScanHeader>>,
    planar: Option<Output<PlanarOdometry, MsgHeader>>,
    odometry: Option<Output<OdometryInput, MsgHeader>>,
    cloud: Option<Output<[CloudPoint], CloudHeader>>,
    heading: Option<Output<HeadingReading, MsgHeader>>,
    depth: Option<Output<DepthReading, MsgHeader>>,
    buoys: Option<Output<[BuoyRange], MsgHeader>>,
}

fn missing(service: &str) -> PortError {
    PortError::Io { service: service.into(), op: "send", reason: "the output is not open".into() }
}

fn header(stamp_ns: u64) -> MsgHeader {
    MsgHeader { stamp_ns, ..Default::default() }
}

impl InPorts {
    /// Opens the outputs of `routes`: `wait` routes wait for a full subscriber (lossless,
    /// slowing the gateway down), the others drop for it (counted by the runtime).
    pub fn open(rt: &mut Runtime, routes: &[GatewayIn]) -> Result<Self, StageError> {
        let mut p = InPorts::default();
        let qos = |s: &str| services::service_spec(s).map(|s| s.qos).ok_or_else(|| missing(s));
        for r in routes {
            let delivery = if r.when_full == crate::settings::WhenFull::Wait {
                Delivery::WaitWhenFull { max_wait: None }
            } else {
                Delivery::DiscardWhenFull
            };
            match r.route.service {
                InService::Laser if p.laser.is_none() => {
                    p.laser = Some(rt.output_slice_with_qos(LASER, &qos(LASER)?, 1081, delivery)?)
                }
                InService::PlanarOdometry if p.planar.is_none() => {
                    p.planar = Some(rt.output_with_qos(PLANAR_ODOMETRY, &qos(PLANAR_ODOMETRY)?, delivery)?)
                }
                InService::Odometry if p.odometry.is_none() => {
                    p.odometry = Some(rt.output_with_qos(ODOMETRY, &qos(ODOMETRY)?, delivery)?)
                }
                InService::Cloud | InService::DepthImage if p.cloud.is_none() => {
                    p.cloud = Some(rt.output_slice_with_qos(CLOUD, &qos(CLOUD)?, 65_536, delivery)?)
                }
                InService::Heading if p.heading.is_none() => {
                    p.heading = Some(rt.output_with_qos(HEADING, &qos(HEADING)?, delivery)?)
                }
                InService::Depth if p.depth.is_none() => {
                    p.depth = Some(rt.output_with_qos(DEPTH, &qos(DEPTH)?, delivery)?)
                }
                InService::BuoyRanges if p.buoys.is_none() => {
                    p.buoys = Some(rt.output_slice_with_qos(BUOY_RANGES, &qos(BUOY_RANGES)?, 16, delivery)?)
                }
                _ => {}
            }
        }
        Ok(p)
    }

    /// Messages sent on every output.
    pub fn sent(&self) -> u64 {
        let s = |o: Option<u64>| o.unwrap_or(0);
        s(self.laser.as_ref().map(|o| o.sent()))
            + s(self.planar.as_ref().map(|o| o.sent()))
            + s(self.odometry.as_ref().map(|o| o.sent()))
            + s(self.cloud.as_ref().map(|o| o.sent()))
            + s(self.heading.as_ref().map(|o| o.sent()))
            + s(self.depth.as_ref().map(|o| o.sent()))
            + s(self.buoys.as_ref().map(|o| o.sent()))
    }

    fn publish(&mut self, d: Decoded) -> Result<bool, PortError> {
        match d {
            Decoded::Laser { stamp_ns, header: h, ranges } => {
                let o = self.laser.as_mut().ok_or_else(|| missing(LASER))?;
                let mut s = o.loan_slice_uninit(ranges.len())?.write_from_fn(|i| LaserRange { range_m: ranges[i] });
                *s.user_header_mut() = LaserScanHeader { msg: header(stamp_ns), ..h };
                o.send(s)?;
            }
            Decoded::PlanarOdometry { stamp_ns, odometry } => {
                self.planar.as_mut().ok_or_else(|| missing(PLANAR_ODOMETRY))?.send_value(header(stamp_ns), odometry)?;
            }
            Decoded::Odometry { stamp_ns, input } => {
                self.odometry.as_mut().ok_or_else(|| missing(ODOMETRY))?.send_value(header(stamp_ns), input)?;
            }
            Decoded::Heading { stamp_ns, reading } => {
                self.heading.as_mut().ok_or_else(|| missing(HEADING))?.send_value(header(stamp_ns), reading)?;
            }
            Decoded::Depth { stamp_ns, reading } => {
                self.depth.as_mut().ok_or_else(|| missing(DEPTH))?.send_value(header(stamp_ns), reading)?;
            }
            Decoded::BuoyRange { stamp_ns, range } => {
                let o = self.buoys.as_mut().ok_or_else(|| missing(BUOY_RANGES))?;
                let mut s = o.loan_slice_uninit(1)?.write_from_fn(|_| range);
                *s.user_header_mut() = header(stamp_ns);
                o.send(s)?;
            }
            Decoded::Cloud { stamp_ns, points, .. } => {
                if points.is_empty() {
                    return Ok(false);
                }
                let o = self.cloud.as_mut().ok_or_else(|| missing(CLOUD))?;
                let mut s = o.loan_slice_uninit(points.len())?.write_from_fn(|i| CloudPoint {
                    x_m: points[i][0],
                    y_m: points[i][1],
                    z_m: points[i][2],
                });
                *s.user_header_mut() = CloudHeader { msg: header(stamp_ns), frame: FRAME_SENSOR, ..Default::default() };
                o.send(s)?;
            }
            Decoded::Nothing => return Ok(false),
        }
        Ok(true)
    }

    /// A cloud's finite points, copied once from the DDS buffer into a loaned sample.
    fn publish_cloud(&mut self, msg: &PointCloud2<'_>) -> Result<Result<usize, ConvertError>, PortError> {
        let stamp_ns = match convert::stamp_ns(&msg.header) {
            Ok(t) => t,
            Err(e) => return Ok(Err(e)),
        };
        let layout = match CloudLayout::of(msg) {
            Ok(l) => l,
            Err(e) => return Ok(Err(e)),
        };
        let data = msg.data.as_slice();
        let o = self.cloud.as_mut().ok_or_else(|| missing(CLOUD))?;
        let header = CloudHeader { msg: header(stamp_ns), frame: FRAME_SENSOR, ..Default::default() };
        if msg.is_dense && !layout.is_empty() {
            // Declared without invalid points: one pass, checked as it goes; a cloud that breaks
            // its word is not sent and takes the two-pass path below.
            let mut all_finite = true;
            let mut loan = o.loan_slice_uninit(layout.len())?;
            let written = layout.fill(data, loan.payload_mut(), |slot, p| {
                all_finite &= p[0].is_finite() & p[1].is_finite() & p[2].is_finite();
                slot.write(CloudPoint { x_m: p[0], y_m: p[1], z_m: p[2] });
            });
            if all_finite && written == layout.len() {
                // SAFETY: `fill` wrote every one of the loan's `layout.len()` elements.
                let mut s = unsafe { loan.assume_init() };
                *s.user_header_mut() = header;
                o.send(s)?;
                return Ok(Ok(0));
            }
        }
        let n = layout.count_finite(data);
        if n == 0 {
            return Ok(Err(ConvertError::Invalid { field: "data", why: "no finite point".into() }));
        }
        let point = |i: usize| {
            let p = layout.point(data, i);
            CloudPoint { x_m: p[0], y_m: p[1], z_m: p[2] }
        };
        let loan = o.loan_slice_uninit(n)?;
        let mut s = if n == layout.len() {
            loan.write_from_fn(point)
        } else {
            let keep = layout.finite_indices(data);
            loan.write_from_fn(|i| point(keep[i] as usize))
        };
        *s.user_header_mut() = header;
        o.send(s)?;
        Ok(Ok(layout.len() - n))
    }
}

/// The seed one sample is taken with.
#[derive(Clone, Copy)]
struct Seed<'a> {
    decoder: &'a RefCell<RouteDecoder>,
    ports: &'a RefCell<InPorts>,
}

impl<'de> DeserializeSeed<'de> for Seed<'_> {
    type Value = Taken;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Taken, D::Error> {
        let mut decoder = self.decoder.borrow_mut();
        let mut ports = self.ports.borrow_mut();
        let port = |e: PortError| Taken::PortFailed(e.to_string());
        if decoder.route.service == InService::Cloud {
            let msg = PointCloud2::deserialize(d)?;
            return Ok(match ports.publish_cloud(&msg) {
                Ok(Ok(non_finite_points)) => Taken::Sent { sent_unix_ns: unix_ns(), non_finite_points },
                Ok(Err(e)) => Taken::Invalid(e),
                Err(e) => port(e),
            });
        }
        Ok(match decoder.decode_from(d)? {
            Ok(decoded) => match ports.publish(decoded) {
                Ok(true) => Taken::Sent { sent_unix_ns: unix_ns(), non_finite_points: 0 },
                Ok(false) => Taken::Nothing,
                Err(e) => port(e),
            },
            Err(e) => Taken::Invalid(e),
        })
    }
}

/// Latency percentiles of a route, ms (from the pipeline's publish for an out route: with a
/// snapshot's coalescing).
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct LatencyMs {
    /// Samples.
    pub count: u64,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest.
    pub max: f64,
}

/// An HDR histogram of µs.
pub struct Hist(hdrhistogram::Histogram<u64>);

impl Default for Hist {
    fn default() -> Self {
        Hist(hdrhistogram::Histogram::new_with_bounds(1, 60_000_000, 3).expect("valid histogram bounds"))
    }
}

impl fmt::Debug for Hist {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Hist({})", self.0.len())
    }
}

impl Hist {
    /// Records `ns` (clamped to the bounds).
    pub fn record_ns(&mut self, ns: i64) {
        let us = (ns.max(0) as u64 / 1000).clamp(1, 60_000_000);
        let _ = self.0.record(us);
    }
    /// Its percentiles.
    pub fn ms(&self) -> LatencyMs {
        let q = |p: f64| self.0.value_at_quantile(p) as f64 / 1000.0;
        LatencyMs { count: self.0.len(), p50: q(0.5), p99: q(0.99), max: self.0.max() as f64 / 1000.0 }
    }
}

/// An `in` route: ROS 2 messages into a pipeline service.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(rename = "Ros2InRouteSummary")]
pub struct InRouteSummary {
    /// The ROS 2 message type.
    #[serde(rename = "type")]
    pub ros_type: String,
    /// What the route did.
    pub counts: InCounts,
    /// Latency of its messages.
    pub latency_ms: InLatency,
}

/// An `in` route's latency, ms.
#[derive(Debug, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct InLatency {
    /// From the publisher's source stamp to the gateway's take (DDS and the publisher's queue).
    pub dds_transport: LatencyMs,
    /// From the take to the pipeline sample sent.
    pub gateway: LatencyMs,
    /// Converting and sending alone.
    pub take_to_sent: LatencyMs,
}

/// Counters of an `in` route (summary.json `ros2.in.<topic>`).
#[derive(Debug, Default, Clone, Serialize, serde::Deserialize, schemars::JsonSchema)]
#[schemars(rename = "Ros2InCounts")]
pub struct InCounts {
    /// The pipeline service it feeds.
    pub service: String,
    /// DDS samples taken.
    pub received: u64,
    /// Published into the pipeline.
    pub published: u64,
    /// Not decodable as the route's type (truncated, wrong layout).
    pub undecodable: u64,
    /// Decoded, but a field breaks what the pipeline input needs.
    pub invalid: u64,
    /// Sequence numbers a publisher skipped: lost in DDS before the gateway took them (a
    /// best-effort link, or a reader history that overflowed).
    pub lost_in_dds: u64,
    /// The pipeline port failed.
    pub port_failed: u64,
    /// Cloud points left out (NaN / Inf; a depth image's zero or out-of-range pixels).
    pub non_finite_points: u64,
    /// CameraInfo messages taken (a depth-image route).
    pub camera_infos: u64,
    /// ROS publishers matched at the end (from DDS discovery's matching events).
    pub publishers: usize,
    /// Remote publishers whose QoS cannot match this route's (nothing of theirs arrives).
    pub qos_incompatible: u64,
    /// Remote publishers on this topic of another type (nothing of theirs arrives).
    pub type_mismatch: u64,
}

/// One `in` route.
pub struct InRoute {
    /// The topic.
    pub topic: String,
    decoder: RefCell<RouteDecoder>,
    /// Its DDS reader.
    pub sub: Subscription<Taken>,
    /// A depth-image route's CameraInfo reader.
    pub info_sub: Option<Subscription<CameraInfo>>,
    /// The remote writers matched to the reader now.
    pub remotes: std::collections::BTreeSet<ros2_client::dds::rustdds::GUID>,
    /// Remote publishers already counted as not matching (discovery may report one more than
    /// once: each update of its discovery data).
    unmatched: std::collections::BTreeSet<ros2_client::dds::rustdds::GUID>,
    /// Its counters.
    pub counts: InCounts,
    last_seq: HashMap<String, i64>,
    warned: std::collections::BTreeSet<&'static str>,
    /// DDS source timestamp → DDS receive (the transport).
    pub transport: Hist,
    /// DDS receive → sent into shared memory (what the gateway adds: its wake-up, the
    /// decode, the copy into shared memory, the send; for a fragmented sample also RustDDS's
    /// reassembly after the first fragment, whose arrival stamps the sample).
    pub gateway: Hist,
    /// The take → sent into shared memory (the decode, the one copy, the send).
    pub convert: Hist,
}

impl InRoute {
    /// A route over its reader.
    pub fn new(cfg: &GatewayIn, sub: Subscription<Taken>, info_sub: Option<Subscription<CameraInfo>>) -> Self {
        Self {
            topic: cfg.route.topic.clone(),
            decoder: RefCell::new(RouteDecoder::new(cfg.route.clone())),
            sub,
            info_sub,
            remotes: Default::default(),
            unmatched: Default::default(),
            counts: InCounts { service: cfg.route.service.service().to_string(), ..Default::default() },
            last_seq: HashMap::new(),
            warned: Default::default(),
            transport: Hist::default(),
            gateway: Hist::default(),
            convert: Hist::default(),
        }
    }

    fn warn_once(&mut self, kind: &'static str, what: &str) {
        if self.warned.insert(kind) {
            tracing::warn!(topic = %self.topic, kind, "{what} (counted in summary.json; warned once per topic and kind)");
        }
    }

    /// Takes every sample waiting on the reader; returns how many.
    pub fn drain(&mut self, ports: &RefCell<InPorts>) -> usize {
        let mut n = 0;
        if let Some(info) = self.info_sub.take() {
            loop {
                match info.take() {
                    Ok(Some((ci, _))) => {
                        self.counts.camera_infos += 1;
                        self.decoder.borrow_mut().set_camera_info(ci);
                    }
                    Ok(None) => break,
                    Err(e) => {
                        self.counts.undecodable += 1;
                        self.warn_once("undecodable", &format!("a CameraInfo that does not decode: {e:?}"));
                    }
                }
            }
            self.info_sub = Some(info);
        }
        loop {
            let seed = Seed { decoder: &self.decoder, ports };
            let taken_at = unix_ns();
            let r = self.sub.take_seed(seed);
            match r {
                Ok(None) => return n,
                Ok(Some((taken, info))) => {
                    n += 1;
                    self.counts.received += 1;
                    let key = format!("{:?}", info.publisher_gid());
                    let seq = info.sequence_number();
                    if let Some(last) = self.last_seq.insert(key, seq)
                        && seq > last + 1
                    {
                        self.counts.lost_in_dds += (seq - last - 1) as u64;
                        let what = format!("{} message(s) lost in DDS before the gateway took them", seq - last - 1);
                        self.warn_once("lost_in_dds", &what);
                    }
                    match taken {
                        Taken::Sent { sent_unix_ns, non_finite_points } => {
                            self.counts.published += 1;
                            self.counts.non_finite_points += non_finite_points as u64;
                            if let (Some(src), Some(rcv)) = (info.source_timestamp(), info.received_timestamp()) {
                                self.transport.record_ns(rcv.to_nanos() - src.to_nanos());
                                self.gateway.record_ns(sent_unix_ns - rcv.to_nanos());
                                self.convert.record_ns(sent_unix_ns - taken_at);
                            }
                        }
                        Taken::Nothing => {}
                        Taken::Invalid(e) => {
                            self.counts.invalid += 1;
                            self.warn_once("invalid", &format!("a message was not used: {e}"));
                        }
                        Taken::PortFailed(e) => {
                            self.counts.port_failed += 1;
                            self.warn_once("port_failed", &format!("the pipeline input failed: {e}"));
                        }
                    }
                }
                Err(e) => {
                    n += 1;
                    self.counts.received += 1;
                    self.counts.undecodable += 1;
                    let what = format!("a sample that does not decode as {}: {e:?}", self.counts_type());
                    self.warn_once("undecodable", &what);
                }
            }
        }
    }

    /// A remote publisher whose QoS cannot match (discovery said so); counted once per publisher.
    pub fn qos_incompatible(&mut self, remote: ros2_client::dds::rustdds::GUID, requested: &str, offered: &str) {
        if !self.unmatched.insert(remote) {
            return;
        }
        self.counts.qos_incompatible += 1;
        let what = format!(
            "a publisher offers QoS ({offered}) that cannot match the route's ({requested}): nothing of it arrives"
        );
        self.warn_once("qos_incompatible", &what);
    }

    /// A remote publisher on the topic, of DDS type `dds_type`; one of another type is counted
    /// once per publisher.
    pub fn remote_type(&mut self, remote: ros2_client::dds::rustdds::GUID, dds_type: &str) {
        let want = ros2_interop::msgs::dds_type_name(self.counts_type());
        if dds_type != want && self.unmatched.insert(remote) {
            self.counts.type_mismatch += 1;
            let what = format!(
                "a publisher of type `{dds_type}` on this topic; the route takes `{want}`: nothing of it arrives"
            );
            self.warn_once("type_mismatch", &what);
        }
    }

    fn counts_type(&self) -> &'static str {
        self.decoder.borrow().route.service.ros_type()
    }

    /// The route's part of summary.json.
    pub fn summary(&self) -> InRouteSummary {
        InRouteSummary {
            ros_type: self.counts_type().to_string(),
            counts: self.counts.clone(),
            latency_ms: InLatency {
                dds_transport: self.transport.ms(),
                gateway: self.gateway.ms(),
                take_to_sent: self.convert.ms(),
            },
        }
    }
}

//! The gateway as a [`Stage`]: its ROS 2 node, the `in` routes' readers (woken by
//! [`crate::dds::DdsWaker`]) and the `out` routes' publishers.

use std::cell::RefCell;
use std::time::{Duration, Instant};

use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{ProcessContext, Runtime, StageError, Wake};
use ros2_client::Publisher;
use ros2_interop::msgs::{CameraInfo, Message, TFMessage};
use ros2_interop::route::InService;

use crate::dds::{DdsWaker, RosNode, err};
use crate::inbound::{InPorts, InRoute, Taken};
use crate::outbound::Outbound;
use crate::settings::{Ros2Settings, TopicQos};
use crate::summary::{GatewaySummary, OutRouteSummary, Ros2Part};

/// The `ros2` gateway stage.
pub struct Ros2Stage {
    name: String,
    settings: Ros2Settings,
    node: RosNode,
    ins: Vec<InRoute>,
    ports: RefCell<InPorts>,
    out: Outbound,
    _waker: Option<DdsWaker>,
    _static_tf: Option<Publisher<TFMessage>>,
    static_transforms: usize,
    last_in: Option<Instant>,
}

fn unix_now_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

fn stage_err(e: crate::dds::DdsError) -> StageError {
    StageError::stage(e)
}

impl Ros2Stage {
    /// `/tf_static`: the configured mounts, and `map → odom` = identity when a `tf` route has
    /// no odometry of its own.
    fn static_tf(
        node: &mut RosNode,
        s: &Ros2Settings,
        bag: Option<&mut ros2_interop::BagSink>,
    ) -> Result<(Option<Publisher<TFMessage>>, usize), StageError> {
        let Some(msg) = ros2_interop::out::static_tf(&s.static_transforms, &s.out, &s.frames) else {
            return Ok((None, 0));
        };
        let topic = node.topic("/tf_static", TFMessage::TYPE_NAME, TopicQos::MAP).map_err(stage_err)?;
        let publisher: Publisher<TFMessage> =
            node.node.create_publisher(&topic, None).map_err(|e| stage_err(err("publisher on `/tf_static`")(&e)))?;
        let n = msg.transforms.len();
        if let Some(bag) = bag {
            let bytes = ros2_interop::cdr::encode(&msg).map_err(StageError::stage)?;
            bag.write("/tf_static", unix_now_ns(), bytes).map_err(StageError::stage)?;
        }
        publisher.publish(msg).map_err(|e| stage_err(err("publishing `/tf_static`")(&e)))?;
        Ok((Some(publisher), n))
    }
}

impl Ros2Stage {
    /// Discovery's verdicts on the routes' topics: a remote endpoint whose QoS cannot match
    /// (best effort offered where reliable is requested, volatile where transient local is), or
    /// one of another type on a route's topic. Counted per route and warned once.
    fn discovery(&mut self) {
        use ros2_client::dds::rustdds::{DomainParticipantStatusEvent as E, StatusEvented};
        while let Some(ev) = self.node.status.try_recv_status() {
            match ev {
                E::RemoteWriterQosIncompatible { local_reader, remote_writer, requested_qos, offered_qos } => {
                    if let Some(r) = self.ins.iter_mut().find(|r| r.sub.guid() == local_reader) {
                        r.qos_incompatible(remote_writer, &qos_text(&requested_qos), &qos_text(&offered_qos));
                    }
                }
                E::RemoteReaderQosIncompatible { local_writer, remote_reader, requested_qos, offered_qos } => {
                    if let Some(r) = self.out.routes.iter_mut().find(|r| r.guid() == local_writer) {
                        r.qos_incompatible(remote_reader, &qos_text(&requested_qos), &qos_text(&offered_qos));
                    }
                }
                E::RemoteWriterMatched { local_reader, remote_writer } => {
                    if let Some(r) = self.ins.iter_mut().find(|r| r.sub.guid() == local_reader) {
                        r.remotes.insert(remote_writer);
                    }
                }
                E::RemoteReaderMatched { local_writer, remote_reader } => {
                    if let Some(r) = self.out.routes.iter_mut().find(|r| r.guid() == local_writer) {
                        r.remotes.insert(remote_reader);
                    }
                }
                E::WriterLost { guid, .. } => {
                    for r in &mut self.ins {
                        r.remotes.remove(&guid);
                    }
                }
                E::ReaderLost { guid, .. } => {
                    for r in &mut self.out.routes {
                        r.remotes.remove(&guid);
                    }
                }
                E::WriterDetected { writer } => {
                    if let Some(r) = self.ins.iter_mut().find(|r| writer.topic_name == format!("rt{}", r.topic)) {
                        r.remote_type(writer.guid, &writer.type_name);
                    }
                }
                E::ReaderDetected { reader } => {
                    if let Some(r) =
                        self.out.routes.iter_mut().find(|r| reader.topic_name == format!("rt{}", r.cfg.topic()))
                    {
                        r.remote_type(reader.guid, &reader.type_name);
                    }
                }
                _ => {}
            }
        }
    }
}

fn qos_text(q: &ros2_client::dds::rustdds::QosPolicies) -> String {
    format!("{:?}, {:?}", q.reliability(), q.durability())
}

impl Stage for Ros2Stage {
    type Settings = Ros2Settings;

    fn open(ctx: &ProcessContext, settings: Ros2Settings, rt: &mut Runtime) -> Result<Self, StageError> {
        let mut node = RosNode::create(&settings).map_err(stage_err)?;
        let ports = RefCell::new(InPorts::open(rt, &settings.inbound)?);
        let mut ins = vec![];
        for r in &settings.inbound {
            let qos = r.qos.unwrap_or(TopicQos::SENSOR_DATA);
            let topic = node.topic(&r.route.topic, r.route.service.ros_type(), qos).map_err(stage_err)?;
            let sub = node
                .node
                .create_subscription::<Taken>(&topic, None)
                .map_err(|e| stage_err(err(format!("subscription to `{}`", r.route.topic))(&e)))?;
            let info_sub = if r.route.service == InService::DepthImage {
                let t = node.topic(&r.route.camera_info, CameraInfo::TYPE_NAME, qos).map_err(stage_err)?;
                Some(
                    node.node
                        .create_subscription::<CameraInfo>(&t, None)
                        .map_err(|e| stage_err(err(format!("subscription to `{}`", r.route.camera_info))(&e)))?,
                )
            } else {
                None
            };
            ins.push(InRoute::new(r, sub, info_sub));
        }
        let mut out = Outbound::open(rt, &mut node, &settings.out, &settings.frames)?;
        if !settings.record_bag.is_empty() {
            let dir = ctx.out_dir.join(&settings.record_bag);
            match ros2_interop::prepare_bag_dir(&dir, pipeline_runtime::restart::is_restart())
                .map_err(StageError::stage)?
            {
                ros2_interop::NewBag::Fresh => {}
                ros2_interop::NewBag::ReplacedEarlierRun { removed } => {
                    tracing::info!(dir = %dir.display(), "replacing an earlier run's ROS 2 bag ({} directory(ies) removed)", removed.len())
                }
                ros2_interop::NewBag::KeptKilledInstance { part } => {
                    tracing::warn!(dir = %part.display(), "restarted: the killed instance's ROS 2 bag is kept as {}", part.display())
                }
            }
            let static_tf =
                ros2_interop::out::static_tf(&settings.static_transforms, &settings.out, &settings.frames).is_some();
            out.record_into(&dir, settings.record_bag_compression, static_tf).map_err(StageError::stage)?;
        }
        let poll = crate::dds::new_poll().map_err(stage_err)?;
        let mut token = 0;
        for r in ins.iter_mut() {
            crate::dds::register(&poll, &mut r.sub, token, &format!("the reader of `{}`", r.topic))
                .map_err(stage_err)?;
            token += 1;
            if let Some(s) = &mut r.info_sub {
                crate::dds::register(&poll, s, token, "a CameraInfo reader").map_err(stage_err)?;
                token += 1;
            }
        }
        crate::dds::register(&poll, &mut node.status, token, "discovery events").map_err(stage_err)?;
        let waker = Some(DdsWaker::start(poll, rt.waker()?).map_err(stage_err)?);
        let (static_tf, static_transforms) = Self::static_tf(&mut node, &settings, out.bag.as_mut())?;
        let ins_text: Vec<String> = ins.iter().map(|r| format!("{} → {}", r.topic, r.counts.service)).collect();
        let outs_text: Vec<String> =
            out.routes.iter().map(|r| format!("{:?} → {}", r.cfg.what, r.cfg.topic())).collect();
        tracing::warn!(
            "plain DDS (insecure = true): anyone on this node's networks can read its topics and publish into its routes"
        );
        tracing::info!(
            domain_id = node.domain,
            "ROS 2 node `{}` (namespace `{}`): in [{}]; out [{}]; {} static transform(s)",
            settings.node_name,
            settings.namespace,
            ins_text.join(", "),
            outs_text.join(", "),
            static_transforms
        );
        rt.wake_at(Instant::now());
        Ok(Self {
            name: ctx.name.clone(),
            settings,
            node,
            ins,
            ports,
            out,
            _waker: waker,
            _static_tf: static_tf,
            static_transforms,
            last_in: None,
        })
    }

    fn end_after(&self) -> EndAfter {
        if self.settings.out.is_empty() { EndAfter::Itself } else { EndAfter::from_list(&self.settings.end_after) }
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, inputs_ended: bool) -> Result<Step, StageError> {
        self.discovery();
        let mut got = 0;
        for r in &mut self.ins {
            got += r.drain(&self.ports);
        }
        if got > 0 {
            self.last_in = Some(Instant::now());
        }
        if let Some(due) = self.out.pump()? {
            rt.wake_at(due);
        }
        if self.out.is_empty()
            && self.settings.end_when_idle_s > 0.0
            && let Some(last) = self.last_in
        {
            let idle = Duration::from_secs_f64(self.settings.end_when_idle_s);
            if last.elapsed() >= idle {
                tracing::info!("nothing from ROS 2 for {} s: ending the stream", self.settings.end_when_idle_s);
                return Ok(Step::Done);
            }
            rt.wake_at(last + idle);
        }
        if inputs_ended {
            self.out.flush_all();
        }
        Ok(Step::Idle)
    }

    type Summary = Ros2Part;

    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        self.discovery();
        for r in &mut self.ins {
            r.drain(&self.ports);
        }
        self.out.pump()?;
        self.out.flush_all();
        // Reliable subscribers acknowledge what was sent last while the node stays up.
        let end = Instant::now() + Duration::from_secs_f64(self.settings.linger_s);
        while Instant::now() < end {
            rt.keep_alive();
            std::thread::sleep(Duration::from_millis(50));
        }
        for r in &mut self.out.routes {
            r.counts.subscribers = r.remotes.len();
        }
        let bag = match self.out.bag.take() {
            Some(b) => {
                let report = b.finish().map_err(StageError::stage)?;
                let refused: u64 = report.refused.values().sum();
                if refused + report.write_errors > 0 {
                    tracing::warn!(
                        "ROS 2 bag {}: {refused} message(s) refused (the writer behind), {} not written ({}) (summary.json `bag`)",
                        report.dir.display(),
                        report.write_errors,
                        report.first_error.as_deref().unwrap_or("-")
                    );
                }
                Some(report)
            }
            None => None,
        };
        for r in &mut self.ins {
            r.counts.publishers = r.remotes.len();
        }
        let inbound = self.ins.iter().map(|r| (r.topic.clone(), r.summary())).collect();
        let out = self
            .out
            .routes
            .iter()
            .map(|r| {
                let route = OutRouteSummary {
                    counts: r.counts.clone(),
                    ros_type: r.cfg.what.ros_type().to_string(),
                    latency_ms: r.latency.ms(),
                };
                (r.cfg.topic().to_string(), route)
            })
            .collect();
        let lost: u64 = self
            .ins
            .iter()
            .map(|r| r.counts.undecodable + r.counts.invalid + r.counts.lost_in_dds + r.counts.port_failed)
            .sum::<u64>()
            + self.out.routes.iter().map(|r| r.counts.failed).sum::<u64>();
        let unmatched: u64 = self.ins.iter().map(|r| r.counts.qos_incompatible + r.counts.type_mismatch).sum::<u64>()
            + self.out.routes.iter().map(|r| r.counts.qos_incompatible + r.counts.type_mismatch).sum::<u64>();
        if unmatched > 0 {
            tracing::warn!(
                "ROS 2 gateway: {unmatched} remote endpoint(s) could not match a route (QoS or type; per route in summary.json `ros2`)"
            );
        }
        if lost > 0 {
            tracing::warn!("ROS 2 gateway: {lost} message(s) not carried (per route in summary.json `ros2`)");
        }
        let gateway = GatewaySummary {
            completed: ending == Ending::EndOfStream,
            insecure: true,
            node: format!("{}/{}", self.settings.namespace.trim_end_matches('/'), self.settings.node_name),
            domain_id: self.node.domain,
            inbound,
            out,
            static_transforms: self.static_transforms,
            pipeline_messages_taken: self.out.taken(),
            voxel_messages_missed: self.out.voxel_gaps().0,
            voxel_deltas_waiting_for_a_full_set: self.out.voxel_gaps().1,
            not_carried: lost,
            endpoints_unmatched: unmatched,
            bag,
        };
        Ok(Ros2Part { ros2: std::collections::BTreeMap::from([(self.name.clone(), gateway)]) })
    }

    fn end_of_stream(&self) -> (u64, u64) {
        let sent = self.ports.borrow().sent();
        (sent.saturating_sub(1), sent)
    }
}

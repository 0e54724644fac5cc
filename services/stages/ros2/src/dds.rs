//! The gateway's ROS 2 node on the DDS wire (ros2-client over RustDDS): the participant, topics
//! with their QoS, and a thread that turns DDS readiness into wake-ups of the stage's loop (the
//! readers themselves are read in the loop, so the loop never spins and never polls).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use ros2_client::dds::rustdds;
use ros2_client::dds::rustdds::mio1::{Events, Interest, Poll, Token};
use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions, QosProfile};

use crate::settings::{Durability, Reliability, Ros2Settings, TopicQos};

/// A failure of the ROS 2 side, named with what was being done.
#[derive(Debug, thiserror::Error)]
#[error("ROS 2 {what}: {why}")]
pub struct DdsError {
    /// What was being done (creating the participant, a topic, ...).
    pub what: String,
    /// Why it failed.
    pub why: String,
}

pub(crate) fn err(what: impl Into<String>) -> impl FnOnce(&dyn std::fmt::Debug) -> DdsError {
    let what = what.into();
    move |e| DdsError { what, why: format!("{e:?}") }
}

/// ros2-client's QoS profile for a topic's settings.
pub fn qos_profile(q: TopicQos) -> QosProfile {
    use ros2_client::qos;
    QosProfile {
        reliability: match q.reliability {
            Reliability::BestEffort => qos::Reliability::BestEffort,
            Reliability::Reliable => {
                qos::Reliability::Reliable { when_full: qos::WhenFull::Wait(Duration::from_millis(100)) }
            }
        },
        durability: match q.durability {
            Durability::Volatile => qos::Durability::Volatile,
            Durability::TransientLocal => qos::Durability::TransientLocal,
        },
        history: qos::History::KeepLast { depth: q.depth as usize },
        ..QosProfile::publisher_default()
    }
}

/// The ROS 2 node of the gateway.
pub struct RosNode {
    /// The node.
    pub node: ros2_client::Node,
    /// Its DDS domain.
    pub domain: u16,
    /// The participant's discovery and matching events (QoS mismatches, remote endpoints).
    pub status: rustdds::DomainParticipantStatusListener,
}

impl RosNode {
    /// Joins the DDS domain (advertising only `only_networks` when given) and creates the node.
    pub fn create(s: &Ros2Settings) -> Result<Self, DdsError> {
        let domain = s.domain().map_err(|why| DdsError { what: "domain".into(), why })?;
        let mut b = rustdds::DomainParticipantBuilder::new(domain);
        if !s.only_networks.is_empty() {
            b = b.with_only_networks(s.only_networks.iter().copied());
        }
        let dp = b.build().map_err(|e| err(format!("participant in domain {domain}"))(&e))?;
        let status = dp.status_listener();
        let ctx = ros2_client::Context::from_domain_participant(dp).map_err(|e| err("context")(&e))?;
        let name = NodeName::new(&s.namespace, &s.node_name).map_err(|e| err("node name")(&e))?;
        let node = ctx
            .new_node(name, NodeOptions::new().enable_rosout(false))
            .map_err(|e| err(format!("node `{}`", s.node_name))(&e))?;
        Ok(Self { node, domain, status })
    }

    /// A topic of ROS 2 type `ros_type` (`pkg/msg/Type`) with `qos`.
    pub fn topic(
        &mut self,
        name: &str,
        ros_type: &str,
        qos: TopicQos,
    ) -> Result<ros2_client::dds::rustdds::Topic, DdsError> {
        let n = Name::parse(name).map_err(|e| err(format!("topic name `{name}`"))(&e))?;
        let mut parts = ros_type.split("/msg/");
        let (pkg, ty) = (parts.next().unwrap_or_default(), parts.next().unwrap_or_default());
        self.node
            .create_topic(&n, MessageTypeName::new(pkg, ty), &qos_profile(qos))
            .map_err(|e| err(format!("topic `{name}` ({ros_type})"))(&e))
    }
}

/// Wakes the stage's loop whenever a registered DDS reader has data (a thread blocked in mio's
/// poll; stopped and joined on drop).
pub struct DdsWaker {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

/// A poll to register DDS readers with before [`DdsWaker::start`].
pub fn new_poll() -> Result<Poll, DdsError> {
    Poll::new().map_err(|e| err("poll")(&e))
}

/// Registers `source` with `poll` (`what` names it in an error).
pub fn register(
    poll: &Poll,
    source: &mut impl rustdds::mio1::event::Source,
    token: usize,
    what: &str,
) -> Result<(), DdsError> {
    poll.registry()
        .register(source, Token(token), Interest::READABLE)
        .map_err(|e| err(format!("registering {what}"))(&e))
}

impl DdsWaker {
    /// Starts the thread on a poll with everything registered.
    pub fn start(poll: Poll, waker: pipeline_runtime::Waker) -> Result<Self, DdsError> {
        let stop = Arc::new(AtomicBool::new(false));
        let stop2 = stop.clone();
        let thread = std::thread::Builder::new()
            .name("dds-wake".into())
            .spawn(move || {
                let mut poll = poll;
                let mut events = Events::with_capacity(64);
                while !stop2.load(Ordering::Acquire) {
                    match poll.poll(&mut events, Some(Duration::from_millis(250))) {
                        Ok(()) if !events.is_empty() => waker.wake(),
                        Ok(()) => {}
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                        Err(e) => {
                            tracing::error!("DDS wake-up thread: {e}: the gateway's ROS 2 inputs are no longer woken");
                            return;
                        }
                    }
                }
            })
            .map_err(|e| err("wake-up thread")(&e))?;
        Ok(Self { stop, thread: Some(thread) })
    }
}

impl Drop for DdsWaker {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

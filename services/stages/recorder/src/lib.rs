//! Record and replay (issue #8): the `recorder` process writes every service of a run to an MCAP
//! file (one channel per service, one schema per wire type, the exact header and payload bytes
//! of every message), and the `replayer` process publishes a recording back into the pipeline
//! in the original publish order, so that one stage can be rerun in isolation on recorded
//! inputs. `pipeline_runtime::topics` is the table of recordable services with their wire types
//! (re-exported here), [`record`] the
//! recorder's settings and MCAP sink, [`replay`] the replayer's settings, file checks and order.
//! The binaries (`src/bin/`) are the wiring around them. [`ros2`] is the recorder's optional
//! ROS 2 bag (rosbag2 MCAP) of the pipeline's outputs.

pub mod error;
pub mod record;
pub mod replay;
pub mod replay_stage;
pub mod ros2;
pub mod stage;
pub mod summary;

pub use error::RecorderError;
pub use pipeline_runtime::topics::{self, Emit, Tap, TopicError};
pub use record::{Compression, McapSink, RecorderSettings, SinkOptions, SinkReport};
pub use replay::{Replay, ReplayError, Replayed, ReplayerSettings, ScanReport, Selection, scan};
pub use ros2::{Ros2Recording, Ros2Report, Ros2Sink};
pub use wire_topics::{TOPICS, Topic, topic};

//! ROS 2 at the pipeline's edges (issue 33), without a ROS installation:
//!
//! - [`msgs`]: the ROS 2 messages the pipeline reads and writes, as serde types;
//! - [`cdr`]: their encoding on the DDS wire and in bags (CDR with the encapsulation header);
//! - [`schema`]: their `.msg` definitions, as rosbag2 writes them into MCAP (`ros2msg`);
//! - [`convert`]: ROS 2 messages to the pipeline's wire types and back, each check naming the
//!   field it failed on;
//! - [`bag`]: rosbag2 bags in MCAP storage, read (damaged parts counted and skipped) and written;
//! - [`route`]: ROS 2 topics into the pipeline (the bag replay's and the gateway's `in` routes);
//! - [`out`]: pipeline outputs as ROS 2 topics (the gateway's and the recorder's `out` routes).
//!
//! Nothing here does I/O on shared memory or the network: the ingest source `rosbag2`, the
//! recorder's ROS 2 bag and the `ros2` gateway are the processes that use it.

pub mod bag;
pub mod bag_sink;
pub mod cdr;
pub mod convert;
pub mod msgs;
pub mod out;
pub mod route;
pub mod schema;

pub use bag::{BagCompression, BagError, BagMessage, BagQos, BagReader, BagWarts, BagWriter};
pub use bag_sink::{BagReport, BagSink, NewBag, prepare_bag_dir};
pub use cdr::{CdrError, decode, encode};
pub use convert::ConvertError;
pub use msgs::Message;

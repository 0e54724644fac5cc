//! Occupancy octree with the semantics of OctoMap 1.9.7 (EQUATIONS §7; Hornung et al. 2013).
//!
//! The map is a depth-16 octree over integer voxel keys (`key = floor(coord / res) + 32768`, see
//! [`OcTreeKey`]). Each node stores an occupancy log-odds value as `f32`, exactly like OctoMap, so
//! a map built here agrees voxel-for-voxel (and bit-for-bit in the log-odds) with OctoMap's
//! `OcTree::insertPointCloud(cloud, origin, maxrange, lazy_eval, discretize = false)`:
//!
//! * per scan all rays are cast first ([`compute_ray_keys`], a 3-D DDA after Amanatides & Woo,
//!   with OctoMap's float/double arithmetic): free keys = union of the traversed voxels (origin
//!   voxel included, end voxel excluded), occupied keys = end-point voxels, and keys in both sets
//!   count as occupied only; points beyond the maximum range give a ray truncated at that range,
//!   free space only;
//! * every key is updated once per scan (log-odds += hit / miss, clamped; an update of a voxel
//!   already at the clamp in the update direction is skipped, "early abort");
//! * inner nodes hold the maximum log-odds of their children; 8 equal leaf children are pruned
//!   into their parent (on the fly in eager mode, or by [`OcTree::update_inner_occupancy`] +
//!   [`OcTree::prune`] after lazy insertion);
//! * `.bt` files ([`OcTree::write_binary`], [`OcTree::read_binary`]) are byte-compatible with
//!   OctoMap's `writeBinary` / `readBinary`.
//!
//! Storage is an arena of 8-node blocks (8 bytes per node: `f32` log-odds + `u32` child-block
//! index), and ray casting may run on several threads (the result does not depend on the number
//! of threads). [`bench_data`] reads the OctoMap benchmark's `scans.bin` and occupied-voxel dumps.

pub mod bench_data;
mod io;
mod key;
mod keyset;
mod raycast;
mod tree;

pub use io::BINARY_FILE_HEADER;
pub use key::{OcTreeKey, TREE_DEPTH, TREE_MAX_VAL};
pub use raycast::compute_ray_keys;
pub use tree::{InsertStats, Leaf, Leaves, MapChanges, OcTree, Point3Like, SensorModel, logodds, probability};

/// Errors of the octree: invalid parameters and malformed `.bt` input.
#[derive(Debug, thiserror::Error)]
pub enum OctreeError {
    /// A parameter (resolution, sensor model, origin, max range) is invalid.
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    /// The `.bt` header is malformed or not an OctoMap `OcTree` binary file.
    #[error("bad .bt header: {0}")]
    BadHeader(String),
    /// The `.bt` node stream is malformed (truncated, too deep, size mismatch).
    #[error("bad .bt data: {0}")]
    BadData(String),
    /// An I/O error while reading or writing.
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
}

/// Result alias of this crate.
pub type Result<T> = std::result::Result<T, OctreeError>;

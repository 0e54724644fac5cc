//! iceoryx2 scope of a run: prefix, root path and base config; node creation and cleanup.
//!
//! Every run (and every test) uses its own prefix and root path so that runs never collide. The
//! iceoryx2 config is built explicitly here and handed to every node: iceoryx2 would otherwise pick
//! up `./config/iceoryx2.toml` from whatever the working directory happens to be.

use std::path::{Path, PathBuf};

use iceoryx2::config::Config;
use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;

/// Environment variable through which the supervisor hands the prefix to its children.
pub const ENV_PREFIX: &str = "SLAM_PIPELINE_IOX_PREFIX";
/// Environment variable through which the supervisor hands the root path to its children.
pub const ENV_ROOT: &str = "SLAM_PIPELINE_IOX_ROOT";
/// Environment variable through which the supervisor hands the base iceoryx2 config file.
pub const ENV_IOX_CONFIG: &str = "SLAM_PIPELINE_IOX_CONFIG";

/// Errors of setting up iceoryx2.
#[derive(Debug, thiserror::Error)]
pub enum IoxError {
    /// The prefix is not a valid file name.
    #[error("iceoryx2 prefix `{0}` is not a valid file name")]
    InvalidPrefix(String),
    /// The root path is not valid.
    #[error("iceoryx2 root path `{0}` is not a valid absolute path")]
    InvalidRoot(String),
    /// The base config file could not be loaded.
    #[error("cannot load iceoryx2 config `{path}`: {reason}")]
    BaseConfig {
        /// The file.
        path: PathBuf,
        /// iceoryx2's reason.
        reason: String,
    },
    /// The node name is invalid.
    #[error("invalid node name `{0}`")]
    InvalidNodeName(String),
    /// Creating the node failed.
    #[error("cannot create iceoryx2 node `{name}`: {reason}")]
    NodeCreation {
        /// Node name.
        name: String,
        /// iceoryx2's reason.
        reason: String,
    },
    /// Listing the nodes failed.
    #[error("cannot list iceoryx2 nodes: {0}")]
    List(String),
}

/// The iceoryx2 scope of one run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IoxScope {
    /// File prefix of every shared-memory object of the run.
    pub prefix: String,
    /// Root path of node and service files.
    pub root: PathBuf,
    /// Optional iceoryx2 config file to start from.
    pub base_config: Option<PathBuf>,
}

impl IoxScope {
    /// The scope a child process inherits from its supervisor (environment), if any.
    pub fn from_env() -> Option<Self> {
        let prefix = std::env::var(ENV_PREFIX).ok()?;
        let root = PathBuf::from(std::env::var_os(ENV_ROOT)?);
        let base_config = std::env::var_os(ENV_IOX_CONFIG).map(PathBuf::from);
        Some(Self { prefix, root, base_config })
    }

    /// Sets the environment of a child so that [`IoxScope::from_env`] returns this scope.
    pub fn export_to(&self, cmd: &mut std::process::Command) {
        cmd.env(ENV_PREFIX, &self.prefix).env(ENV_ROOT, &self.root);
        match &self.base_config {
            Some(p) => cmd.env(ENV_IOX_CONFIG, p),
            None => cmd.env_remove(ENV_IOX_CONFIG),
        };
    }

    /// The iceoryx2 config of this scope.
    pub fn config(&self) -> Result<Config, IoxError> {
        let mut config = match &self.base_config {
            Some(path) => {
                let fp = iceoryx2::prelude::FilePath::new(path.as_os_str().as_encoded_bytes())
                    .map_err(|e| IoxError::BaseConfig { path: path.clone(), reason: format!("{e:?}") })?;
                Config::from_file(&fp)
                    .map_err(|e| IoxError::BaseConfig { path: path.clone(), reason: format!("{e:?}") })?
            }
            None => Config::default(),
        };
        config.global.prefix =
            FileName::new(self.prefix.as_bytes()).map_err(|_| IoxError::InvalidPrefix(self.prefix.clone()))?;
        let mut root = self.root.to_string_lossy().into_owned();
        if !root.ends_with('/') {
            root.push('/');
        }
        let root_path =
            iceoryx2::prelude::Path::new(root.as_bytes()).map_err(|_| IoxError::InvalidRoot(root.clone()))?;
        if !self.root.is_absolute() {
            return Err(IoxError::InvalidRoot(root));
        }
        config.global.set_root_path(&root_path);
        Ok(config)
    }

    /// Creates a node named `name` in this scope. Signal handling is left to the caller
    /// (the runtime installs its own SIGINT/SIGTERM flags).
    pub fn create_node(&self, name: &str) -> Result<Node<ipc::Service>, IoxError> {
        let config = self.config()?;
        let node_name = NodeName::new(name).map_err(|_| IoxError::InvalidNodeName(name.to_string()))?;
        NodeBuilder::new()
            .name(&node_name)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| IoxError::NodeCreation { name: name.to_string(), reason: format!("{e:?}") })
    }

    /// Creates a node of the thread-safe service variant (same resources as `ipc`; its ports may
    /// be used from any thread), for ports shared between threads such as a [`crate::Waker`]'s.
    pub fn create_threadsafe_node(&self, name: &str) -> Result<Node<ipc_threadsafe::Service>, IoxError> {
        let config = self.config()?;
        let node_name = NodeName::new(name).map_err(|_| IoxError::InvalidNodeName(name.to_string()))?;
        NodeBuilder::new()
            .name(&node_name)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc_threadsafe::Service>()
            .map_err(|e| IoxError::NodeCreation { name: name.to_string(), reason: format!("{e:?}") })
    }

    /// Counts the nodes of this scope that are alive and dead (dead = crashed, resources stale).
    pub fn node_census(&self) -> Result<NodeCensus, IoxError> {
        let config = self.config()?;
        let mut census = NodeCensus::default();
        Node::<ipc::Service>::list(&config, |state| {
            match state {
                NodeState::Alive(view) => census
                    .alive
                    .push(view.details().as_ref().map(|d| d.name().to_string()).unwrap_or_else(|| "?".into())),
                NodeState::Dead(_) => census.dead += 1,
                NodeState::Inaccessible(_) | NodeState::Undefined(_) => census.other += 1,
            }
            CallbackProgression::Continue
        })
        .map_err(|e| IoxError::List(format!("{e:?}")))?;
        Ok(census)
    }

    /// Removes the stale resources of every dead node of this scope; returns how many were cleaned.
    pub fn cleanup_dead_nodes(&self) -> Result<u64, IoxError> {
        let config = self.config()?;
        let mut cleaned = 0;
        Node::<ipc::Service>::list(&config, |state| {
            if let NodeState::Dead(view) = state
                && view.try_remove_stale_resources().is_ok()
            {
                cleaned += 1;
            }
            CallbackProgression::Continue
        })
        .map_err(|e| IoxError::List(format!("{e:?}")))?;
        Ok(cleaned)
    }

    /// Files of this scope still in /dev/shm (names start with the prefix).
    pub fn shm_files(&self) -> Vec<PathBuf> {
        files_with_prefix(Path::new("/dev/shm"), &self.prefix)
    }

    /// Removes every file of this scope from /dev/shm and the root path. Only call this when no
    /// process of the scope is alive.
    pub fn remove_all_resources(&self) -> std::io::Result<usize> {
        let mut removed = 0;
        for f in self.shm_files() {
            if std::fs::remove_file(&f).is_ok() {
                removed += 1;
            }
        }
        if self.root.exists() {
            removed += count_files(&self.root);
            std::fs::remove_dir_all(&self.root)?;
        }
        Ok(removed)
    }
}

/// Nodes of a scope by state.
#[derive(Debug, Default, Clone)]
pub struct NodeCensus {
    /// Names of live nodes.
    pub alive: Vec<String>,
    /// Number of dead nodes with stale resources.
    pub dead: usize,
    /// Nodes that could not be classified.
    pub other: usize,
}

fn files_with_prefix(dir: &Path, prefix: &str) -> Vec<PathBuf> {
    let Ok(rd) = std::fs::read_dir(dir) else { return vec![] };
    rd.filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with(prefix))
        .map(|e| e.path())
        .collect()
}

fn count_files(dir: &Path) -> usize {
    let Ok(rd) = std::fs::read_dir(dir) else { return 0 };
    rd.filter_map(|e| e.ok()).map(|e| if e.path().is_dir() { count_files(&e.path()) } else { 1 }).sum()
}

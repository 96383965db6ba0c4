//! The daemon's configuration (TOML). deploy/graspd.toml documents every option.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// How the dispatcher waits for requests.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Waiting {
    /// Sleep until a client notifies the method's event service (default).
    Event,
    /// Spin on the request queues: lowest latency, one core busy.
    Poll,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Services are `<service_prefix>/v4/<method>`.
    pub service_prefix: String,
    /// Categories to load at start (built-in families: mug, drill, hammer).
    pub categories: Vec<String>,
    /// Shape-space cache; a missing or stale artefact is built at start and saved here.
    /// Default: the repository's assets/spaces.
    pub cache_dir: Option<PathBuf>,
    /// Largest cloud accepted (points); larger requests get RESOURCE_EXHAUSTED.
    pub max_points: u32,
    /// Client ports per service (iceoryx2 service limit).
    pub max_clients: u32,
    /// Requests one client may have in flight; more get RESOURCE_EXHAUSTED.
    pub max_in_flight_per_client: u32,
    /// Requests worked on at once (engine threads); 0 = one per available core. The daemon runs one
    /// thread more, so that one always receives.
    pub workers: u32,
    pub waiting: Waiting,
    /// After answering a Register or Grasp, the thread that worked on it
    /// keeps receiving for this long before it sleeps (event-driven) or
    /// goes back to wait for the lead (polling), so that a client calling
    /// again at once finds a running thread with the ports in its cache.
    /// Microseconds; 0 = off.
    pub linger_us: u64,
    /// Requests slower than this (receipt to answer) are logged and counted, milliseconds.
    pub slow_request_ms: f64,
    /// Period of housekeeping (dead-peer cleanup, idle reply notifiers), milliseconds.
    pub housekeeping_ms: u64,
    /// On SIGINT/SIGTERM, how long in-flight requests may take to finish, seconds.
    pub shutdown_grace_s: f64,
    /// Log a metrics line (per-method counts and latencies) every this many seconds; 0 = never.
    pub metrics_interval_s: f64,
    /// A Unix-domain socket serving Register with a serialised copy of the cloud: the
    /// baseline `graspctl bench` compares with. Off when absent.
    pub uds_baseline: Option<PathBuf>,
    /// Another hand than the bundled SIH-like one, for Grasp: its URDF
    /// (collision primitives; an OBJ or STL mesh as the capsule enclosing
    /// it) and keypoints file, both or neither.
    pub hand_urdf: Option<PathBuf>,
    pub hand_keypoints: Option<PathBuf>,
    /// A demonstration file per category, made with the hand Grasp solves
    /// for; a category not named here uses the bundled
    /// `assets/demos/<category>.json` (made with the SIH-like hand).
    pub demos: BTreeMap<String, PathBuf>,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            service_prefix: graspd_proto::DEFAULT_PREFIX.to_owned(),
            categories: vec!["mug".into(), "drill".into(), "hammer".into()],
            cache_dir: None,
            max_points: 200_000,
            max_clients: 64,
            max_in_flight_per_client: 4,
            workers: 0,
            waiting: Waiting::Event,
            linger_us: 200,
            slow_request_ms: 250.0,
            housekeeping_ms: 500,
            shutdown_grace_s: 30.0,
            metrics_interval_s: 0.0,
            uds_baseline: None,
            hand_urdf: None,
            hand_keypoints: None,
            demos: BTreeMap::new(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("configuration: {0}")]
    Invalid(String),
}

impl Config {
    /// Reads and checks a configuration file. Relative paths in it (the
    /// cache, the hand, the demonstrations, the baseline socket) are taken
    /// from the file's directory, as a unit file's `/etc/graspd/graspd.toml`
    /// naming `hands/my_hand.urdf` means `/etc/graspd/hands/my_hand.urdf`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.into(), source })?;
        let mut cfg: Config =
            toml::from_str(&text).map_err(|e| ConfigError::Parse { path: path.into(), message: e.to_string() })?;
        cfg.validate()?;
        let dir = path.parent().unwrap_or(Path::new(""));
        let within = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = dir.join(&*p);
            }
        };
        cfg.cache_dir
            .iter_mut()
            .chain(&mut cfg.hand_urdf)
            .chain(&mut cfg.hand_keypoints)
            .chain(&mut cfg.uds_baseline)
            .for_each(within);
        cfg.demos.values_mut().for_each(within);
        Ok(cfg)
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |m: String| Err(ConfigError::Invalid(m));
        let p = &self.service_prefix;
        if p.is_empty() || p.len() > 64 || !p.chars().all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c)) {
            return bad(format!("service_prefix {p:?}: 1 to 64 characters of [A-Za-z0-9_.-]"));
        }
        if self.categories.is_empty() {
            return bad("categories: at least one".into());
        }
        if self.categories.len() > graspd_proto::MAX_CATEGORIES {
            return bad(format!("categories: at most {}", graspd_proto::MAX_CATEGORIES));
        }
        for (i, c) in self.categories.iter().enumerate() {
            c.parse::<crate::tools::Category>().map_err(|e| ConfigError::Invalid(format!("categories: {e}")))?;
            if self.categories[..i].contains(c) {
                return bad(format!("categories: {c:?} twice"));
            }
        }
        if self.max_points == 0 || self.max_points > 10_000_000 {
            return bad(format!("max_points {}: 1 to 10000000", self.max_points));
        }
        if self.max_clients == 0 || self.max_clients > 4096 {
            return bad(format!("max_clients {}: 1 to 4096", self.max_clients));
        }
        if self.max_in_flight_per_client == 0 || self.max_in_flight_per_client > 256 {
            return bad(format!("max_in_flight_per_client {}: 1 to 256", self.max_in_flight_per_client));
        }
        if self.workers > 256 {
            return bad(format!("workers {}: at most 256", self.workers));
        }
        for (name, v) in [
            ("slow_request_ms", self.slow_request_ms),
            ("shutdown_grace_s", self.shutdown_grace_s),
            ("metrics_interval_s", self.metrics_interval_s),
        ] {
            if !v.is_finite() || v < 0.0 {
                return bad(format!("{name} {v}: a finite number ≥ 0"));
            }
        }
        if self.linger_us > 100_000 {
            return bad(format!("linger_us {}: at most 100000", self.linger_us));
        }
        if self.housekeeping_ms == 0 || self.housekeeping_ms > 60_000 {
            return bad(format!("housekeeping_ms {}: 1 to 60000", self.housekeeping_ms));
        }
        if self.hand_urdf.is_some() != self.hand_keypoints.is_some() {
            return bad("hand_urdf and hand_keypoints: both or neither".into());
        }
        for c in self.demos.keys() {
            if !self.categories.contains(c) {
                return bad(format!("demos: {c:?} is not among the categories served"));
            }
        }
        Ok(())
    }

    /// The hand and demonstrations Grasp uses.
    pub fn grasp_sources(&self) -> super::engine::GraspSources {
        super::engine::GraspSources {
            hand: self.hand_urdf.clone().zip(self.hand_keypoints.clone()),
            demos: self.demos.clone(),
        }
    }

    /// Worker threads to start (with `workers = 0`, the cores available:
    /// reading cgroup files each call, so call it once).
    pub fn worker_count(&self) -> usize {
        match self.workers {
            0 => std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
            n => n as usize,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_configuration_parses_and_equals_the_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/graspd.toml");
        let cfg = Config::load(&path).unwrap();
        let d = Config::default();
        assert_eq!(toml::to_string(&cfg).unwrap(), toml::to_string(&d).unwrap());
    }

    #[test]
    fn relative_paths_are_taken_from_the_files_directory() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("graspd.toml");
        std::fs::write(
            &p,
            "cache_dir = \"spaces\"\nhand_urdf = \"hands/h.urdf\"\nhand_keypoints = \"/abs/k.json\"\n[demos]\nmug = \"demos/mug.json\"\n",
        )
        .unwrap();
        let cfg = Config::load(&p).unwrap();
        assert_eq!(cfg.cache_dir.unwrap(), dir.path().join("spaces"));
        assert_eq!(cfg.hand_urdf.unwrap(), dir.path().join("hands/h.urdf"));
        assert_eq!(cfg.hand_keypoints.unwrap(), PathBuf::from("/abs/k.json"));
        assert_eq!(cfg.demos["mug"], dir.path().join("demos/mug.json"));
        assert_eq!(cfg.uds_baseline, None);
    }

    #[test]
    fn bad_configurations_are_clear_errors() {
        for (text, needle) in [
            ("max_points = 0", "max_points"),
            ("categories = [\"spoon\"]", "categories"),
            ("waiting = \"sometimes\"", "waiting"),
            ("unknown_option = 1", "unknown_option"),
            ("service_prefix = \"a/b\"", "service_prefix"),
            ("slow_request_ms = -1.0", "slow_request_ms"),
            ("linger_us = 1000000", "linger_us"),
            ("hand_urdf = \"/etc/graspd/h.urdf\"", "both or neither"),
            ("[demos]\nspoon = \"/etc/graspd/s.json\"", "spoon"),
        ] {
            let dir = tempfile::tempdir().unwrap();
            let p = dir.path().join("c.toml");
            std::fs::write(&p, text).unwrap();
            let e = Config::load(&p).unwrap_err().to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
    }
}

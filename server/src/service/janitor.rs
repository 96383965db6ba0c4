//! The daemon's housekeeping of iceoryx2's shared resources: the nodes'
//! configuration, and the threads that remove what dead peers left behind
//! (their nodes, ports and services; shared memory abandoned half-created),
//! including what iceoryx2 0.10's own cleanup cannot remove: tags left
//! half-written and directories of nodes killed before they were listed.

use super::daemon::Ipc;
use iceoryx2::node::{CleanupState, NodeView};
use iceoryx2::prelude::*;
use std::os::unix::fs::PermissionsExt;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// iceoryx2 configuration of the daemon's nodes: no implicit dead-node cleanup
/// (on node creation or destruction, on opening a service). Those cleanups can
/// block forever on a peer killed at the wrong moment (see
/// `graspd_proto::hygiene`); the daemon cleans explicitly, off the serving path.
pub(super) fn ipc_config() -> iceoryx2::config::Config {
    let mut c = iceoryx2::config::Config::global_config().clone();
    c.global.node.cleanup_dead_nodes_on_creation = false;
    c.global.node.cleanup_dead_nodes_on_destruction = false;
    c.global.service.cleanup_dead_nodes_on_open = false;
    c
}

fn janitor_node(config: &iceoryx2::config::Config) -> Option<Node<Ipc>> {
    let name: NodeName = "graspd-janitor".try_into().ok()?;
    NodeBuilder::new()
        .name(&name)
        .config(config)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .ok()
}

/// Removes the resources of dead iceoryx2 peers, purging abandoned shared
/// memory meanwhile so that the cleanup cannot hang on it.
pub(super) fn cleanup_dead_peers_guarded(config: &iceoryx2::config::Config) {
    let purged = graspd_proto::hygiene::purge_abandoned_shm(Duration::from_secs(1));
    let cfg = config.clone();
    let (tx, rx) = std::sync::mpsc::channel();
    let spawned = std::thread::Builder::new().name("graspd-cleanup".into()).spawn(move || {
        let r = janitor_node(&cfg).map(|n| cleanup_dead_nodes(&n, &cfg));
        let _ = tx.send(r);
    });
    if spawned.is_err() {
        return;
    }
    let t0 = Instant::now();
    loop {
        match rx.recv_timeout(Duration::from_millis(300)) {
            Ok(Some(c)) => {
                tracing::info!(
                    cleanups = c.cleanups,
                    failed = c.failed_cleanups,
                    purged,
                    "removed the stale resources of dead iceoryx2 peers"
                );
                return;
            }
            Ok(None) | Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => return,
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                graspd_proto::hygiene::purge_abandoned_shm(Duration::from_secs(1));
                if t0.elapsed() > Duration::from_secs(30) {
                    tracing::warn!("the cleanup of dead peers takes over 30 s; serving without waiting for it");
                    return;
                }
            }
        }
    }
}

/// The background housekeeping threads; [`Janitors::stop`] ends them.
pub(super) struct Janitors {
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

/// Sleeps `d` in short slices; false as soon as `stop` is set.
fn nap(d: Duration, stop: &AtomicBool) -> bool {
    let until = Instant::now() + d;
    while !stop.load(Ordering::Acquire) {
        let left = until.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return true;
        }
        std::thread::sleep(left.min(Duration::from_millis(20)));
    }
    false
}

/// Background housekeeping: one thread removes dead peers' resources every
/// `period`, another purges abandoned shared memory every second (which also
/// frees the first should a cleanup ever block).
pub(super) fn start_janitors(
    config: &iceoryx2::config::Config,
    period: Duration,
) -> Result<Janitors, super::daemon::ServeError> {
    let stop = Arc::new(AtomicBool::new(false));
    let cfg = config.clone();
    let s = stop.clone();
    let janitor = std::thread::Builder::new()
        .name("graspd-janitor".into())
        .spawn(move || {
            let Some(node) = janitor_node(&cfg) else { return };
            // A dead peer whose resources cannot be removed (another user's,
            // say) fails again on every pass: say so when the count changes,
            // not twice a second for the daemon's life.
            let mut failing = 0;
            while nap(period, &s) {
                let c = cleanup_dead_nodes(&node, &cfg);
                if c.cleanups > 0 {
                    tracing::info!(cleanups = c.cleanups, "removed the resources of dead peers");
                }
                if c.failed_cleanups != failing {
                    if c.failed_cleanups > 0 {
                        tracing::warn!(
                            failed = c.failed_cleanups,
                            "cannot remove the resources of some dead peers (retrying every pass; said again when the count changes)"
                        );
                    } else {
                        tracing::info!("the dead peers' resources that could not be removed are gone");
                    }
                    failing = c.failed_cleanups;
                }
            }
        })
        .map_err(|e| super::daemon::ServeError::Ipc(format!("cannot start the janitor: {e}")))?;
    let s = stop.clone();
    let purger = std::thread::Builder::new()
        .name("graspd-purger".into())
        .spawn(move || {
            while nap(Duration::from_secs(1), &s) {
                let n = graspd_proto::hygiene::purge_abandoned_shm(Duration::from_secs(1));
                if n > 0 {
                    tracing::info!(
                        removed = n,
                        "removed abandoned shared-memory objects of peers killed while creating them"
                    );
                }
            }
        })
        .map_err(|e| super::daemon::ServeError::Ipc(format!("cannot start the purger: {e}")))?;
    Ok(Janitors { stop, threads: vec![janitor, purger] })
}

impl Janitors {
    /// Stops the threads and waits up to `within` for them: the janitor's
    /// node is then dropped as a live node's should be, not left for the next
    /// daemon to clean as a dead peer's. A thread still busy after that (a
    /// cleanup blocked on a peer's resources) is left to the process's exit.
    pub(super) fn stop(mut self, within: Duration) {
        self.stop.store(true, Ordering::Release);
        let threads = std::mem::take(&mut self.threads);
        let until = Instant::now() + within;
        while threads.iter().any(|t| !t.is_finished()) && Instant::now() < until {
            std::thread::sleep(Duration::from_millis(5));
        }
        for t in threads.into_iter().filter(|t| t.is_finished()) {
            let _ = t.join();
        }
    }
}

impl Drop for Janitors {
    /// A daemon that fails after starting them stops them too (without waiting).
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
    }
}

/// Removes the resources of dead peers, repairing first the tags iceoryx2
/// cannot remove by itself (see [`finish_orphaned_tags`]). First: a failed
/// cleanup removes the node's details, and without them iceoryx2 cleans with
/// its global configuration instead of the node's.
pub(super) fn cleanup_dead_nodes(node: &Node<Ipc>, config: &iceoryx2::config::Config) -> CleanupState {
    let finished = finish_orphaned_tags(config);
    let c = node.try_cleanup_dead_nodes();
    if finished > 0 {
        tracing::info!(tags = finished, "finished the tags dead peers left half-written, for their cleanup");
    }
    let unborn = remove_unborn_nodes(config, UNBORN_NODE_AGE);
    if unborn > 0 {
        tracing::info!(nodes = unborn, "removed the directories of peers killed while their node was being made");
    }
    c
}

/// Whether a file is iceoryx2 static storage still being written: created
/// read-write for its owner, made read-only once written (iceoryx2-cal's
/// static storage; listing skips such files).
fn being_written(m: &std::fs::Metadata) -> bool {
    m.is_file() && m.permissions().mode() & 0o777 == 0o600
}

/// Age from which a node directory without a monitor is taken as abandoned
/// (a node being made gets its monitor within milliseconds).
const UNBORN_NODE_AGE: Duration = Duration::from_secs(60);

/// Directories of nodes that never came to life: iceoryx2 makes a node's
/// directory, writes its details (static storage, read-write until written)
/// and only then its monitor, by which nodes are listed. A process killed
/// before the monitor leaves a directory that nothing lists, so nothing
/// removes it (five here after a morning of end-to-end tests, 2 KB each).
/// Such a directory is removed when it has no monitor, holds nothing but an
/// unfinished details file, and nothing in it changed for `min_age`: no
/// tag, port or service can refer to it yet. Returns how many were removed.
pub(super) fn remove_unborn_nodes(config: &iceoryx2::config::Config, min_age: Duration) -> usize {
    let g = &config.global;
    let nodes = PathBuf::from(g.node_dir().to_string());
    let Ok(entries) = std::fs::read_dir(&nodes) else { return 0 };
    let entries: Vec<_> = entries.flatten().collect();
    let prefix = g.prefix.to_string();
    let monitor = g.node.monitor_suffix.to_string();
    let details = format!("{prefix}node{}", g.node.static_config_suffix);
    let has_monitor = |id: &str| {
        let own = format!("{prefix}{id}{monitor}");
        entries.iter().any(|e| e.file_name().to_string_lossy().starts_with(&own))
    };
    let old =
        |m: &std::fs::Metadata| m.modified().ok().and_then(|t| t.elapsed().ok()).is_some_and(|age| age >= min_age);
    let mut removed = 0;
    for dir in &entries {
        let id = dir.file_name().to_string_lossy().into_owned();
        let is_node_dir = !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit());
        if !is_node_dir || !dir.metadata().is_ok_and(|m| m.is_dir() && old(&m)) || has_monitor(&id) {
            continue;
        }
        let Ok(inside) = std::fs::read_dir(dir.path()) else { continue };
        let inside: Vec<_> = inside.flatten().collect();
        let unborn = inside.iter().all(|f| {
            f.file_name().to_string_lossy() == details && f.metadata().is_ok_and(|m| being_written(&m) && old(&m))
        });
        if unborn && std::fs::remove_dir_all(dir.path()).is_ok() {
            removed += 1;
        }
    }
    removed
}

/// iceoryx2 0.10 writes a node's service and port tags as static storage:
/// created read-write, made read-only once written, and a read-write one is
/// taken for one still being created. A peer killed between the two (a
/// window with an fsync in it; the end-to-end tests that kill clients left
/// 14 such nodes in a morning) leaves a tag that iceoryx2's cleanup skips;
/// it then cannot remove the node's directory and fails on every later pass
/// ("cannot remove the resources of some dead peers", for ever). Marking
/// such a tag finished (read-only) lets the cleanup treat it as any other:
/// the node is taken out of the service, or the service is already gone,
/// and the tag is removed. Only tags of nodes iceoryx2 reports dead, whose
/// process is gone and will finish nothing: their cleanup removes all they
/// had anyway. Returns how many were marked. (Upstream's issue #1967 is the
/// port-tag half of the same leftover.)
pub(super) fn finish_orphaned_tags(config: &iceoryx2::config::Config) -> usize {
    let mut dead = Vec::new();
    let listed = Node::<Ipc>::list(config, |state| {
        if let NodeState::Dead(view) = state {
            dead.push(view.id().value());
        }
        CallbackProgression::Continue
    });
    if listed.is_err() {
        return 0;
    }
    let g = &config.global;
    let prefix = g.prefix.to_string();
    let suffixes = [g.node.service_tag_suffix.to_string(), g.node.port_tag_suffix.to_string()];
    let nodes = PathBuf::from(g.node_dir().to_string());
    let mut finished = 0;
    for id in dead {
        let Ok(entries) = std::fs::read_dir(nodes.join(id.to_string())) else { continue };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let Ok(meta) = e.metadata() else { continue };
            let tag = name.starts_with(&prefix) && suffixes.iter().any(|s| name.ends_with(s.as_str()));
            if tag
                && being_written(&meta)
                && std::fs::set_permissions(e.path(), std::fs::Permissions::from_mode(0o400)).is_ok()
            {
                finished += 1;
            }
        }
    }
    finished
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{BufRead, BufReader};
    use std::process::{Command, Stdio};

    /// Set in the child process this test starts: the iceoryx2 root it uses.
    const CHILD_ROOT: &str = "GRASPD_TEST_JANITOR_CHILD_ROOT";

    fn config_at(root: &std::path::Path) -> iceoryx2::config::Config {
        let mut c = ipc_config();
        let root = format!("{}/", root.display());
        c.global.set_root_path(&Path::new_normalized(root.as_bytes()).expect("a short temporary path"));
        c
    }

    /// The child: a node with a service and a port, then waits to be killed.
    fn peer(root: &str) {
        let config = config_at(std::path::Path::new(root));
        let node = NodeBuilder::new().config(&config).create::<Ipc>().expect("a node");
        let name: ServiceName = "graspd-test/janitor".try_into().expect("a service name");
        let service = node.service_builder(&name).event().open_or_create().expect("a service");
        let _notifier = service.notifier_builder().create().expect("a port");
        println!("READY");
        std::thread::sleep(Duration::from_secs(60));
    }

    #[test]
    fn directories_of_nodes_never_made_are_removed_once_old() {
        let root = tempfile::tempdir().expect("a temporary directory");
        let config = config_at(root.path());
        let nodes = PathBuf::from(config.global.node_dir().to_string());
        let make = |id: &str, files: &[(&str, u32)]| {
            let d = nodes.join(id);
            std::fs::create_dir_all(&d).unwrap();
            for (name, mode) in files {
                let f = d.join(name);
                std::fs::write(&f, b"x").unwrap();
                std::fs::set_permissions(&f, std::fs::Permissions::from_mode(*mode)).unwrap();
            }
            d
        };
        let empty = make("1111", &[]);
        let half_written = make("2222", &[("iox2_node.details", 0o600)]);
        let finished = make("3333", &[("iox2_node.details", 0o400)]);
        let with_tag = make("4444", &[("iox2_node.details", 0o600), ("iox2_ab.service_tag", 0o600)]);
        let monitored = make("5555", &[("iox2_node.details", 0o600)]);
        std::fs::write(nodes.join("iox2_5555.node_monitor"), b"").unwrap();
        let not_a_node = make("spare", &[]);
        // A node being made right now (young) is never touched.
        assert_eq!(remove_unborn_nodes(&config, Duration::from_secs(3600)), 0);
        assert_eq!(remove_unborn_nodes(&config, Duration::ZERO), 2);
        assert!(!empty.exists() && !half_written.exists());
        assert!(finished.exists() && with_tag.exists() && monitored.exists() && not_a_node.exists());
    }

    #[test]
    fn a_killed_peers_unfinished_tags_are_cleaned_up() {
        if let Ok(root) = std::env::var(CHILD_ROOT) {
            return peer(&root);
        }
        let root = tempfile::tempdir().expect("a temporary directory");
        let config = config_at(root.path());
        let mut child = Command::new(std::env::current_exe().expect("the test binary"))
            .args(["--exact", "service::janitor::tests::a_killed_peers_unfinished_tags_are_cleaned_up", "--nocapture"])
            .env(CHILD_ROOT, root.path())
            .stdout(Stdio::piped())
            .spawn()
            .expect("the peer process");
        let ready = BufReader::new(child.stdout.take().expect("its stdout"))
            .lines()
            .map_while(Result::ok)
            .any(|l| l == "READY");
        child.kill().expect("killed");
        child.wait().expect("reaped");
        assert!(ready, "the peer did not get its node and service up");
        // The peer killed while writing its tags: they are left read-write (unfinished).
        let nodes = PathBuf::from(config.global.node_dir().to_string());
        let dirs: Vec<PathBuf> =
            std::fs::read_dir(&nodes).unwrap().flatten().map(|e| e.path()).filter(|p| p.is_dir()).collect();
        assert_eq!(dirs.len(), 1, "{dirs:?}");
        let mut tags = 0;
        for e in std::fs::read_dir(&dirs[0]).unwrap().flatten() {
            if e.file_name().to_string_lossy().ends_with("_tag") {
                std::fs::set_permissions(e.path(), std::fs::Permissions::from_mode(0o600)).unwrap();
                tags += 1;
            }
        }
        assert!(tags >= 2, "a service tag and a port tag: {tags}");
        let janitor = janitor_node(&config).expect("a janitor node");
        let c = cleanup_dead_nodes(&janitor, &config);
        assert_eq!((c.cleanups, c.failed_cleanups), (1, 0));
        let left: Vec<_> =
            std::fs::read_dir(&dirs[0]).map(|d| d.flatten().map(|e| e.file_name()).collect()).unwrap_or_default();
        assert!(!dirs[0].exists(), "the dead node's directory is removed: {left:?}");
    }
}

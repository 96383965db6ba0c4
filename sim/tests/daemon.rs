//! End to end: the simulator as a client of a running daemon. `graspd
//! serve` runs as a separate process (the binary built in this target
//! directory: `cargo build --release --workspace` builds it) under a service
//! prefix of its own, and `sim place --grasp-from daemon` runs a Place-mug
//! episode whose grasp comes from the scene camera's view through it.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use graspd_client::protocol::Method;
use graspd_client::{Client, ClientOptions};

/// `graspd` beside this test's executable (target/<profile>/deps/.. ).
fn graspd_binary() -> PathBuf {
    let exe = std::env::current_exe().expect("the test knows its own path");
    let dir = exe.parent().and_then(|d| d.parent()).expect("the test runs from target/<profile>/deps");
    let graspd = dir.join(format!("graspd{}", std::env::consts::EXE_SUFFIX));
    assert!(
        graspd.is_file(),
        "{} is missing: this test runs the daemon as a separate process; run `cargo build --release --workspace` first",
        graspd.display()
    );
    graspd
}

/// A daemon of its own: a temporary configuration, a unique prefix; stopped
/// (SIGTERM, then SIGKILL after 5 s) when dropped.
struct Daemon {
    child: Child,
    prefix: String,
    _dir: tempfile::TempDir,
}

impl Daemon {
    fn start(name: &str) -> Daemon {
        Self::start_with(name, &["mug"])
    }

    /// A daemon serving `categories`.
    fn start_with(name: &str, categories: &[&str]) -> Daemon {
        let graspd = graspd_binary();
        let prefix = format!("graspd_sim_test_{}_{name}", std::process::id());
        let dir = tempfile::tempdir().unwrap();
        let cfg = dir.path().join("graspd.toml");
        std::fs::write(
            &cfg,
            format!(
                "service_prefix = \"{prefix}\"\ncategories = {categories:?}\nworkers = 1\nhousekeeping_ms = 100\nslow_request_ms = 5000.0\n"
            ),
        )
        .unwrap();
        let mut child = Command::new(&graspd)
            .args(["serve", "--json", "--config", cfg.to_str().unwrap()])
            .env("GRASPD_LOG", "warn")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("graspd serve starts");
        let out = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let daemon = Daemon { child, prefix, _dir: dir };
        // Up to minutes: a stale shape-space cache is rebuilt before it serves.
        let ready = rx.recv_timeout(Duration::from_secs(300)).expect("the daemon reports that it serves");
        let v: serde_json::Value = serde_json::from_str(&ready).expect("the ready line is JSON");
        assert_eq!(v["ready"], true, "{ready}");
        daemon
    }

    /// A client that waits for Health to say the daemon serves.
    fn client(&self) -> Client {
        let mut client = Client::connect(ClientOptions {
            prefix: self.prefix.clone(),
            connect_timeout: Duration::from_secs(30),
            ..ClientOptions::default()
        })
        .expect("the client connects");
        let t0 = Instant::now();
        loop {
            let h = client.health().expect("Health answers");
            if h.serving && h.grasp_available {
                return client;
            }
            assert!(t0.elapsed() < Duration::from_secs(30), "not serving Grasp: {h:?}");
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = Command::new("kill").args(["-s", "TERM", &self.child.id().to_string()]).status();
            let t0 = Instant::now();
            while let Ok(None) = self.child.try_wait() {
                if t0.elapsed() > Duration::from_secs(5) {
                    let _ = self.child.kill();
                    break;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        let _ = self.child.wait();
    }
}

/// One Place-mug episode on the canonical mug with its grasp from the
/// daemon: the daemon answered one Grasp, the episode used it (a solved
/// grasp, not the demonstration, with its round trip), and the mug was lifted.
#[test]
fn a_place_mug_episode_takes_its_grasp_from_the_daemon() {
    let daemon = Daemon::start("place");
    let mut client = daemon.client();
    let out = Command::new(env!("CARGO_BIN_EXE_sim"))
        .args([
            "place",
            "--grasp-from",
            "daemon",
            "--daemon-prefix",
            &daemon.prefix,
            "--instances",
            "canonical",
            "--episodes",
            "1",
            "--json",
        ])
        .output()
        .expect("sim runs");
    assert!(out.status.success(), "sim place failed: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("sim prints JSON");
    assert_eq!(v["grasp_from"], "daemon", "{v}");
    assert_eq!(v["start"], "pregrasp", "{v}");
    let row = &v["results"][0];
    assert_eq!(row["instance"], "mug_canonical");
    assert_eq!(row["grasp_source"], "daemon");
    let e = &row["episodes"][0];
    let g = &e["grasp"];
    assert_eq!(g["source"], "daemon", "{g}");
    assert!(g["latency_ms"].as_f64().is_some_and(|ms| ms > 0.0), "{g}");
    assert!(g["cloud_points"].as_u64().is_some_and(|n| n > 1000), "{g}");
    // A grasp solved on the registered shape: the demonstration itself would score 0.
    let tsd = g["task_space_distance_cm"].as_f64().unwrap();
    assert!(tsd > 0.0 && tsd < 2.0, "{g}");
    // The daemon's own count: exactly the one Grasp, answered OK.
    let stats = client.stats().expect("Stats answers");
    let grasp = &stats.methods[Method::Grasp as usize];
    assert_eq!(grasp.requests, 1, "Grasp requests");
    assert_eq!(grasp.by_status[0], 1, "Grasp answered OK");
    // The episode behaved: the mug was lifted clear of the table, and ended near its goal.
    assert!(e["clearance_after_lift_m"].as_f64().unwrap() > 0.05, "{e}");
    assert!(e["final_distance_m"].as_f64().unwrap() < 0.10, "{e}");
}

/// `--grasp-from register` does what the daemon's Grasp does, in this
/// process: for the same camera view (a training hammer at a Drive-nail
/// start, the table given) the daemon's answer and the in-process engine's
/// are the same grasp, pre-grasp, registered pose and latent. So a gap
/// between daemon grasps and in-process grasps from the tool's training
/// latent is the registration's, not the transport's; and the register path
/// (which runs without a daemon) stands in for it in measurements.
#[test]
fn the_register_path_gives_the_daemons_grasp() {
    use graspd::tools::{self, Category};
    use graspd_sim::camera::{LabFrame, SceneCamera};
    use graspd_sim::daemon::{DaemonGrasper, DaemonOptions};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

    let daemon = Daemon::start_with("register", &["hammer"]);
    let _ = daemon.client();
    let hand = graspd::hand::HandModel::default_sih().unwrap();
    let space =
        graspd::shape::builtin::load_or_build(Category::Hammer, &graspd_sim::plan::spaces_dir(), |_, _| {}).unwrap();
    let options =
        DaemonOptions { prefix: daemon.prefix.clone(), connect_timeout: Duration::from_secs(30), ..Default::default() };
    let mut remote = DaemonGrasper::connect(
        options,
        Category::Hammer,
        space.modes.len(),
        SceneCamera::default(),
        LabFrame::default(),
    )
    .unwrap();
    let mut local =
        DaemonGrasper::in_process(&hand, Category::Hammer, space, SceneCamera::default(), LabFrame::default()).unwrap();
    assert!(remote.is_daemon() && !local.is_daemon());
    let tool = tools::family(Category::Hammer).unwrap().into_iter().find(|i| i.name == "hammer_train_00").unwrap();
    let start = Isometry3::from_parts(
        Translation3::new(0.01, -0.02, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.1),
    );
    for seed in [0, 1] {
        let a = remote.grasp(&hand, Category::Hammer, &tool.mesh, &start, 0.0, true, seed).unwrap();
        let b = local.grasp(&hand, Category::Hammer, &tool.mesh, &start, 0.0, true, seed).unwrap();
        assert_eq!(a.cloud_points, b.cloud_points);
        for (x, y) in [(&a.grasp, &b.grasp), (&a.pregrasp, &b.pregrasp)] {
            let dt = (x.wrist_pose_world.translation.vector - y.wrist_pose_world.translation.vector).norm();
            let dr = x.wrist_pose_world.rotation.angle_to(&y.wrist_pose_world.rotation);
            assert!(dt < 1e-5 && dr < 1e-4, "seed {seed}: wrists {dt} m, {dr} rad apart");
            for (p, q) in x.actuated.iter().zip(&y.actuated) {
                assert!((p - q).abs() < 1e-4, "seed {seed}: joints {:?} vs {:?}", x.actuated, y.actuated);
            }
        }
        assert!((a.tool_from_canonical.scale - b.tool_from_canonical.scale).abs() < 1e-6);
        assert!((a.tool_from_canonical.translation - b.tool_from_canonical.translation).norm() < 1e-6);
        for (p, q) in a.latent.iter().zip(&b.latent) {
            assert!((p - q).abs() < 1e-6, "seed {seed}: latents {:?} vs {:?}", a.latent, b.latent);
        }
        assert_eq!(a.pregrasp_collision_free, b.pregrasp_collision_free);
    }
}

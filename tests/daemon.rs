//! End-to-end: `graspd serve` as a separate process, called through the
//! graspd-client SDK (and graspctl). Each test runs its own daemon under a
//! unique service prefix, so the tests run in parallel without colliding.
//! Clouds are rendered by `graspd cloud` from the built-in test mugs; the
//! expected answers come from `graspd register` on the same files.

use graspd_client::protocol::{self as proto, Point};
use graspd_client::{cloudfile, Client, ClientOptions, Cloud, CloudOptions, StatusCode, WaitMode};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

const GRASPD: &str = env!("CARGO_BIN_EXE_graspd");
const TIMEOUT: Duration = Duration::from_secs(30);

fn graspd_json(args: &[&str]) -> serde_json::Value {
    let out = Command::new(GRASPD).args(args).env("GRASPD_LOG", "warn").output().expect("graspd runs");
    assert!(out.status.success(), "graspd {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("JSON")
}

/// Two rendered mug views and what `graspd register` says about them (this
/// also builds the mug shape space in the default cache once, before any daemon).
struct Fixture {
    _dir: tempfile::TempDir,
    views: Vec<(PathBuf, Vec<[f32; 3]>, serde_json::Value)>,
    /// `graspd grasp --json` on the first view.
    grasp: serde_json::Value,
    /// `graspd register --table-z 0 --json` on the first view (the mug stands on z = 0).
    on_table: serde_json::Value,
    /// `graspd hand info --json`: the bundled hand the daemon's Grasp solves for.
    hand: serde_json::Value,
    /// `graspd register --viewpoint FIRST_CAMERA --second-viewpoint SECOND_CAMERA
    /// --json` on the first view.
    two_cameras: serde_json::Value,
}

/// The camera positions of `Fixture::two_cameras`, in the cloud's frame.
const FIRST_CAMERA: [f32; 3] = [0.05, -0.45, 0.4];
const SECOND_CAMERA: [f32; 3] = [0.45, 0.05, 0.3];

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let assets = Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/tools/mug");
        let mut views = Vec::new();
        for (mesh, view) in [("mug_test_00.obj", "0"), ("mug_test_01.obj", "3")] {
            let out = dir.path().join(format!("{mesh}.{view}.ply"));
            let m = assets.join(mesh);
            graspd_json(&[
                "cloud",
                "--mesh",
                m.to_str().unwrap(),
                "--view",
                view,
                "--seed",
                "1",
                "--out",
                out.to_str().unwrap(),
                "--json",
            ]);
            let expected = graspd_json(&["register", "--category", "mug", "--cloud", out.to_str().unwrap(), "--json"]);
            let points = cloudfile::read_cloud(&out).unwrap();
            views.push((out, points, expected));
        }
        let grasp = graspd_json(&["grasp", "--category", "mug", "--cloud", views[0].0.to_str().unwrap(), "--json"]);
        let first = views[0].0.to_str().unwrap();
        let on_table = graspd_json(&["register", "--category", "mug", "--cloud", first, "--table-z", "0", "--json"]);
        let hand = graspd_json(&["hand", "info", "--json"]);
        let text = |c: [f32; 3]| format!("{},{},{}", c[0], c[1], c[2]);
        let (a, b) = (text(FIRST_CAMERA), text(SECOND_CAMERA));
        let args = ["register", "--category", "mug", "--cloud", first, "--viewpoint", &a, "--second-viewpoint", &b];
        let two_cameras = graspd_json(&[&args[..], &["--json"]].concat());
        Fixture { _dir: dir, views, grasp, on_table, hand, two_cameras }
    })
}

static COUNTER: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

fn unique_prefix(name: &str) -> String {
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    format!("graspd_test_{}_{n}_{name}", std::process::id())
}

struct Daemon {
    child: Child,
    prefix: String,
    dir: tempfile::TempDir,
    stdout: Option<std::sync::mpsc::Receiver<String>>,
}

impl Daemon {
    /// Starts a mug-only daemon with `extra` configuration lines; waits until it serves.
    fn start(name: &str, extra: &str) -> Daemon {
        fixture();
        let prefix = unique_prefix(name);
        Self::start_with_prefix(&prefix, extra, &[])
    }

    fn start_with_prefix(prefix: &str, extra: &str, args: &[&str]) -> Daemon {
        let dir = tempfile::tempdir().unwrap();
        let cfg = dir.path().join("graspd.toml");
        // Test defaults, unless `extra` sets the key.
        let base = [
            format!("service_prefix = \"{prefix}\""),
            "categories = [\"mug\"]".into(),
            "workers = 2".into(),
            "housekeeping_ms = 100".into(),
            "slow_request_ms = 5000.0".into(),
        ];
        let keys: Vec<&str> = extra.lines().filter_map(|l| l.split('=').next()).map(str::trim).collect();
        let mut text: Vec<String> =
            base.into_iter().filter(|l| !keys.contains(&l.split('=').next().unwrap().trim())).collect();
        text.push(extra.to_owned());
        std::fs::write(&cfg, text.join("\n")).unwrap();
        let mut child = Command::new(GRASPD)
            .args(["serve", "--json", "--config", cfg.to_str().unwrap()])
            .args(args)
            .env("GRASPD_LOG", "warn")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("graspd serve starts");
        let (tx, rx) = std::sync::mpsc::channel();
        let out = child.stdout.take().unwrap();
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let ready = rx.recv_timeout(Duration::from_secs(120)).expect("the daemon reports it serves");
        let v: serde_json::Value = serde_json::from_str(&ready).expect("ready line is JSON");
        assert_eq!(v["ready"], true, "{ready}");
        Daemon { child, prefix: prefix.to_owned(), dir, stdout: Some(rx) }
    }

    fn options(&self) -> ClientOptions {
        ClientOptions { prefix: self.prefix.clone(), ..ClientOptions::default() }
    }

    fn client(&self) -> Client {
        Client::connect(self.options()).expect("client connects")
    }

    fn signal(&self, sig: &str) {
        let ok = Command::new("kill").args(["-s", sig, &self.child.id().to_string()]).status().unwrap().success();
        assert!(ok, "kill -s {sig}");
    }

    /// Waits for the daemon to exit; returns its exit status and the JSON report it printed.
    fn wait_exit(&mut self, within: Duration) -> (std::process::ExitStatus, String) {
        let t0 = Instant::now();
        loop {
            if let Some(st) = self.child.try_wait().unwrap() {
                let rest: Vec<String> = self.stdout.take().map(|rx| rx.iter().collect()).unwrap_or_default();
                return (st, rest.join("\n"));
            }
            assert!(t0.elapsed() < within, "the daemon did not exit within {within:?}");
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for Daemon {
    /// A graceful stop (the daemon removes its shared-memory resources), SIGKILL after 5 s.
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
        let _ = &self.dir;
    }
}

fn floats(v: &serde_json::Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

/// The daemon's Grasp against `graspd grasp --json` on the same cloud: the same numbers.
fn assert_same_grasp(got: &graspd_client::Grasp, expected: &serde_json::Value) {
    assert_same_registration(&got.registration, &expected["registration"]);
    for (h, e) in [(&got.grasp, &expected["grasp"]), (&got.pregrasp, &expected["pregrasp"])] {
        assert_eq!(h.wrist_pose.translation.to_vec(), floats(&e["wrist_pose"]["translation"]));
        assert_eq!(h.wrist_pose.rotation_xyzw.to_vec(), floats(&e["wrist_pose"]["rotation_xyzw"]));
        assert_eq!(h.joints.len(), e["joints"].as_object().unwrap().len());
        for (name, q) in &h.joints {
            assert_eq!(*q, e["joints"][name].as_f64().unwrap(), "{name}");
        }
        for (name, q) in &h.actuated {
            assert_eq!(*q, e["actuated"][name].as_f64().unwrap(), "{name}");
        }
    }
    assert!((got.task_space_distance_m * 100.0 - expected["task_space_distance_cm"].as_f64().unwrap()).abs() < 1e-12);
    assert_eq!(got.pregrasp_collision_free, expected["pregrasp"]["collision_free"].as_bool().unwrap());
    assert_eq!(got.table_z_m, expected["table_z"].as_f64());
}

fn assert_same_registration(got: &graspd_client::Registration, expected: &serde_json::Value) {
    let latent = floats(&expected["latent"]);
    assert_eq!(got.latent, latent, "latent");
    assert_eq!(got.scale, expected["scale"].as_f64().unwrap());
    let kps = expected["keypoints"].as_array().unwrap();
    assert_eq!(got.keypoints.len(), kps.len());
    for (g, e) in got.keypoints.iter().zip(kps) {
        assert_eq!(g.name, e["name"].as_str().unwrap());
        let p: Vec<f64> = e["position"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        assert_eq!(g.position.to_vec(), p, "{}", g.name);
    }
    let q: Vec<f64> =
        expected["pose"]["rotation_xyzw"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert_eq!(got.pose.rotation_xyzw.to_vec(), q);
    assert_eq!(got.fit.confident, expected["fit"]["confident"].as_bool().unwrap());
    assert_eq!(got.fit.ambiguous_pose, expected["fit"]["ambiguous_pose"].as_bool().unwrap());
    assert_eq!(u64::from(got.fit.stray_points), expected["fit"]["stray_points"].as_u64().unwrap());
    // Every verdict of the fit the CLI prints travels (protocol 3), in the SDK's SI units.
    let fit = &expected["fit"];
    assert_eq!(u64::from(got.fit.table_points), fit["table_points"].as_u64().unwrap());
    assert_eq!(got.fit.coverage, fit["coverage"].as_f64().unwrap());
    assert_eq!(got.fit.latent_mahalanobis, fit["latent_mahalanobis"].as_f64().unwrap());
    assert!((got.fit.view_width_m * 1e3 - fit["view_width_mm"].as_f64().unwrap()).abs() < 1e-9);
    assert_eq!(got.fit.contradicted_fraction, fit["contradicted_fraction"].as_f64(), "contradicted fraction");
    // No camera position in these requests: the daemon's estimate is the CLI's (null when unsettled).
    let estimated: Option<Vec<f64>> = serde_json::from_value(expected["estimated_viewpoint"].clone()).unwrap();
    assert_eq!(got.viewpoint.estimated().map(|p| p.to_vec()), estimated, "estimated viewpoint");
    assert!(!matches!(got.viewpoint, graspd_client::Viewpoint::Given { .. }));
    // The yaw arc: its half width travels as f32; the axis and spreads the SDK derives.
    let arc = got.yaw_arc([0.0, 0.0, 1.0]).expect("assessed: the requests' up is z");
    let close = |a: f64, b: &serde_json::Value| (a - b.as_f64().unwrap()).abs() < 1e-6;
    assert!(close(arc.half_width_rad, &expected["yaw_arc"]["half_width_rad"]), "{arc:?}");
    for (a, e) in arc.axis_cloud.iter().zip(expected["yaw_arc"]["axis_cloud"].as_array().unwrap()) {
        assert!(close(*a, e), "{arc:?} against {}", expected["yaw_arc"]);
    }
    for (a, e) in arc.keypoint_spread_m.iter().zip(expected["yaw_arc"]["keypoint_spread_m"].as_array().unwrap()) {
        assert!(close(*a, e), "{arc:?} against {}", expected["yaw_arc"]);
    }
}

#[test]
fn concurrent_clients_get_the_same_answers_as_the_cli() {
    let d = Daemon::start("concurrent", "");
    let f = fixture();
    let threads: Vec<_> = (0..4)
        .map(|t| {
            let opts = d.options();
            std::thread::spawn(move || {
                let f = fixture();
                let mut c = Client::connect(opts).unwrap();
                for i in 0..3 {
                    let (_, points, expected) = &f.views[(t + i) % f.views.len()];
                    let r = c.register("mug", points, TIMEOUT).unwrap();
                    assert_same_registration(&r, expected);
                    assert_eq!(r.points as usize, points.len());
                    assert!(c.health().unwrap().serving);
                }
                if c.health().unwrap().grasp_available {
                    assert_same_grasp(&c.grasp("mug", &f.views[0].1, TIMEOUT).unwrap(), &f.grasp);
                }
            })
        })
        .collect();
    for t in threads {
        t.join().expect("client thread");
    }
    let mut c = d.client();
    // Health names the hand Grasp solves for, as `graspd hand info` does; the category says it is served.
    let h = c.health().unwrap();
    assert_eq!(h.hand_name.as_deref(), f.hand["name"].as_str());
    assert_eq!(h.hand_actuated_joints as usize, f.hand["actuated"].as_array().unwrap().len());
    assert_eq!(c.categories().unwrap()[0].grasp_available, h.grasp_available);
    // A given table is the registration's support, as `graspd register --table-z` makes it.
    let on_table = CloudOptions { table: Some(graspd_client::Table::At(0.0)), ..CloudOptions::default() };
    let r = c.register_with("mug", &f.views[0].1, &on_table, TIMEOUT).unwrap();
    assert_same_registration(&r, &f.on_table);
    assert_ne!(f.on_table["keypoints"], f.views[0].2["keypoints"], "the table changed nothing");
    let cats = c.categories().unwrap();
    assert_eq!(cats.len(), 1);
    assert_eq!(cats[0].name, "mug");
    assert_eq!(cats[0].keypoints.len(), f.views[0].2["keypoints"].as_array().unwrap().len());
    let s = c.stats().unwrap();
    let reg = &s.methods[proto::Method::Register as usize];
    assert_eq!(reg.requests, 13);
    assert_eq!(reg.by_status[0], 13);
    assert!(reg.compute_p50_us > 0.0 && reg.latency_p50_us >= reg.compute_p50_us);
    // graspctl reads the same daemon (same JSON shape as `graspd register`: keypoints, pose, fit).
    // graspctl is another package's binary: `cargo test` does not rebuild it,
    // so use it only when it is at least as new as this graspd.
    let graspctl = Path::new(GRASPD).with_file_name("graspctl");
    let mtime = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    let fresh = matches!((mtime(&graspctl), mtime(Path::new(GRASPD))), (Some(a), Some(b)) if a >= b);
    if !fresh {
        eprintln!(
            "skipping the graspctl check: {} is absent or older than graspd (cargo build --release -p graspd-client)",
            graspctl.display()
        );
    }
    if fresh {
        let out = Command::new(&graspctl)
            .args([
                "--prefix",
                &d.prefix,
                "register",
                "--category",
                "mug",
                "--cloud",
                f.views[0].0.to_str().unwrap(),
                "--json",
            ])
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(v["keypoints"], f.views[0].2["keypoints"]);
        assert_eq!(v["pose"], f.views[0].2["pose"]);
        assert_eq!(v["latent"], f.views[0].2["latent"]);
        assert_eq!(v["estimated_viewpoint"], f.views[0].2["estimated_viewpoint"]);
    }
}

#[test]
fn bad_inputs_get_their_status_and_the_daemon_keeps_serving() {
    let d = Daemon::start("bad", "max_points = 50000\nmax_in_flight_per_client = 1");
    let f = fixture();
    let good: Vec<Point> = Point::from_arrays(&f.views[0].1).to_vec();
    let mut c = d.client();
    let set_mug = |h: &mut proto::RequestHeader| {
        h.category = proto::str_to_text("mug");
        h.up_in_cloud = [0.0, 0.0, 1.0];
    };
    let code = |r: Result<(proto::ResponseHeader, proto::RegisterResponse), graspd_client::Error>| {
        let (h, _) = r.expect("an answer");
        (StatusCode::from_u32(h.status), proto::text_lossy(&h.message))
    };
    type Edit = Box<dyn Fn(&mut proto::RequestHeader)>;
    let cases: Vec<(&str, Edit, Vec<Point>, StatusCode)> = vec![
        (
            "wrong protocol version",
            Box::new(move |h| {
                set_mug(h);
                h.protocol_version = 99
            }),
            good.clone(),
            StatusCode::InvalidArgument,
        ),
        (
            "a reserved field set (a newer protocol's?)",
            Box::new(move |h| {
                set_mug(h);
                h.reserved = 1
            }),
            good.clone(),
            StatusCode::InvalidArgument,
        ),
        (
            "a second camera without the first",
            Box::new(move |h| {
                set_mug(h);
                h.flags = proto::flags::SECOND_VIEWPOINT;
                h.second_viewpoint_in_cloud_m = SECOND_CAMERA
            }),
            good.clone(),
            StatusCode::InvalidArgument,
        ),
        (
            "unknown flags",
            Box::new(move |h| {
                set_mug(h);
                h.flags = 4
            }),
            good.clone(),
            StatusCode::InvalidArgument,
        ),
        (
            "unknown category",
            Box::new(move |h| {
                set_mug(h);
                h.category = proto::str_to_text("teapot")
            }),
            good.clone(),
            StatusCode::NotFound,
        ),
        (
            "garbage category bytes",
            Box::new(move |h| {
                set_mug(h);
                h.category = [0xfe; 32]
            }),
            good.clone(),
            StatusCode::InvalidArgument,
        ),
        (
            "garbage after the NUL",
            Box::new(move |h| {
                set_mug(h);
                h.category[20] = b'x'
            }),
            good.clone(),
            StatusCode::InvalidArgument,
        ),
        (
            "garbage frame name",
            Box::new(move |h| {
                set_mug(h);
                h.cloud_frame = [0xc3; 32]
            }),
            good.clone(),
            StatusCode::InvalidArgument,
        ),
        ("empty cloud", Box::new(set_mug), vec![], StatusCode::InvalidArgument),
        (
            "NaN",
            Box::new(set_mug),
            {
                let mut v = good.clone();
                v[7].0[1] = f32::NAN;
                v
            },
            StatusCode::InvalidArgument,
        ),
        (
            "Inf",
            Box::new(set_mug),
            {
                let mut v = good.clone();
                v[0].0[2] = f32::NEG_INFINITY;
                v
            },
            StatusCode::InvalidArgument,
        ),
        (
            "NaN up",
            Box::new(move |h| {
                set_mug(h);
                h.up_in_cloud = [f32::NAN, 0.0, 1.0]
            }),
            good.clone(),
            StatusCode::InvalidArgument,
        ),
        ("too many points", Box::new(set_mug), vec![Point([0.01, 0.02, 0.03]); 50_001], StatusCode::ResourceExhausted),
        (
            "expired deadline",
            Box::new(move |h| {
                set_mug(h);
                h.deadline_unix_ns = 1
            }),
            good.clone(),
            StatusCode::DeadlineExceeded,
        ),
        ("all points at one place", Box::new(set_mug), vec![Point([0.1, 0.2, 0.3]); 500], StatusCode::InvalidArgument),
        (
            "a cloud in millimetres",
            Box::new(set_mug),
            good.iter().map(|p| Point(p.0.map(|x| x * 1000.0))).collect(),
            StatusCode::InvalidArgument,
        ),
    ];
    for (what, edit, points, want) in &cases {
        let (got, msg) = code(c.register_raw(Cloud::Slice(points), |h| edit(h), TIMEOUT));
        assert_eq!(got, *want, "{what}: {msg}");
        assert!(!msg.is_empty(), "{what}: a status without a message");
    }
    // A given camera position comes back as the one the fit used.
    let camera = [0.05f32, -0.45, 0.4];
    let (h, body) = c
        .register_raw(
            Cloud::Slice(&good),
            |h| {
                set_mug(h);
                h.flags = proto::flags::VIEWPOINT;
                h.viewpoint_in_cloud_m = camera
            },
            TIMEOUT,
        )
        .unwrap();
    assert_eq!(StatusCode::from_u32(h.status), StatusCode::Ok, "{}", proto::text_lossy(&h.message));
    assert_eq!(body.registration.viewpoint_source, proto::viewpoint_source::GIVEN);
    assert_eq!(body.registration.viewpoint_cloud_m, camera.map(f64::from));
    // Two cameras' positions: the answer of `graspd register --viewpoint
    // --second-viewpoint` on the same cloud.
    let co =
        CloudOptions { viewpoint: Some(FIRST_CAMERA), second_viewpoint: Some(SECOND_CAMERA), ..Default::default() };
    let r = c.register_with("mug", &f.views[0].1, &co, TIMEOUT).unwrap();
    assert_eq!(r.latent, floats(&f.two_cameras["latent"]), "two cameras: latent");
    for (g, e) in r.keypoints.iter().zip(f.two_cameras["keypoints"].as_array().unwrap()) {
        assert_eq!(g.position.to_vec(), floats(&e["position"]), "two cameras: {}", g.name);
    }
    // Grasp: its own checks (table, pre-grasp options), then the same answer as `graspd grasp`.
    for (what, edit) in [
        (
            "table_mode 7",
            Box::new(move |h: &mut proto::RequestHeader| {
                set_mug(h);
                h.table_mode = 7
            }) as Box<dyn Fn(&mut proto::RequestHeader)>,
        ),
        (
            "NaN table",
            Box::new(move |h| {
                set_mug(h);
                h.table_mode = proto::table_mode::GIVEN;
                h.table_z_m = f32::NAN
            }),
        ),
        (
            "back-off 3 m",
            Box::new(move |h| {
                set_mug(h);
                h.pregrasp_backoff_m = 3.0
            }),
        ),
        (
            "NaN viewpoint",
            Box::new(move |h| {
                set_mug(h);
                h.flags = proto::flags::VIEWPOINT;
                h.viewpoint_in_cloud_m = [0.0, f32::NAN, 0.0]
            }),
        ),
    ] {
        let (h, _) = c.grasp_raw(Cloud::Slice(&good), |h| edit(h), TIMEOUT).unwrap();
        assert_eq!(
            StatusCode::from_u32(h.status),
            StatusCode::InvalidArgument,
            "{what}: {}",
            proto::text_lossy(&h.message)
        );
    }
    match c.grasp("mug", &f.views[0].1, TIMEOUT) {
        Ok(g) => assert_same_grasp(&g, &f.grasp),
        Err(e) => {
            assert!(!c.health().unwrap().grasp_available, "{e}");
            assert_eq!(e.code, StatusCode::FailedPrecondition, "{e}");
        }
    }
    // More than max_in_flight_per_client (1) requests from one client at once.
    // The first is the largest cloud allowed (the view repeated), so that it is
    // still being worked on when the second arrives (one view alone took 5 ms,
    // and a fast daemon had answered it before the second was sent).
    let heavy: Vec<[f32; 3]> = f.views[0].1.iter().cycle().take(50_000).copied().collect();
    let first = c.start_register("mug", &heavy, TIMEOUT).unwrap();
    let second = c.start_register("mug", &f.views[1].1, TIMEOUT).unwrap();
    let r2 = c.wait_register(second);
    assert_eq!(r2.unwrap_err().code, StatusCode::ResourceExhausted);
    assert!(c.wait_register(first).is_ok());
    // The daemon still serves, correctly, and counted every answer.
    assert_same_registration(&c.register("mug", &f.views[1].1, TIMEOUT).unwrap(), &f.views[1].2);
    let s = c.stats().unwrap();
    let reg = &s.methods[proto::Method::Register as usize];
    // The cases, the given camera positions, the two in flight at once and the last.
    assert_eq!(reg.requests as usize, cases.len() + 5);
    assert_eq!(reg.by_status[StatusCode::InvalidArgument as usize], 13);
    assert_eq!(reg.by_status[StatusCode::NotFound as usize], 1);
    assert_eq!(reg.by_status[StatusCode::DeadlineExceeded as usize], 1);
    assert_eq!(reg.by_status[StatusCode::ResourceExhausted as usize], 2);
    assert_eq!(reg.in_flight, 0);
}

#[test]
fn a_client_killed_mid_request_costs_nothing() {
    let d = Daemon::start("killed", "");
    let f = fixture();
    let graspctl = Path::new(GRASPD).with_file_name("graspctl");
    if !graspctl.exists() {
        eprintln!("skipped: {} is not built (cargo test --workspace builds it)", graspctl.display());
        return;
    }
    // graspctl processes killed at every stage: starting, creating their
    // iceoryx2 ports, sending, waiting while the request is worked on.
    for (i, delay_ms) in [1u64, 3, 5, 8, 12, 18, 25].into_iter().enumerate() {
        let mut child = Command::new(&graspctl)
            .args([
                "--prefix",
                &d.prefix,
                "--wait",
                "event",
                "register",
                "--category",
                "mug",
                "--cloud",
                f.views[i % 2].0.to_str().unwrap(),
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(delay_ms));
        child.kill().unwrap();
        child.wait().unwrap();
    }
    // New clients connect (their node creation must not hang on the dead ones' leftovers).
    let mut c = d.client();
    assert_same_registration(&c.register("mug", &f.views[0].1, TIMEOUT).unwrap(), &f.views[0].2);
    // The dead clients' resources are removed by the daemon's housekeeping.
    let t0 = Instant::now();
    loop {
        let s = c.stats().unwrap();
        let in_flight: u32 = s.methods.iter().map(|m| m.in_flight).sum();
        if s.clients_connected == 1 && in_flight == 0 {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "dead clients linger: {} connected, {in_flight} in flight",
            s.clients_connected
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(c.health().unwrap().serving);
}

#[test]
fn a_waiting_client_survives_a_daemon_crash_and_restart() {
    let mut d = Daemon::start("restart", "");
    let opts = d.options();
    let first_pid = d.client().health().unwrap().pid;
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let worker = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let f = fixture();
            let mut c = Client::connect(opts).unwrap();
            let mut max_attempts = 0;
            let mut calls = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let r = c.register("mug", &f.views[0].1, TIMEOUT).expect("the call survives the restart");
                assert_same_registration(&r, &f.views[0].2);
                max_attempts = max_attempts.max(c.last_call().attempts);
                calls += 1;
            }
            (calls, max_attempts, c.health().unwrap().pid)
        })
    };
    std::thread::sleep(Duration::from_millis(300));
    d.signal("KILL");
    let _ = d.wait_exit(Duration::from_secs(5));
    std::thread::sleep(Duration::from_millis(200));
    let prefix = d.prefix.clone();
    let d2 = Daemon::start_with_prefix(&prefix, "", &[]);
    std::thread::sleep(Duration::from_millis(300));
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let (calls, max_attempts, pid) = worker.join().expect("client thread");
    assert!(calls > 2, "{calls} calls");
    assert!(max_attempts >= 2, "no call had to be resent ({calls} calls)");
    assert_ne!(pid, first_pid, "the client talks to the new daemon");
    assert_eq!(pid, d2.client().health().unwrap().pid);
}

#[test]
fn sigterm_while_busy_finishes_the_requests_in_flight() {
    let mut d = Daemon::start("sigterm", "workers = 1\nmax_in_flight_per_client = 16");
    let f = fixture();
    let mut c = d.client();
    // Sixteen requests (about 100 ms of work): three were gone in a few
    // milliseconds, before a loaded machine let the first Stats call through.
    let pending: Vec<_> = (0..16).map(|i| c.start_register("mug", &f.views[i % 2].1, TIMEOUT).unwrap()).collect();
    // Busy: one request on the worker, the others queued behind it.
    let t0 = Instant::now();
    while c.stats().unwrap().queued == 0 {
        assert!(t0.elapsed() < Duration::from_secs(5), "the requests never queued");
    }
    d.signal("TERM");
    for (i, p) in pending.into_iter().enumerate() {
        let r = c.wait_register(p).expect("an in-flight request finishes");
        assert_same_registration(&r, &f.views[i % 2].2);
    }
    let (status, report) = d.wait_exit(Duration::from_secs(20));
    assert!(status.success(), "{status:?}");
    let v: serde_json::Value = serde_json::from_str(&report).unwrap_or_else(|e| panic!("{e}: {report}"));
    assert_eq!(v["abandoned"], 0);
    assert!(v["requests"].as_u64().unwrap() >= 3);
    // Gone: a new client finds no daemon.
    let e = Client::connect(ClientOptions { prefix: d.prefix.clone(), ..ClientOptions::default() })
        .err()
        .expect("no daemon");
    assert_eq!(e.code, StatusCode::Unavailable, "{e}");
}

#[test]
fn polling_mode_serves_spinning_and_event_clients() {
    let d = Daemon::start("poll", "waiting = \"poll\"\nworkers = 1");
    let f = fixture();
    for wait in [WaitMode::Auto, WaitMode::Event] {
        let mut c = Client::connect(ClientOptions { wait, ..d.options() }).unwrap();
        assert_eq!(c.health().unwrap().waiting, "poll");
        assert_same_registration(&c.register("mug", &f.views[1].1, TIMEOUT).unwrap(), &f.views[1].2);
    }
}

/// A daemon configured with another hand and its demonstration (here the
/// bundled hand under other names) solves Grasp for that hand: the CLI's
/// grasp of the bundled hand on the same view, its joints under the
/// configured names. A configured demonstration that is not there, or was
/// made with another hand, stops the start with the reason.
#[test]
fn a_configured_hand_serves_grasp_under_its_own_names() {
    let f = fixture();
    let dir = tempfile::tempdir().unwrap();
    let assets = Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets");
    let renamed = graspd::hand::renamed::write(dir.path()).unwrap();
    let (urdf, keypoints) = (renamed.urdf.to_str().unwrap(), renamed.keypoints.to_str().unwrap());
    let demo = renamed.mug_demo.to_str().unwrap();
    let hand = format!("hand_urdf = \"{urdf}\"\nhand_keypoints = \"{keypoints}\"\n");
    let d = Daemon::start("hand", &format!("{hand}[demos]\nmug = \"{demo}\""));
    let h = d.client().health().unwrap();
    assert_eq!(h.hand_name.as_deref(), Some(graspd::hand::renamed::ROBOT), "Health names the configured hand");
    let g = d.client().grasp("mug", &f.views[0].1, TIMEOUT).unwrap();
    let expected = &f.grasp["grasp"];
    assert_eq!(g.grasp.wrist_pose.translation.to_vec(), floats(&expected["wrist_pose"]["translation"]));
    let names: Vec<&str> = g.grasp.actuated.iter().map(|(n, _)| n.as_str()).collect();
    assert!(names.contains(&"palm_to_index_base") && !names.contains(&"palm_to_if_proximal"), "{names:?}");
    for (name, q) in &g.grasp.actuated {
        let bundled = if name == "palm_to_index_base" { "palm_to_if_proximal" } else { name.as_str() };
        assert_eq!(*q, expected["actuated"][bundled].as_f64().unwrap(), "{name}");
    }
    drop(d);
    for (demo, needle) in [
        (dir.path().join("missing.json").to_str().unwrap().to_owned(), "missing.json"),
        (assets.join("demos/mug.json").to_str().unwrap().to_owned(), "made with hand `sih_right`"),
    ] {
        let cfg = dir.path().join("bad.toml");
        let text = format!(
            "service_prefix = \"{}\"\ncategories = [\"mug\"]\n{hand}[demos]\nmug = \"{demo}\"\n",
            unique_prefix("badhand")
        );
        std::fs::write(&cfg, text).unwrap();
        let out = Command::new(GRASPD)
            .args(["serve", "--config", cfg.to_str().unwrap()])
            .env("GRASPD_LOG", "warn")
            .output()
            .unwrap();
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{err}");
    }
}

/// Event-driven waiting with a long linger: after each answer the worker
/// keeps receiving while the leader sleeps, so back-to-back calls from two
/// clients are received by either thread. Every call is answered once, and
/// right.
#[test]
fn lingering_workers_answer_back_to_back_calls_once_and_right() {
    let d = Daemon::start("linger", "waiting = \"event\"\nlinger_us = 100000\nworkers = 1");
    let threads: Vec<_> = (0..2)
        .map(|t| {
            let opts = ClientOptions { wait: WaitMode::Spin, ..d.options() };
            std::thread::spawn(move || {
                let f = fixture();
                let mut c = Client::connect(opts).unwrap();
                for i in 0..3 {
                    let (_, points, expected) = &f.views[(t + i) % f.views.len()];
                    assert_same_registration(&c.register("mug", points, TIMEOUT).unwrap(), expected);
                    assert!(c.health().unwrap().serving);
                }
            })
        })
        .collect();
    for t in threads {
        t.join().expect("client thread");
    }
    let s = d.client().stats().unwrap();
    let reg = &s.methods[proto::Method::Register as usize];
    assert_eq!((reg.requests, reg.by_status[0]), (6, 6));
}

/// The Python SDK (client/python), written from proto/README.md alone,
/// against a daemon: its pytest suite compares its answers with the CLI's
/// (the same engine: bit for bit) and checks the status of bad inputs.
/// Its environment comes from scripts/python-sdk.sh (the README's test
/// command runs it first); without it this test fails, naming the script.
#[test]
fn the_python_sdk_answers_as_the_cli() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let python = root.join("client/python/.venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run scripts/python-sdk.sh (the README's test command does)",
        python.display()
    );
    let d = Daemon::start("python", "");
    let f = fixture();
    let (path, points, expected) = &f.views[0];
    let _ = path;
    let fixture_file = d.dir.path().join("sdk_fixture.json");
    let v = serde_json::json!({
        "prefix": d.prefix,
        "points": points,
        "register": expected,
        "grasp": f.grasp,
        "on_table": f.on_table,
        "hand": f.hand,
        "two_cameras": f.two_cameras,
        "cameras": [FIRST_CAMERA, SECOND_CAMERA],
    });
    std::fs::write(&fixture_file, serde_json::to_vec(&v).unwrap()).unwrap();
    let out = Command::new(&python)
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider", "client/python/tests"])
        .current_dir(&root)
        .env("GRASPD_SDK_FIXTURE", &fixture_file)
        .output()
        .expect("the SDK's python runs");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the Python SDK's tests failed:\n{text}");
    // Every test ran against the daemon: none skipped.
    assert!(text.contains("8 passed") && !text.contains("skipped"), "{text}");

    // A Python client started before its daemon waits for it (connect_timeout_s).
    let prefix = unique_prefix("python_wait");
    let script =
        "import sys, graspd_client as g\nc = g.Client(sys.argv[1], connect_timeout_s=60)\nprint(c.health()['serving'])";
    let waiter = Command::new(&python)
        .args(["-c", script, &prefix])
        .current_dir(&root)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the SDK's python runs");
    std::thread::sleep(Duration::from_millis(500));
    let late = Daemon::start_with_prefix(&prefix, "", &[]);
    let out = waiter.wait_with_output().unwrap();
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "True",
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );

    // A daemon killed with a request pending: the client waits for the next
    // one and resends, and gets the same answer.
    let script = "import sys, json, numpy as np, graspd_client as g\n\
                  f = json.load(open(sys.argv[2]))\n\
                  c = g.Client(sys.argv[1], timeout_s=60)\n\
                  print('connected', flush=True)\n\
                  sys.stdin.readline()\n\
                  r = c.register('mug', np.array(f['points'], dtype=np.float32), timeout_s=60)\n\
                  print(json.dumps(r['latent']))";
    let mut child = Command::new(&python)
        .args(["-c", script, &prefix, fixture_file.to_str().unwrap()])
        .current_dir(&root)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the SDK's python runs");
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    assert_eq!(lines.next().and_then(Result::ok).as_deref(), Some("connected"));
    late.signal("STOP");
    use std::io::Write;
    child.stdin.take().unwrap().write_all(b"go\n").unwrap();
    std::thread::sleep(Duration::from_millis(400));
    late.signal("KILL");
    let _next = Daemon::start_with_prefix(&prefix, "", &[]);
    let answer = lines.next().and_then(Result::ok).unwrap_or_default();
    let status = child.wait().unwrap();
    let mut err = String::new();
    let _ = std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err);
    let latent: Vec<f64> = serde_json::from_str(&answer)
        .unwrap_or_else(|e| panic!("no answer after the restart ({e}): {answer:?} {status:?} {err}"));
    assert_eq!(latent, floats(&expected["latent"]));
    assert!(status.success(), "{err}");
}

//! `graspctl`: the graspd daemon from the command line (health, categories,
//! stats, register, grasp, bench). Every command takes --json.

use clap::{Parser, Subcommand, ValueEnum};
use graspd_client::cloudfile::{read_cloud, synthetic_mug_view};
use graspd_client::protocol::{self as proto, Plain, Point, RequestHeader, ResponseHeader};
use graspd_client::{Client, ClientOptions, CloudOptions, Error, StatusCode, WaitMode};
use std::io::{Read, Write};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

#[derive(Parser)]
#[command(name = "graspctl", version, about = "Client of the graspd daemon")]
struct Cli {
    /// The daemon's service prefix.
    #[arg(long, global = true, default_value = proto::DEFAULT_PREFIX)]
    prefix: String,
    /// How to wait for responses.
    #[arg(long, global = true, value_enum, default_value_t = Wait::Auto)]
    wait: Wait,
    /// Wait this long for a daemon to appear, milliseconds.
    #[arg(long, global = true, default_value_t = 0)]
    connect_timeout_ms: u64,
    /// Deadline of each request, milliseconds.
    #[arg(long, global = true, default_value_t = 10_000)]
    timeout_ms: u64,
    /// Machine-readable output.
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum Wait {
    /// Spin when the daemon polls, sleep on events otherwise.
    Auto,
    Spin,
    Event,
}

#[derive(Subcommand)]
enum Command {
    /// Is the daemon serving? (version, mode, limits, uptime)
    Health,
    /// The categories the daemon serves, their keypoints and canonical frames.
    Categories,
    /// Per-method counts, statuses and latency percentiles.
    Stats,
    /// Registers a cloud: latent shape, pose, fit, keypoints (cloud frame).
    Register(CloudArgs),
    /// Registration, grasp and pre-grasp in one round trip.
    Grasp(CloudArgs),
    /// Round-trip latency of Register over shared memory, and over a Unix socket as a baseline.
    Bench(BenchArgs),
    /// Many clients calling in a loop; reports errors and whether the daemon's memory stays flat.
    Soak(SoakArgs),
}

#[derive(clap::Args)]
struct SoakArgs {
    #[arg(long, default_value_t = 8)]
    clients: usize,
    #[arg(long, default_value_t = 300)]
    seconds: u64,
    #[arg(long, default_value_t = 20_000)]
    points: usize,
    /// Send this cloud (all its points) instead of a synthetic one of --points.
    #[arg(long)]
    cloud: Option<PathBuf>,
    /// grasp (when the daemon serves it) or register.
    #[arg(long, default_value = "register")]
    method: String,
    #[arg(long, default_value = "mug")]
    category: String,
    /// Seconds between samples of the daemon's RSS and of /dev/shm.
    #[arg(long, default_value_t = 10)]
    every: u64,
}

#[derive(clap::Args)]
struct CloudArgs {
    #[arg(long)]
    category: String,
    /// Segmented partial cloud of one tool (.xyz/.csv, .npy, .ply), metres.
    #[arg(long)]
    cloud: PathBuf,
    /// Name of the cloud's frame (echoed in the result).
    #[arg(long, default_value = "world")]
    frame: String,
    /// World up in the cloud's frame, "x,y,z", or "none" when unknown.
    #[arg(long, default_value = "0,0,1")]
    up: String,
    /// The camera's origin in the cloud's frame, "x,y,z" ("0,0,0" for a cloud in the camera frame).
    #[arg(long)]
    viewpoint: Option<String>,
    /// With --viewpoint, a second camera's origin, "x,y,z", when the cloud
    /// merges two cameras' views (a second look at the tool).
    #[arg(long, requires = "viewpoint")]
    second_viewpoint: Option<String>,
    /// Table top height z in the cloud's frame, the tool resting on it: the
    /// registration holds its lowest point there (Register and Grasp, z-up
    /// clouds). Grasp's default: a table from the cloud when z is up.
    #[arg(long, allow_hyphen_values = true)]
    table_z: Option<f32>,
    /// Grasp: no table plane.
    #[arg(long)]
    no_table: bool,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum BenchMethod {
    /// Register a cloud of --points points (and the same over --uds).
    Register,
    /// Health: an empty request, the transport alone.
    Health,
    /// Grasp a cloud of --points points: registration, grasp and pre-grasp
    /// in one round trip (no Unix-socket baseline).
    Grasp,
}

#[derive(clap::Args)]
struct BenchArgs {
    #[arg(long, value_enum, default_value_t = BenchMethod::Register)]
    method: BenchMethod,
    /// Points per request (a synthetic mug-sized partial view unless --cloud).
    #[arg(long, default_value_t = 20_000)]
    points: usize,
    /// Measured requests per transport.
    #[arg(long, default_value_t = 200)]
    requests: usize,
    /// Unmeasured requests first.
    #[arg(long, default_value_t = 20)]
    warmup: usize,
    #[arg(long, default_value = "mug")]
    category: String,
    /// Use this cloud (resampled to --points) instead of the synthetic one.
    #[arg(long)]
    cloud: Option<PathBuf>,
    /// The daemon's `uds_baseline` socket: measure the same requests over it too.
    #[arg(long)]
    uds: Option<PathBuf>,
}

/// "x,y,z" given to `flag`, or "none".
fn parse_up(flag: &str, s: &str) -> Result<Option<[f32; 3]>, String> {
    if s.eq_ignore_ascii_case("none") {
        return Ok(None);
    }
    let v: Vec<f32> = s
        .split(',')
        .map(|x| x.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{flag} {s:?}: {e}"))?;
    match v.as_slice() {
        [x, y, z] => Ok(Some([*x, *y, *z])),
        _ => Err(format!("{flag} {s:?}: expected x,y,z or none")),
    }
}

fn print(json: bool, v: &serde_json::Value, human: impl FnOnce()) {
    if json {
        println!("{}", serde_json::to_string_pretty(v).unwrap_or_default());
    } else {
        human();
    }
}

fn main() -> ExitCode {
    // `... | head` must end quietly, not panic in println!: restore the
    // default SIGPIPE disposition that Rust's runtime replaces.
    // SAFETY: called first thing in main, before any thread exists.
    #[cfg(unix)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    match run(&cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            if cli.json {
                let (code, value) = match &e {
                    Failure::Status(s) => (s.code.name(), s.code as u32),
                    Failure::Other(_) => ("CLIENT_ERROR", u32::MAX),
                };
                println!(
                    "{}",
                    serde_json::json!({"error": {"code": code, "code_value": value, "message": e.message()}})
                );
            } else {
                eprintln!("error: {}", e.message_with_code());
            }
            ExitCode::from(1)
        }
    }
}

enum Failure {
    Status(Error),
    Other(String),
}

impl Failure {
    fn message(&self) -> String {
        match self {
            Failure::Status(e) => e.message.clone(),
            Failure::Other(m) => m.clone(),
        }
    }
    fn message_with_code(&self) -> String {
        match self {
            Failure::Status(e) => e.to_string(),
            Failure::Other(m) => m.clone(),
        }
    }
}

impl From<Error> for Failure {
    fn from(e: Error) -> Self {
        Failure::Status(e)
    }
}
impl From<String> for Failure {
    fn from(e: String) -> Self {
        Failure::Other(e)
    }
}
impl From<&str> for Failure {
    fn from(e: &str) -> Self {
        Failure::Other(e.to_owned())
    }
}

fn run(cli: &Cli) -> Result<(), Failure> {
    let opts = ClientOptions {
        prefix: cli.prefix.clone(),
        wait: match cli.wait {
            Wait::Auto => WaitMode::Auto,
            Wait::Spin => WaitMode::Spin,
            Wait::Event => WaitMode::Event,
        },
        connect_timeout: Duration::from_millis(cli.connect_timeout_ms),
        default_timeout: Duration::from_millis(cli.timeout_ms),
        ..ClientOptions::default()
    };
    let timeout = Duration::from_millis(cli.timeout_ms);
    match &cli.command {
        Command::Health => {
            let mut c = Client::connect(opts)?;
            let h = c.health()?;
            print(cli.json, &serde_json::json!(h), || {
                println!(
                    "{} (pid {}, graspd {}, protocol {}, {} waiting, {} workers), up {:.1} s, started in {:.0} ms, {} categories, max {} points, grasp {}",
                    if h.serving { "SERVING" } else { "DRAINING" },
                    h.pid, h.server_version, h.protocol_version, h.waiting, h.workers, h.uptime_s, h.startup_ms, h.categories, h.max_points,
                    match (&h.hand_name, h.grasp_available) {
                        (Some(hand), true) => format!("available ({hand}, {} actuated joints)", h.hand_actuated_joints),
                        (Some(hand), false) => format!("not available ({hand} loaded, no demonstration)"),
                        (None, _) => "not available (no hand)".to_owned(),
                    }
                )
            });
        }
        Command::Categories => {
            let mut c = Client::connect(opts)?;
            let cats = c.categories()?;
            print(cli.json, &serde_json::json!({"categories": cats}), || {
                for k in &cats {
                    println!(
                        "{}: latent {}, keypoints {}, grasp {}",
                        k.name,
                        k.latent_dim,
                        k.keypoints.join(", "),
                        if k.grasp_available { "served" } else { "not served" }
                    );
                }
            });
        }
        Command::Stats => {
            let mut c = Client::connect(opts)?;
            let s = c.stats()?;
            let v = proto::json::stats_json(&s);
            print(cli.json, &v, || {
                println!(
                    "up {:.1} s, RSS {:.1} MiB, {} clients, {} queued",
                    s.uptime_ns as f64 * 1e-9,
                    s.rss_bytes as f64 / 1048576.0,
                    s.clients_connected,
                    s.queued
                );
                for m in &s.methods[..s.method_count as usize] {
                    println!(
                        "  {:<16} {:>8} requests, {:>6} errors, p50 {:>9.1} µs, p99 {:>9.1} µs, max {:>9.1} µs",
                        proto::text_lossy(&m.name),
                        m.requests,
                        m.requests - m.by_status[0],
                        m.latency_p50_us,
                        m.latency_p99_us,
                        m.latency_max_us
                    );
                }
            });
        }
        Command::Register(a) | Command::Grasp(a) => {
            let cloud = read_cloud(&a.cloud).map_err(|e| e.to_string())?;
            let viewpoint = match &a.viewpoint {
                Some(v) => Some(parse_up("--viewpoint", v)?.ok_or("--viewpoint needs three numbers")?),
                None => None,
            };
            let second_viewpoint = match &a.second_viewpoint {
                Some(v) => Some(parse_up("--second-viewpoint", v)?.ok_or("--second-viewpoint needs three numbers")?),
                None => None,
            };
            let table = match (a.no_table, a.table_z) {
                (true, _) => Some(graspd_client::Table::None),
                (false, Some(z)) => Some(graspd_client::Table::At(z)),
                (false, None) => None,
            };
            let co = CloudOptions {
                cloud_frame: a.frame.clone(),
                up: parse_up("--up", &a.up)?,
                viewpoint,
                second_viewpoint,
                seed: a.seed,
                table,
                ..CloudOptions::default()
            };
            let mut c = Client::connect(opts)?;
            let is_grasp = matches!(cli.command, Command::Grasp(_));
            // The same JSON fields as `graspd register` / `graspd grasp` (what the daemon sends).
            let mut v = if is_grasp {
                grasp_cli_json(&a.category, cloud.len(), &c.grasp_with(&a.category, &cloud, &co, timeout)?, co.up)
            } else {
                let mut v = registration_cli_json(&c.register_with(&a.category, &cloud, &co, timeout)?, co.up);
                v["category"] = serde_json::json!(a.category);
                v["points"] = serde_json::json!(cloud.len());
                v
            };
            let t = c.last_call();
            v["timing_us"] = serde_json::json!({"rtt": t.rtt_ns as f64 * 1e-3, "server": t.server_ns as f64 * 1e-3, "compute": t.compute_ns as f64 * 1e-3});
            print(cli.json, &v, || {
                let r = if is_grasp { &v["registration"] } else { &v };
                println!(
                    "{}: scale {:.3}, inliers {:.1}%, residual {:.2} mm, {}{} (round trip {:.1} ms)",
                    a.category,
                    r["scale"].as_f64().unwrap_or(f64::NAN),
                    100.0 * r["fit"]["inlier_fraction"].as_f64().unwrap_or(f64::NAN),
                    r["fit"]["residual_mm"].as_f64().unwrap_or(f64::NAN),
                    if r["fit"]["confident"].as_bool() == Some(true) { "confident" } else { "POOR FIT" },
                    if r["fit"]["ambiguous_pose"].as_bool() == Some(true) { ", AMBIGUOUS POSE" } else { "" },
                    t.rtt_ns as f64 * 1e-6
                );
                let half_width = r["yaw_arc"]["half_width_rad"].as_f64().unwrap_or(0.0);
                if half_width > 0.0 {
                    println!(
                        "  the view leaves the turn about the tool's axis open by ±{:.0}°: spread per keypoint below",
                        half_width.to_degrees()
                    );
                }
                for (i, k) in r["keypoints"].as_array().into_iter().flatten().enumerate() {
                    let s = r["yaw_arc"]["keypoint_spread_m"][i].as_f64().filter(|s| *s > 0.0);
                    let s = s.map_or(String::new(), |s| format!("  ±{:.0} mm", s * 1e3));
                    println!("  {:<16} {}{s}", k["name"].as_str().unwrap_or(""), k["position"]);
                }
                if is_grasp {
                    println!(
                        "grasp wrist {}, task-space distance {:.3} cm",
                        v["grasp"]["wrist_pose"],
                        v["task_space_distance_cm"].as_f64().unwrap_or(f64::NAN)
                    );
                    for w in v["warnings"].as_array().into_iter().flatten() {
                        println!("warning: {}", w.as_str().unwrap_or(""));
                    }
                }
            });
        }
        Command::Bench(b) => bench(cli, b, opts)?,
        Command::Soak(a) => soak(cli, a, opts)?,
    }
    Ok(())
}

/// Nearest-rank percentile of unsorted values, microseconds from nanoseconds.
fn pct_us(v: &[u64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_unstable();
    let rank = ((q * s.len() as f64).ceil() as usize).clamp(1, s.len());
    s[rank - 1] as f64 * 1e-3
}

#[derive(Default)]
struct Samples {
    rtt: Vec<u64>,
    rtt_excl_fill: Vec<u64>,
    server: Vec<u64>,
    compute: Vec<u64>,
    overhead: Vec<u64>,
    overhead_excl_fill: Vec<u64>,
    /// Round trip (without the fill) minus the daemon's receipt-to-answer time: the two legs.
    legs: Vec<u64>,
    /// The daemon's receipt-to-answer time minus engine time: its own handling.
    server_handling: Vec<u64>,
}

impl Samples {
    fn push(&mut self, rtt: u64, fill: u64, server: u64, compute: u64) {
        self.rtt.push(rtt + fill);
        self.rtt_excl_fill.push(rtt);
        self.server.push(server);
        self.compute.push(compute);
        self.overhead.push((rtt + fill).saturating_sub(compute));
        self.overhead_excl_fill.push(rtt.saturating_sub(compute));
        self.legs.push(rtt.saturating_sub(server));
        self.server_handling.push(server.saturating_sub(compute));
    }
}

fn bench(cli: &Cli, b: &BenchArgs, opts: ClientOptions) -> Result<(), Failure> {
    if b.points == 0 || b.requests == 0 {
        return Err("--points and --requests must be positive".to_string().into());
    }
    let cloud: Vec<[f32; 3]> = match &b.cloud {
        Some(p) => {
            let c = read_cloud(p).map_err(|e| e.to_string())?;
            if c.is_empty() {
                return Err(format!("{}: empty cloud", p.display()).into());
            }
            (0..b.points).map(|i| c[i * c.len() / b.points]).collect()
        }
        None => synthetic_mug_view(b.points),
    };
    let mut c = Client::connect(ClientOptions { initial_max_points: b.points, ..opts })?;
    let health = c.health()?;
    let timeout = Duration::from_millis(cli.timeout_ms);
    let co = CloudOptions::default();
    for _ in 0..b.warmup {
        match b.method {
            BenchMethod::Register => drop(c.register_with(&b.category, &cloud, &co, timeout)?),
            BenchMethod::Health => drop(c.health()?),
            BenchMethod::Grasp => drop(c.grasp_with(&b.category, &cloud, &co, timeout)?),
        }
    }
    let mut shm = Samples::default();
    for _ in 0..b.requests {
        match b.method {
            BenchMethod::Register => drop(c.register_with(&b.category, &cloud, &co, timeout)?),
            BenchMethod::Health => drop(c.health()?),
            BenchMethod::Grasp => drop(c.grasp_with(&b.category, &cloud, &co, timeout)?),
        }
        let t = c.last_call();
        shm.push(t.rtt_ns, t.fill_ns, t.server_ns, t.compute_ns);
    }
    let baseline = match (&b.uds, b.method) {
        (Some(path), BenchMethod::Register) => Some(bench_uds(path, b, &cloud)?),
        _ => None,
    };
    let client_wait = match (c.options().wait, health.waiting) {
        (WaitMode::Spin, _) | (WaitMode::Auto, "poll") => "spin",
        _ => "event",
    };
    let summary = |s: &Samples| {
        serde_json::json!({
            "rtt_us": {"p50": pct_us(&s.rtt, 0.5), "p99": pct_us(&s.rtt, 0.99), "max": pct_us(&s.rtt, 1.0)},
            "server_us": {"p50": pct_us(&s.compute, 0.5), "total_p50": pct_us(&s.server, 0.5)},
            "transport_overhead_us": {"p50": pct_us(&s.overhead, 0.5), "p99": pct_us(&s.overhead, 0.99)},
        })
    };
    let mut v = summary(&shm);
    v["rtt_excl_fill_us"] = serde_json::json!({"p50": pct_us(&shm.rtt_excl_fill, 0.5), "p99": pct_us(&shm.rtt_excl_fill, 0.99), "max": pct_us(&shm.rtt_excl_fill, 1.0)});
    v["transport_overhead_excl_fill_us"] =
        serde_json::json!({"p50": pct_us(&shm.overhead_excl_fill, 0.5), "p99": pct_us(&shm.overhead_excl_fill, 0.99)});
    // Where the overhead lies: in the two legs between the processes, or in the daemon around the engine.
    v["overhead_split_us"] = serde_json::json!({
        "legs_p50": pct_us(&shm.legs, 0.5), "legs_p99": pct_us(&shm.legs, 0.99),
        "daemon_handling_p50": pct_us(&shm.server_handling, 0.5), "daemon_handling_p99": pct_us(&shm.server_handling, 0.99),
    });
    v["method"] = serde_json::json!(match b.method {
        BenchMethod::Register => "register",
        BenchMethod::Health => "health",
        BenchMethod::Grasp => "grasp",
    });
    v["points"] = serde_json::json!(if b.method == BenchMethod::Health { 0 } else { b.points });
    v["requests"] = serde_json::json!(b.requests);
    v["category"] = serde_json::json!(b.category);
    v["daemon_waiting"] = serde_json::json!(health.waiting);
    v["client_wait"] = serde_json::json!(client_wait);
    v["baseline_uds"] = match &baseline {
        Some(s) => summary(s),
        None => serde_json::Value::Null,
    };
    if let Some(s) = &baseline {
        v["overhead_ratio_uds_over_shm"] = serde_json::json!({
            "p50": pct_us(&s.overhead, 0.5) / pct_us(&shm.overhead, 0.5),
            "p50_excl_fill": pct_us(&s.overhead, 0.5) / pct_us(&shm.overhead_excl_fill, 0.5),
        });
    }
    v["definitions"] = serde_json::json!({
        "rtt_us": "client call: cloud written into shared memory (uds: serialised into a buffer), sent, response in hand",
        "rtt_excl_fill_us": "shared memory only: from send to response (the client produced the cloud in shared memory)",
        "server_us": "p50: engine time in the daemon (ResponseHeader::compute_ns); total_p50: receipt to answer (server_ns)",
        "transport_overhead_us": "per request rtt minus engine time, then percentiles",
        "overhead_split_us": "legs: rtt (without the fill) minus the daemon's receipt-to-answer time; daemon_handling: that time minus engine time",
    });
    print(cli.json, &v, || {
        let what = match b.method {
            BenchMethod::Register => format!("register, {} points", b.points),
            BenchMethod::Health => "health".to_owned(),
            BenchMethod::Grasp => format!("grasp, {} points", b.points),
        };
        println!(
            "{what}, {} requests, daemon {} / client {}: rtt p50 {:.1} µs p99 {:.1} µs, engine p50 {:.1} µs, overhead p50 {:.1} µs p99 {:.1} µs (excluding the cloud copy: p50 {:.1} µs)",
            b.requests, health.waiting, client_wait,
            pct_us(&shm.rtt, 0.5), pct_us(&shm.rtt, 0.99), pct_us(&shm.compute, 0.5),
            pct_us(&shm.overhead, 0.5), pct_us(&shm.overhead, 0.99), pct_us(&shm.overhead_excl_fill, 0.5)
        );
        if let Some(s) = &baseline {
            println!(
                "UDS baseline: rtt p50 {:.1} µs, overhead p50 {:.1} µs p99 {:.1} µs ({:.1}× the shared-memory overhead)",
                pct_us(&s.rtt, 0.5), pct_us(&s.overhead, 0.5), pct_us(&s.overhead, 0.99), pct_us(&s.overhead, 0.5) / pct_us(&shm.overhead, 0.5)
            );
        }
    });
    Ok(())
}

/// The same Register requests over the daemon's Unix-socket baseline endpoint:
/// header and points serialised into a buffer, written, response read back.
fn bench_uds(path: &std::path::Path, b: &BenchArgs, cloud: &[[f32; 3]]) -> Result<Samples, Failure> {
    let mut s = std::os::unix::net::UnixStream::connect(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut out = Samples::default();
    let mut buf: Vec<u8> = Vec::new();
    let mut resp = vec![0u8; std::mem::size_of::<ResponseHeader>() + std::mem::size_of::<proto::RegisterResponse>()];
    for i in 0..(b.warmup + b.requests) {
        let t0 = Instant::now();
        let mut h = RequestHeader::zeroed();
        h.request_id = i as u64 + 1;
        h.protocol_version = proto::PROTOCOL_VERSION;
        h.category = proto::str_to_text(&b.category);
        h.cloud_frame = proto::str_to_text("world");
        h.up_in_cloud = [0.0, 0.0, 1.0];
        buf.clear();
        buf.extend_from_slice(h.as_bytes());
        buf.extend_from_slice(&(cloud.len() as u32).to_le_bytes());
        for p in Point::from_arrays(cloud) {
            for v in p.0 {
                buf.extend_from_slice(&v.to_le_bytes());
            }
        }
        s.write_all(&buf).map_err(|e| format!("uds write: {e}"))?;
        s.read_exact(&mut resp).map_err(|e| format!("uds read: {e}"))?;
        let hdr =
            ResponseHeader::from_bytes(&resp[..std::mem::size_of::<ResponseHeader>()]).ok_or("uds: short response")?;
        let _body = proto::RegisterResponse::from_bytes(&resp[std::mem::size_of::<ResponseHeader>()..])
            .ok_or("uds: short response")?;
        let rtt = t0.elapsed().as_nanos() as u64;
        if hdr.status != 0 {
            return Err(Error::new(StatusCode::from_u32(hdr.status), proto::text_lossy(&hdr.message)).into());
        }
        if i >= b.warmup {
            out.push(rtt, 0, hdr.server_ns, hdr.compute_ns);
        }
    }
    Ok(out)
}

/// Bytes of iceoryx2 objects in /dev/shm, and their count.
fn shm_usage() -> (u64, usize) {
    let Ok(dir) = std::fs::read_dir("/dev/shm") else { return (0, 0) };
    dir.flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("iox2_"))
        .filter_map(|e| e.metadata().ok())
        .fold((0, 0), |(b, n), m| (b + m.len(), n + 1))
}

fn soak(cli: &Cli, a: &SoakArgs, opts: ClientOptions) -> Result<(), Failure> {
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    use std::sync::Arc;
    let grasp = match a.method.as_str() {
        "grasp" => true,
        "register" => false,
        m => return Err(format!("--method {m}: grasp or register").into()),
    };
    let cloud = Arc::new(match &a.cloud {
        Some(p) => read_cloud(p).map_err(|e| e.to_string())?,
        None => synthetic_mug_view(a.points),
    });
    let stop = Arc::new(AtomicBool::new(false));
    let (ok, errors) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let first_error = Arc::new(std::sync::Mutex::new(None::<String>));
    let mut monitor = Client::connect(opts.clone())?;
    let timeout = Duration::from_millis(cli.timeout_ms);
    let threads: Vec<_> = (0..a.clients)
        .map(|_| {
            let (opts, cloud, stop, ok, errors, first_error, category) = (
                opts.clone(),
                cloud.clone(),
                stop.clone(),
                ok.clone(),
                errors.clone(),
                first_error.clone(),
                a.category.clone(),
            );
            std::thread::spawn(move || {
                let mut c = match Client::connect(ClientOptions { initial_max_points: cloud.len(), ..opts }) {
                    Ok(c) => c,
                    Err(e) => {
                        errors.fetch_add(1, Ordering::Relaxed);
                        first_error.lock().unwrap().get_or_insert(e.to_string());
                        return;
                    }
                };
                while !stop.load(Ordering::Relaxed) {
                    let r = if grasp {
                        c.grasp(&category, &cloud, timeout).map(|_| ())
                    } else {
                        c.register(&category, &cloud, timeout).map(|_| ())
                    };
                    match r {
                        Ok(()) => ok.fetch_add(1, Ordering::Relaxed),
                        Err(e) => {
                            first_error.lock().unwrap().get_or_insert(e.to_string());
                            errors.fetch_add(1, Ordering::Relaxed)
                        }
                    };
                }
            })
        })
        .collect();
    let t0 = Instant::now();
    let mut samples = Vec::new();
    let sample = |monitor: &mut Client, t: f64| -> Result<serde_json::Value, Failure> {
        let s = monitor.stats()?;
        let (shm_bytes, shm_objects) = shm_usage();
        Ok(serde_json::json!({"t_s": t, "rss_bytes": s.rss_bytes, "shm_bytes": shm_bytes, "shm_objects": shm_objects,
            "ok": ok.load(Ordering::Relaxed), "errors": errors.load(Ordering::Relaxed), "clients_connected": s.clients_connected}))
    };
    while t0.elapsed() < Duration::from_secs(a.seconds) {
        std::thread::sleep(
            Duration::from_secs(a.every.max(1)).min(Duration::from_secs(a.seconds).saturating_sub(t0.elapsed())),
        );
        let v = sample(&mut monitor, t0.elapsed().as_secs_f64())?;
        if !cli.json {
            println!("{v}");
        }
        samples.push(v);
    }
    stop.store(true, Ordering::Relaxed);
    for t in threads {
        let _ = t.join();
    }
    let after = sample(&mut monitor, t0.elapsed().as_secs_f64())?;
    // Flatness: the last sample against the first one (after warm-up).
    let get = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap_or(0.0);
    let (first, last) =
        (samples.first().cloned().unwrap_or(after.clone()), samples.last().cloned().unwrap_or(after.clone()));
    let v = serde_json::json!({
        "clients": a.clients, "seconds": a.seconds, "points": cloud.len(), "method": a.method,
        "requests_ok": ok.load(Ordering::Relaxed), "errors": errors.load(Ordering::Relaxed),
        "first_error": first_error.lock().unwrap().clone(),
        "rss_bytes": {"first": get(&first, "rss_bytes"), "last": get(&last, "rss_bytes"), "max": samples.iter().map(|s| get(s, "rss_bytes")).fold(0.0, f64::max)},
        "shm_bytes": {"first": get(&first, "shm_bytes"), "last": get(&last, "shm_bytes"), "after_clients_left": get(&after, "shm_bytes")},
        "shm_objects": {"first": get(&first, "shm_objects"), "last": get(&last, "shm_objects"), "after_clients_left": get(&after, "shm_objects")},
        "samples": samples,
    });
    print(cli.json, &v, || println!("{}", serde_json::to_string_pretty(&v).unwrap_or_default()));
    if errors.load(Ordering::Relaxed) > 0 {
        return Err(format!("{} errors during the soak", errors.load(Ordering::Relaxed)).into());
    }
    Ok(())
}

/// A registration in `graspd register`'s JSON fields and units (fit in mm).
/// `up`: the request's up direction (the yaw arc's axis is found from it).
fn registration_cli_json(r: &graspd_client::Registration, up: Option<[f32; 3]>) -> serde_json::Value {
    let yaw_arc = up.and_then(|u| r.yaw_arc(u.map(f64::from)));
    serde_json::json!({
        "latent": r.latent,
        "pose": r.pose,
        "scale": r.scale,
        "sigma2": r.sigma2_m2,
        "fit": {
            "inlier_fraction": r.fit.inlier_fraction,
            "residual_mm": r.fit.residual_m * 1e3,
            "inlier_mm": r.fit.inlier_threshold_m * 1e3,
            "confident": r.fit.confident,
            "ambiguous_pose": r.fit.ambiguous_pose,
            "stray_fraction": if r.points > 0 { f64::from(r.fit.stray_points) / f64::from(r.points) } else { 0.0 },
            "stray_points": r.fit.stray_points,
            "table_points": r.fit.table_points,
            "coverage": r.fit.coverage,
            "view_width_mm": r.fit.view_width_m * 1e3,
            "latent_mahalanobis": r.fit.latent_mahalanobis,
            "contradicted_fraction": r.fit.contradicted_fraction,
        },
        "keypoints": r.keypoints,
        "cloud_frame": r.cloud_frame,
        // As `graspd register`: the camera position assumed when none was given (null: none used).
        "estimated_viewpoint": r.viewpoint.estimated(),
        // As `graspd register`: the turns the view leaves open (null: not assessed).
        "yaw_arc": yaw_arc,
    })
}

fn hand_cli_json(h: &graspd_client::HandConfiguration) -> serde_json::Value {
    let map = |v: &[(String, f64)]| -> serde_json::Map<String, serde_json::Value> {
        v.iter().map(|(n, q)| (n.clone(), serde_json::json!(q))).collect()
    };
    serde_json::json!({
        "wrist_pose": {"translation": h.wrist_pose.translation, "rotation_xyzw": h.wrist_pose.rotation_xyzw},
        "joints": map(&h.joints),
        "actuated": map(&h.actuated),
    })
}

/// A grasp in `graspd grasp`'s JSON fields and units (what the daemon sends of it).
fn grasp_cli_json(category: &str, points: usize, g: &graspd_client::Grasp, up: Option<[f32; 3]>) -> serde_json::Value {
    let mut pregrasp = hand_cli_json(&g.pregrasp);
    pregrasp["collision_free"] = serde_json::json!(g.pregrasp_collision_free);
    pregrasp["min_clearance_mm"] = serde_json::json!(g.pregrasp_min_clearance_m * 1e3);
    serde_json::json!({
        "category": category,
        "points": points,
        "registration": registration_cli_json(&g.registration, up),
        "grasp": hand_cli_json(&g.grasp),
        "pregrasp": pregrasp,
        "task_space_distance_cm": g.task_space_distance_m * 1e2,
        "residual_mm": {"mean": g.residual_mean_m * 1e3, "max": g.residual_max_m * 1e3},
        "penetration_mm": g.penetration_m * 1e3,
        "table_z": g.table_z_m,
        "warnings": g.warnings,
    })
}

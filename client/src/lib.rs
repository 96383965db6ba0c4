//! graspd client SDK: a blocking Rust API over the daemon's iceoryx2 services
//! (the contract: crate `graspd-proto`, proto/README.md).
//!
//! ```no_run
//! use graspd_client::{Client, ClientOptions};
//! use std::time::Duration;
//! let mut client = Client::connect(ClientOptions::default())?;
//! let cloud: Vec<[f32; 3]> = vec![[0.0, 0.0, 0.0]; 1000]; // metres, cloud frame
//! let reg = client.register("mug", &cloud, Duration::from_secs(1))?;
//! println!("scale {}", reg.scale);
//! # Ok::<(), graspd_client::Error>(())
//! ```
//!
//! Every error carries a [`StatusCode`]: the daemon's (INVALID_ARGUMENT,
//! NOT_FOUND, ...) or the client's own (UNAVAILABLE when no daemon serves the
//! prefix, DEADLINE_EXCEEDED when the wait timed out, FAILED_PRECONDITION when
//! the daemon speaks another protocol version). A client survives daemon
//! restarts: when the daemon dies while a request waits, the client notices,
//! reopens the services once a daemon serves them again and resends (all
//! methods are idempotent), within the call's deadline.

use graspd_proto::{self as proto, Method, NoPayload, Point, RequestHeader, ResponseHeader};
use iceoryx2::pending_response::PendingResponse;
use iceoryx2::port::client::Client as IpcClient;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::{event as event_factory, request_response as rr_factory};
use serde::Serialize;
use std::fmt::Debug;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

pub mod cloudfile;

pub use graspd_proto as protocol;
pub use graspd_proto::StatusCode;

/// The thread-safe iceoryx2 IPC variant (a [`Client`] can move between threads).
pub type Ipc = ipc_threadsafe::Service;

type RrFactory<P, R> = rr_factory::PortFactory<Ipc, P, RequestHeader, R, ResponseHeader>;
type Port<P, R> = IpcClient<Ipc, P, RequestHeader, R, ResponseHeader>;
type Pending<P, R> = PendingResponse<Ipc, P, RequestHeader, R, ResponseHeader>;
type NotifyPorts = (Option<event_factory::PortFactory<Ipc>>, Option<Notifier<Ipc>>);
type SendFn<'a, P, R> = dyn FnMut(&Port<P, R>, RequestHeader) -> Result<Pending<P, R>, Error> + 'a;

/// A failed call: the status code and a message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Error {
    pub code: StatusCode,
    pub message: String,
    /// The transport lost the daemon (it died or restarted); the call may be resent.
    transport: bool,
}

impl Error {
    pub fn new(code: StatusCode, message: impl Into<String>) -> Self {
        Self { code, message: message.into(), transport: false }
    }
    fn lost(message: impl Into<String>) -> Self {
        Self { code: StatusCode::Unavailable, message: message.into(), transport: true }
    }
    pub fn code(&self) -> StatusCode {
        self.code
    }
}

impl std::fmt::Display for Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.code.name(), self.message)
    }
}

impl std::error::Error for Error {}

/// How the client waits for a response.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WaitMode {
    /// Spin when the daemon polls, sleep on the reply event otherwise.
    Auto,
    /// Spin on the pending response (lowest latency, a core busy while waiting).
    Spin,
    /// Sleep until the daemon notifies the client's reply event service.
    Event,
}

#[derive(Clone, Debug)]
pub struct ClientOptions {
    /// The daemon's `service_prefix`.
    pub prefix: String,
    pub wait: WaitMode,
    /// Clouds up to this many points fit the first shared-memory segment; larger
    /// ones grow it (power-of-two steps), which costs once.
    pub initial_max_points: usize,
    /// How long `connect` waits for a daemon to appear (zero: fail at once).
    pub connect_timeout: Duration,
    /// Resend a request when the daemon died or restarted while it was pending.
    pub resend_after_restart: bool,
    /// Deadline of calls without their own (health, categories, stats).
    pub default_timeout: Duration,
}

impl Default for ClientOptions {
    fn default() -> Self {
        Self {
            prefix: proto::DEFAULT_PREFIX.to_owned(),
            wait: WaitMode::Auto,
            initial_max_points: 32 * 1024,
            connect_timeout: Duration::ZERO,
            resend_after_restart: true,
            default_timeout: Duration::from_secs(5),
        }
    }
}

/// Timings of the last call, nanoseconds.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct CallTiming {
    /// Writing the request into shared memory (the cloud copy), before sending.
    pub fill_ns: u64,
    /// From send to the response in hand.
    pub rtt_ns: u64,
    /// The daemon's time from receipt to answer (ResponseHeader::server_ns).
    pub server_ns: u64,
    /// The engine's share of it (ResponseHeader::compute_ns).
    pub compute_ns: u64,
    /// How many times the request was sent (more than 1 after a daemon restart).
    pub attempts: u32,
}

#[derive(Clone, Debug, Serialize)]
pub struct Health {
    pub serving: bool,
    pub draining: bool,
    pub waiting: &'static str,
    pub pid: u32,
    pub protocol_version: u32,
    pub server_version: String,
    pub uptime_s: f64,
    pub startup_ms: f64,
    pub categories: u32,
    pub max_points: u32,
    pub max_in_flight_per_client: u32,
    pub workers: u32,
    /// Grasp serves at least one category (see [`CategoryInfo::grasp_available`]).
    pub grasp_available: bool,
    /// The hand Grasp solves for (its URDF robot name); None when no hand loaded.
    pub hand_name: Option<String>,
    /// Its actuated joints (0 when no hand loaded).
    pub hand_actuated_joints: u32,
}

#[derive(Clone, Debug, Serialize)]
pub struct CategoryInfo {
    pub name: String,
    pub latent_dim: u32,
    pub keypoints: Vec<String>,
    pub canonical_frame: String,
    /// Grasp serves this category (the hand and its demonstration loaded).
    pub grasp_available: bool,
}

#[derive(Clone, Debug, Serialize)]
pub struct NamedPoint {
    pub name: String,
    /// Cloud frame, metres.
    pub position: [f64; 3],
}

/// A pose: `p_target = R · p_source + t` (with the registration's scale on p_source where stated).
#[derive(Clone, Debug, Serialize)]
pub struct Pose {
    /// "`<target>_from_<source>`", e.g. "cloud_from_canonical".
    pub frame: String,
    pub translation: [f64; 3],
    pub rotation_xyzw: [f64; 4],
}

#[derive(Clone, Debug, Serialize)]
pub struct Fit {
    pub inlier_fraction: f64,
    pub residual_m: f64,
    pub inlier_threshold_m: f64,
    pub confident: bool,
    /// Another pose explains the view almost as well: the orientation is not determined by it.
    pub ambiguous_pose: bool,
    /// Points of the request set aside as stray before the fit (flying pixels,
    /// speckle, segmentation leaks); they count as outside in `inlier_fraction`.
    pub stray_points: u32,
    /// Of `stray_points`, those set aside as the table a leaking segmentation included.
    pub table_points: u32,
    /// Fraction of the completed shape's surface near a point of the cloud:
    /// how much of the tool the view shows (proto/README.md).
    pub coverage: f64,
    /// The view's width across its longest direction, metres.
    pub view_width_m: f64,
    /// How far the fitted latent lies outside the category's family (standard deviations).
    pub latent_mahalanobis: f64,
    /// Share of the fitted shape's camera-facing surface the view
    /// contradicts (something in front of the tool raises it); None when
    /// not assessed (no camera position, given or estimated).
    pub contradicted_fraction: Option<f64>,
    /// The turns about the tool's upright axis that explain the view about as
    /// well as the reported pose reach this far either way of it, radians; 0
    /// when the view settles the turn; None when not assessed (no up
    /// direction, or the pose is the race's runner-up: proto/README.md).
    /// See [`Registration::yaw_arc`].
    pub yaw_half_width_rad: Option<f64>,
}

/// The arc of turns a view leaves open, in the cloud's frame.
#[derive(Clone, Debug, Serialize)]
pub struct YawArc {
    /// The canonical axis nearest up (or up itself when none is within 10°):
    /// the arc turns about it through the canonical origin (`pose.translation`).
    pub axis_cloud: [f64; 3],
    pub half_width_rad: f64,
    /// How far each keypoint may lie from where it is reported (`keypoints`
    /// order), metres: 2·r·sin(h/2), r its distance from the axis.
    pub keypoint_spread_m: Vec<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Registration {
    pub category: String,
    pub cloud_frame: String,
    pub points: u32,
    pub latent: Vec<f64>,
    pub pose: Pose,
    pub scale: f64,
    pub sigma2_m2: f64,
    pub fit: Fit,
    pub keypoints: Vec<NamedPoint>,
    /// The camera position the fit used, in the cloud's frame, metres.
    pub viewpoint: Viewpoint,
}

impl Registration {
    /// The arc of turns the view leaves open about the tool's upright axis,
    /// for a request whose up direction (cloud frame) was `up`, with each
    /// keypoint's spread across it (proto/README.md, `yaw_half_width_rad`);
    /// None when the daemon did not assess it.
    pub fn yaw_arc(&self, up: [f64; 3]) -> Option<YawArc> {
        let h = self.fit.yaw_half_width_rad?;
        let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let n = norm(up);
        if !(n > 0.0 && n.is_finite()) {
            return None;
        }
        let up = [up[0] / n, up[1] / n, up[2] / n];
        // The rotation's columns (the canonical axes in the cloud's frame), each turned towards up.
        let [x, y, z, w] = self.pose.rotation_xyzw;
        let columns = [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + z * w), 2.0 * (x * z - y * w)],
            [2.0 * (x * y - z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + x * w)],
            [2.0 * (x * z + y * w), 2.0 * (y * z - x * w), 1.0 - 2.0 * (x * x + y * y)],
        ]
        .map(|c| if dot(c, up) < 0.0 { [-c[0], -c[1], -c[2]] } else { c });
        let nearest = columns.into_iter().max_by(|a, b| dot(*a, up).total_cmp(&dot(*b, up)))?;
        let axis = if dot(nearest, up) > 10f64.to_radians().cos() {
            let m = norm(nearest);
            [nearest[0] / m, nearest[1] / m, nearest[2] / m]
        } else {
            up
        };
        let pivot = self.pose.translation;
        let spread = self
            .keypoints
            .iter()
            .map(|k| {
                let d = [k.position[0] - pivot[0], k.position[1] - pivot[1], k.position[2] - pivot[2]];
                let along = dot(d, axis);
                let r = norm([d[0] - along * axis[0], d[1] - along * axis[1], d[2] - along * axis[2]]);
                2.0 * r * (h.min(std::f64::consts::PI) / 2.0).sin()
            })
            .collect();
        Some(YawArc { axis_cloud: axis, half_width_rad: h, keypoint_spread_m: spread })
    }
}

/// Where a registration's camera position came from.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(tag = "source", rename_all = "snake_case")]
pub enum Viewpoint {
    /// None given, and the view did not settle one.
    None,
    /// The request's (`CloudOptions::viewpoint`).
    Given { position: [f64; 3] },
    /// Estimated by the daemon from the view.
    Estimated { position: [f64; 3] },
}

impl Viewpoint {
    /// The estimated position, if the daemon estimated one.
    pub fn estimated(&self) -> Option<[f64; 3]> {
        match *self {
            Viewpoint::Estimated { position } => Some(position),
            _ => None,
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct HandConfiguration {
    /// "cloud_from_wrist".
    pub wrist_pose: Pose,
    /// Actuated joint name → rad (or m).
    pub actuated: Vec<(String, f64)>,
    /// Every moving joint name → rad (or m).
    pub joints: Vec<(String, f64)>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Grasp {
    pub registration: Registration,
    pub grasp: HandConfiguration,
    pub pregrasp: HandConfiguration,
    pub task_space_distance_m: f64,
    pub residual_mean_m: f64,
    pub residual_max_m: f64,
    pub penetration_m: f64,
    pub pregrasp_min_clearance_m: f64,
    pub pregrasp_collision_free: bool,
    pub table_z_m: Option<f64>,
    pub warnings: Vec<&'static str>,
}

/// Options of Register and Grasp beyond the cloud.
#[derive(Clone, Debug)]
pub struct CloudOptions {
    /// Name of the cloud's frame (echoed; result poses are in it).
    pub cloud_frame: String,
    /// World up in the cloud's frame; None = unknown. Default z up.
    pub up: Option<[f32; 3]>,
    /// The camera's origin in the cloud's frame, when known ([0, 0, 0] for a cloud in the camera frame).
    pub viewpoint: Option<[f32; 3]>,
    /// With `viewpoint`: a second camera's origin, when the cloud merges two
    /// cameras' views (a second look at the tool). Alone it is refused
    /// (INVALID_ARGUMENT).
    pub second_viewpoint: Option<[f32; 3]>,
    pub seed: u64,
    /// Grasp: table plane (None: AUTO). `At(z)` in a z-up frame is also the
    /// plane the tool rests on: Register and Grasp hold the registered
    /// shape's lowest point on it.
    pub table: Option<Table>,
    /// Grasp: pre-grasp back-off, m (None: daemon default).
    pub pregrasp_backoff_m: Option<f32>,
    /// Grasp: pre-grasp joint fraction in (0, 1] (None: daemon default).
    pub pregrasp_joint_fraction: Option<f32>,
}

#[derive(Clone, Copy, Debug)]
pub enum Table {
    None,
    /// z of the table top in the cloud's frame, m.
    At(f32),
}

impl Default for CloudOptions {
    fn default() -> Self {
        Self {
            cloud_frame: "world".into(),
            up: Some([0.0, 0.0, 1.0]),
            viewpoint: None,
            second_viewpoint: None,
            seed: 0,
            table: None,
            pregrasp_backoff_m: None,
            pregrasp_joint_fraction: None,
        }
    }
}

struct Endpoint<P: Debug + IceoryxSend + ?Sized + 'static, R: Debug + ZeroCopySend + 'static> {
    _service: RrFactory<P, R>,
    port: Port<P, R>,
    _event: Option<event_factory::PortFactory<Ipc>>,
    notifier: Option<Notifier<Ipc>>,
}

struct Connection {
    health: Endpoint<NoPayload, proto::HealthResponse>,
    categories: Endpoint<NoPayload, proto::CategoriesResponse>,
    register: Endpoint<[Point], proto::RegisterResponse>,
    grasp: Endpoint<[Point], proto::GraspResponse>,
    stats: Endpoint<NoPayload, proto::StatsResponse>,
    /// The daemon's node (its liveness is checked while waiting).
    daemon: Option<iceoryx2::identifiers::UniqueNodeId>,
    daemon_polls: bool,
    reply: Option<(event_factory::PortFactory<Ipc>, Listener<Ipc>)>,
}

/// A blocking client of one daemon (one prefix). Not shared between threads:
/// give each thread its own (they are cheap: a node, ten ports).
pub struct Client {
    opts: ClientOptions,
    node: Node<Ipc>,
    conn: Option<Connection>,
    next_id: u64,
    token: u64,
    last: CallTiming,
}

fn unix_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

fn ipc_error(what: &str, e: impl Debug) -> Error {
    Error::new(StatusCode::Internal, format!("{what}: {e:?}"))
}

macro_rules! open_rr {
    ($node:expr, $opts:expr, $method:expr, $req:ty, $resp:ty) => {{
        let name = $method.service_name(&$opts.prefix);
        let sname: ServiceName = name
            .as_str()
            .try_into()
            .map_err(|e| Error::new(StatusCode::InvalidArgument, format!("service name {name}: {e:?}")))?;
        $node
            .service_builder(&sname)
            .request_response::<$req, $resp>()
            .request_user_header::<RequestHeader>()
            .response_user_header::<ResponseHeader>()
            .open()
            .map_err(|e| open_error(&name, &$opts.prefix, e))
    }};
}

fn open_error(
    name: &str,
    prefix: &str,
    e: iceoryx2::service::builder::request_response::RequestResponseOpenError,
) -> Error {
    use iceoryx2::service::builder::request_response::RequestResponseOpenError as E;
    match e {
        E::DoesNotExist | E::IsMarkedForDestruction | E::HangsInCreation | E::ServiceInCorruptedState => {
            Error::lost(format!("no graspd serves prefix {prefix:?} ({name}: {e:?})"))
        }
        E::IncompatibleRequestOrResponseType
        | E::IncompatibleMessagingPattern
        | E::IncompatibleAttributes
        | E::VersionMismatch => Error::new(
            StatusCode::FailedPrecondition,
            format!(
                "{name} speaks another protocol (this client: graspd.{}, protocol {}): {e:?}",
                proto::VERSION_SEGMENT,
                proto::PROTOCOL_VERSION
            ),
        ),
        E::InsufficientPermissions => Error::new(
            StatusCode::FailedPrecondition,
            format!("{name}: insufficient permissions (is this user in the daemon's group?)"),
        ),
        E::ExceedsMaxNumberOfNodes | E::DoesNotSupportRequestedAmountOfClients => {
            Error::new(StatusCode::ResourceExhausted, format!("{name}: the daemon's client limit is reached"))
        }
        e => Error::new(StatusCode::Internal, format!("{name}: {e:?}")),
    }
}

impl Client {
    /// Connects to the daemon serving `opts.prefix`, waiting up to `opts.connect_timeout` for one.
    pub fn connect(opts: ClientOptions) -> Result<Client, Error> {
        iceoryx2::prelude::set_log_level_from_env_or(LogLevel::Error);
        // No implicit dead-node cleanups: they can block forever on a peer
        // killed at the wrong moment (graspd_proto::hygiene); the daemon cleans.
        let mut config = iceoryx2::config::Config::global_config().clone();
        config.global.node.cleanup_dead_nodes_on_creation = false;
        config.global.node.cleanup_dead_nodes_on_destruction = false;
        config.global.service.cleanup_dead_nodes_on_open = false;
        let node = NodeBuilder::new()
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>()
            .map_err(|e| Error::new(StatusCode::Unavailable, format!("cannot create an iceoryx2 node: {e:?}")))?;
        let token = {
            // Unique per client: the node id (random) folded with time and pid.
            let id = node.id().value();
            let t = unix_ns() as u128 ^ ((std::process::id() as u128) << 64);
            let v = (id ^ t.rotate_left(17)) as u64 ^ (id >> 64) as u64;
            v.max(1)
        };
        let mut c = Client { opts, node, conn: None, next_id: 1, token, last: CallTiming::default() };
        let until = Instant::now() + c.opts.connect_timeout;
        loop {
            match c.ensure_connected() {
                Ok(()) => return Ok(c),
                Err(e) if e.transport && Instant::now() < until => std::thread::sleep(Duration::from_millis(20)),
                Err(e) => return Err(e),
            }
        }
    }

    /// Whether the connected daemon polls (None when not connected).
    pub fn daemon_polls(&self) -> Option<bool> {
        self.conn.as_ref().map(|c| c.daemon_polls)
    }

    pub fn options(&self) -> &ClientOptions {
        &self.opts
    }

    /// Timings of the last call.
    pub fn last_call(&self) -> CallTiming {
        self.last
    }

    /// Drops the connection; the next call reconnects.
    pub fn disconnect(&mut self) {
        self.conn = None;
    }

    fn ensure_connected(&mut self) -> Result<(), Error> {
        if self.conn.is_some() {
            return Ok(());
        }
        let o = &self.opts;
        let node = &self.node;
        let slice_len = o.initial_max_points.max(1);
        let health_svc = open_rr!(node, o, Method::Health, NoPayload, proto::HealthResponse)?;
        let attr = |key: &str| -> Option<String> {
            let k: iceoryx2::service::attribute::AttributeKey = key.try_into().ok()?;
            let mut out = None;
            health_svc.attributes().iter_key_values(&k, |v| {
                out = Some(v.to_string());
                CallbackProgression::Stop
            });
            out
        };
        let version = attr(proto::attribute::PROTOCOL_VERSION);
        if version.as_deref() != Some(&proto::PROTOCOL_VERSION.to_string()) {
            return Err(Error::new(
                StatusCode::FailedPrecondition,
                format!("the daemon speaks protocol {version:?}, this client {}", proto::PROTOCOL_VERSION),
            ));
        }
        // The daemon serving now: the server whose node is alive (a crashed
        // daemon's server lingers until the next daemon removes its stale resources).
        let mut servers = Vec::new();
        health_svc.dynamic_config().list_servers(|s| {
            servers.push(s.node_id);
            CallbackProgression::Continue
        });
        let daemon = servers.into_iter().find(|id| {
            matches!(
                Node::<Ipc>::state_of(node.config(), *id),
                Ok(Some(NodeState::Alive(_))) | Ok(Some(NodeState::Inaccessible(_)))
            )
        });
        if daemon.is_none() {
            return Err(Error::lost(format!(
                "no graspd serves prefix {:?} (services without a live server)",
                o.prefix
            )));
        }
        // Notifiers on the daemon's wake-up event services (dropped below if it polls).
        let notify = |m: Method| -> Result<NotifyPorts, Error> {
            let name = m.notify_service_name(&o.prefix);
            let sname: ServiceName = name.as_str().try_into().map_err(|e| ipc_error("notify service name", e))?;
            let svc = node.service_builder(&sname).event().open().map_err(|e| Error::lost(format!("{name}: {e:?}")))?;
            let n = svc
                .notifier_builder()
                .create()
                .map_err(|e| Error::new(StatusCode::ResourceExhausted, format!("{name} notifier: {e:?}")))?;
            Ok((Some(svc), Some(n)))
        };
        let port_err = |name: &str, e: &dyn Debug| {
            Error::new(StatusCode::ResourceExhausted, format!("client port on {name}: {e:?}"))
        };
        macro_rules! plain {
            ($svc:expr, $m:expr) => {{
                let svc = $svc;
                let port = svc.client_builder().create().map_err(|e| port_err($m.name(), &e))?;
                let (ev, n) = notify($m)?;
                Endpoint { _service: svc, port, _event: ev, notifier: n }
            }};
        }
        macro_rules! cloud {
            ($svc:expr, $m:expr) => {{
                let svc = $svc;
                let port = svc
                    .client_builder()
                    .initial_max_slice_len(slice_len)
                    .allocation_strategy(AllocationStrategy::PowerOfTwo)
                    .create()
                    .map_err(|e| port_err($m.name(), &e))?;
                let (ev, n) = notify($m)?;
                Endpoint { _service: svc, port, _event: ev, notifier: n }
            }};
        }
        let conn = Connection {
            health: plain!(health_svc, Method::Health),
            categories: plain!(
                open_rr!(node, o, Method::ListCategories, NoPayload, proto::CategoriesResponse)?,
                Method::ListCategories
            ),
            register: cloud!(open_rr!(node, o, Method::Register, [Point], proto::RegisterResponse)?, Method::Register),
            grasp: cloud!(open_rr!(node, o, Method::Grasp, [Point], proto::GraspResponse)?, Method::Grasp),
            stats: plain!(open_rr!(node, o, Method::Stats, NoPayload, proto::StatsResponse)?, Method::Stats),
            daemon,
            daemon_polls: false,
            reply: None,
        };
        self.conn = Some(conn);
        // Ask the daemon how it waits (spinning on this first answer).
        let polls = match self.plain_call_once(|c| &c.health) {
            Ok(h) => h.waiting == proto::waiting::POLL,
            Err(e) => {
                self.conn = None;
                return Err(e);
            }
        };
        let event_wait = match self.opts.wait {
            WaitMode::Spin => false,
            WaitMode::Event => true,
            WaitMode::Auto => !polls,
        };
        let reply = if event_wait {
            let name = proto::reply_service_name(&self.opts.prefix, self.token);
            let sname: ServiceName = name.as_str().try_into().map_err(|e| ipc_error("reply service name", e))?;
            let svc = self
                .node
                .service_builder(&sname)
                .event()
                .max_listeners(1)
                .max_notifiers(2)
                .open_or_create()
                .map_err(|e| ipc_error("reply event service", e))?;
            let l = svc.listener_builder().create().map_err(|e| ipc_error("reply listener", e))?;
            Some((svc, l))
        } else {
            None
        };
        let conn = self.conn.as_mut().expect("connected");
        conn.daemon_polls = polls;
        conn.reply = reply;
        if polls {
            // A polling daemon does not listen: skip the notification (a syscall) per call.
            for n in [
                &mut conn.health.notifier,
                &mut conn.categories.notifier,
                &mut conn.register.notifier,
                &mut conn.grasp.notifier,
                &mut conn.stats.notifier,
            ] {
                *n = None;
            }
        }
        Ok(())
    }

    fn header(&mut self, deadline_unix_ns: u64) -> RequestHeader {
        let mut h = RequestHeader::zeroed();
        h.request_id = self.next_id;
        self.next_id += 1;
        h.deadline_unix_ns = deadline_unix_ns;
        h.protocol_version = proto::PROTOCOL_VERSION;
        h.notify_token = match &self.conn {
            Some(c) if c.reply.is_some() => self.token,
            _ => 0,
        };
        h
    }

    /// Waits for the response of `pending` until the deadline.
    fn wait<P: Debug + IceoryxSend + ?Sized, R: Debug + ZeroCopySend + Copy>(
        node: &Node<Ipc>,
        conn: &Connection,
        pending: &Pending<P, R>,
        deadline: Instant,
    ) -> Result<(ResponseHeader, R), Error> {
        let mut last_check = Instant::now();
        let started = last_check;
        loop {
            match pending.receive() {
                Ok(Some(r)) => return Ok((*r.user_header(), *r.payload())),
                Ok(None) => {}
                Err(e) => return Err(Error::lost(format!("receiving the response: {e:?}"))),
            }
            if !pending.is_connected() {
                if let Ok(Some(r)) = pending.receive() {
                    return Ok((*r.user_header(), *r.payload()));
                }
                return Err(Error::lost("the daemon dropped the request (it stopped or restarted)"));
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(Error::new(StatusCode::DeadlineExceeded, "no response before the deadline"));
            }
            // The daemon's liveness (a directory scan) only for waits longer than usual.
            if now.duration_since(last_check) >= Duration::from_millis(200) {
                last_check = now;
                if !daemon_alive(node, conn) {
                    return Err(Error::lost("the daemon died while the request was pending"));
                }
            }
            match &conn.reply {
                Some((_, l)) => {
                    let slice = (deadline - now).min(Duration::from_millis(50));
                    let _ = l.timed_wait(|_| {}, slice);
                }
                // Spin 50 µs, then yield the core between looks (the daemon's
                // threads may need it on a busy machine).
                None if now.duration_since(started) < Duration::from_micros(50) => std::hint::spin_loop(),
                None => std::thread::yield_now(),
            }
        }
    }

    /// Sends with `send` (fills and sends the request) and waits; reconnects and
    /// resends when the daemon was lost, within the deadline.
    fn call<P: Debug + IceoryxSend + ?Sized + 'static, R: Debug + ZeroCopySend + Copy + 'static>(
        &mut self,
        timeout: Duration,
        select: fn(&Connection) -> &Endpoint<P, R>,
        send: &mut SendFn<'_, P, R>,
        mut edit: impl FnMut(&mut RequestHeader),
    ) -> Result<(ResponseHeader, R), Error> {
        let deadline = Instant::now() + timeout;
        let deadline_unix = unix_ns().saturating_add(timeout.as_nanos().min(u64::MAX as u128) as u64);
        let mut attempts = 0;
        loop {
            attempts += 1;
            let r = self.ensure_connected().and_then(|_| {
                let mut h = self.header(deadline_unix);
                edit(&mut h);
                let conn = self.conn.as_ref().expect("connected");
                let ep = select(conn);
                let t0 = Instant::now();
                let pending = send(&ep.port, h)?;
                let t1 = Instant::now();
                if let Some(n) = &ep.notifier {
                    let _ = n.notify();
                }
                let out = Self::wait(&self.node, conn, &pending, deadline)?;
                let rtt = t1.elapsed();
                self.last = CallTiming {
                    fill_ns: (t1 - t0).as_nanos() as u64,
                    rtt_ns: rtt.as_nanos() as u64,
                    server_ns: out.0.server_ns,
                    compute_ns: out.0.compute_ns,
                    attempts,
                };
                if out.0.request_id != h.request_id {
                    return Err(Error::new(
                        StatusCode::Internal,
                        format!("response for request {} to request {}", out.0.request_id, h.request_id),
                    ));
                }
                Ok(out)
            });
            match r {
                Err(e)
                    if e.transport
                        && self.opts.resend_after_restart
                        && Instant::now() + Duration::from_millis(20) < deadline =>
                {
                    self.conn = None;
                    std::thread::sleep(Duration::from_millis(20));
                }
                Err(e) => {
                    if e.transport {
                        self.conn = None;
                    }
                    return Err(e);
                }
                Ok(v) => return Ok(v),
            }
        }
    }

    /// One request on the current connection, no reconnection (used while connecting).
    fn plain_call_once<R: Debug + ZeroCopySend + Copy + 'static>(
        &mut self,
        select: fn(&Connection) -> &Endpoint<NoPayload, R>,
    ) -> Result<R, Error> {
        let timeout = self.opts.default_timeout;
        let deadline = Instant::now() + timeout;
        let h = self.header(unix_ns().saturating_add(timeout.as_nanos() as u64));
        let conn = self.conn.as_ref().ok_or_else(|| Error::lost("not connected"))?;
        let ep = select(conn);
        let mut req =
            ep.port.loan_uninit().map_err(|e| Error::new(StatusCode::ResourceExhausted, format!("loan: {e:?}")))?;
        *req.user_header_mut() = h;
        let pending = req.write_payload(NoPayload::default()).send().map_err(send_error)?;
        if let Some(n) = &ep.notifier {
            let _ = n.notify();
        }
        let (rh, body) = Self::wait(&self.node, conn, &pending, deadline)?;
        status(&rh)?;
        Ok(body)
    }

    fn plain_call<R: Debug + ZeroCopySend + Copy + 'static>(
        &mut self,
        select: fn(&Connection) -> &Endpoint<NoPayload, R>,
    ) -> Result<R, Error> {
        let timeout = self.opts.default_timeout;
        let mut send = |port: &Port<NoPayload, R>, h: RequestHeader| -> Result<Pending<NoPayload, R>, Error> {
            let mut req =
                port.loan_uninit().map_err(|e| Error::new(StatusCode::ResourceExhausted, format!("loan: {e:?}")))?;
            *req.user_header_mut() = h;
            req.write_payload(NoPayload::default()).send().map_err(send_error)
        };
        let (h, body) = self.call(timeout, select, &mut send, |_| {})?;
        status(&h)?;
        Ok(body)
    }

    pub fn health(&mut self) -> Result<Health, Error> {
        let r = self.plain_call(|c| &c.health)?;
        Ok(Health {
            serving: r.serving == proto::serving::SERVING,
            draining: r.serving == proto::serving::DRAINING,
            waiting: if r.waiting == proto::waiting::POLL { "poll" } else { "event" },
            pid: r.pid,
            protocol_version: r.protocol_version,
            server_version: proto::text_lossy(&r.server_version),
            uptime_s: r.uptime_ns as f64 * 1e-9,
            startup_ms: r.startup_ns as f64 * 1e-6,
            categories: r.categories,
            max_points: r.max_points,
            max_in_flight_per_client: r.max_in_flight_per_client,
            workers: r.workers,
            grasp_available: r.grasp_available != 0,
            hand_name: Some(proto::text_lossy(&r.hand_name)).filter(|n| !n.is_empty()),
            hand_actuated_joints: r.hand_actuated_joints,
        })
    }

    pub fn categories(&mut self) -> Result<Vec<CategoryInfo>, Error> {
        let r = self.plain_call(|c| &c.categories)?;
        Ok(r.categories[..(r.count as usize).min(proto::MAX_CATEGORIES)]
            .iter()
            .map(|c| CategoryInfo {
                name: proto::text_lossy(&c.name),
                latent_dim: c.latent_dim,
                keypoints: c.keypoint_names[..(c.keypoint_count as usize).min(proto::MAX_KEYPOINTS)]
                    .iter()
                    .map(|n| proto::text_lossy(n))
                    .collect(),
                canonical_frame: proto::text_lossy(&c.canonical_frame),
                grasp_available: c.grasp_available != 0,
            })
            .collect())
    }

    /// The daemon's counters and latency percentiles (raw wire body).
    pub fn stats(&mut self) -> Result<proto::StatsResponse, Error> {
        self.plain_call(|c| &c.stats)
    }

    /// Registers a cloud (metres, cloud frame z up) to `category`.
    pub fn register(&mut self, category: &str, points: &[[f32; 3]], timeout: Duration) -> Result<Registration, Error> {
        self.register_with(category, points, &CloudOptions::default(), timeout)
    }

    pub fn register_with(
        &mut self,
        category: &str,
        points: &[[f32; 3]],
        opts: &CloudOptions,
        timeout: Duration,
    ) -> Result<Registration, Error> {
        let (h, body) = self.register_raw(
            Cloud::Slice(Point::from_arrays(points)),
            |h| apply_cloud_options(h, category, opts),
            timeout,
        )?;
        status(&h)?;
        Ok(registration(&body.registration, category, &opts.cloud_frame))
    }

    /// Register with full control: the cloud is copied from a slice or written
    /// point by point straight into shared memory, `edit` adjusts the header
    /// (tests use it to send bad headers). Returns the raw response, whatever its status.
    pub fn register_raw(
        &mut self,
        mut cloud: Cloud<'_>,
        edit: impl FnMut(&mut RequestHeader),
        timeout: Duration,
    ) -> Result<(ResponseHeader, proto::RegisterResponse), Error> {
        let mut send =
            |port: &Port<[Point], proto::RegisterResponse>, h: RequestHeader| send_cloud(port, h, &mut cloud);
        self.call(timeout, |c| &c.register, &mut send, edit)
    }

    /// Grasp: registration, grasp and pre-grasp in one round trip.
    pub fn grasp(&mut self, category: &str, points: &[[f32; 3]], timeout: Duration) -> Result<Grasp, Error> {
        self.grasp_with(category, points, &CloudOptions::default(), timeout)
    }

    pub fn grasp_with(
        &mut self,
        category: &str,
        points: &[[f32; 3]],
        opts: &CloudOptions,
        timeout: Duration,
    ) -> Result<Grasp, Error> {
        let (h, body) = self.grasp_raw(
            Cloud::Slice(Point::from_arrays(points)),
            |h| apply_cloud_options(h, category, opts),
            timeout,
        )?;
        status(&h)?;
        Ok(grasp(&body, category, &opts.cloud_frame))
    }

    pub fn grasp_raw(
        &mut self,
        mut cloud: Cloud<'_>,
        edit: impl FnMut(&mut RequestHeader),
        timeout: Duration,
    ) -> Result<(ResponseHeader, proto::GraspResponse), Error> {
        let mut send = |port: &Port<[Point], proto::GraspResponse>, h: RequestHeader| send_cloud(port, h, &mut cloud);
        self.call(timeout, |c| &c.grasp, &mut send, edit)
    }

    /// Sends a Register without waiting (for pipelining and tests of the
    /// in-flight limit); collect the answer with [`Client::wait_register`].
    pub fn start_register(
        &mut self,
        category: &str,
        points: &[[f32; 3]],
        timeout: Duration,
    ) -> Result<PendingRegister, Error> {
        self.ensure_connected()?;
        let deadline_unix = unix_ns() + timeout.as_nanos() as u64;
        let mut h = self.header(deadline_unix);
        apply_cloud_options(&mut h, category, &CloudOptions::default());
        let conn = self.conn.as_ref().expect("connected");
        let pending = send_cloud(&conn.register.port, h, &mut Cloud::Slice(Point::from_arrays(points)))?;
        if let Some(n) = &conn.register.notifier {
            let _ = n.notify();
        }
        Ok(PendingRegister {
            pending,
            request_id: h.request_id,
            deadline: Instant::now() + timeout,
            category: category.to_owned(),
        })
    }

    pub fn wait_register(&mut self, p: PendingRegister) -> Result<Registration, Error> {
        let conn = self.conn.as_ref().ok_or_else(|| Error::lost("disconnected"))?;
        let (h, body) = Self::wait(&self.node, conn, &p.pending, p.deadline)?;
        if h.request_id != p.request_id {
            return Err(Error::new(StatusCode::Internal, "response to another request"));
        }
        status(&h)?;
        Ok(registration(&body.registration, &p.category, "world"))
    }
}

/// A Register sent and not yet answered.
pub struct PendingRegister {
    pending: Pending<[Point], proto::RegisterResponse>,
    request_id: u64,
    deadline: Instant,
    category: String,
}

/// Where the points of a request come from.
pub enum Cloud<'a> {
    /// Copied into shared memory in one pass.
    Slice(&'a [Point]),
    /// `n` points produced one by one straight into shared memory.
    Generate(usize, &'a mut dyn FnMut(usize) -> Point),
}

fn send_cloud<R: Debug + ZeroCopySend + Copy>(
    port: &Port<[Point], R>,
    h: RequestHeader,
    cloud: &mut Cloud<'_>,
) -> Result<Pending<[Point], R>, Error> {
    let n = match cloud {
        Cloud::Slice(s) => s.len(),
        Cloud::Generate(n, _) => *n,
    };
    let req = port.loan_slice_uninit(n).map_err(|e| {
        Error::new(StatusCode::ResourceExhausted, format!("cannot loan {n} points of shared memory: {e:?}"))
    })?;
    let mut req = match cloud {
        Cloud::Slice(s) => req.write_from_slice(s),
        Cloud::Generate(_, f) => req.write_from_fn(f),
    };
    *req.user_header_mut() = h;
    req.send().map_err(send_error)
}

fn send_error(e: iceoryx2::port::client::RequestSendError) -> Error {
    use iceoryx2::port::client::RequestSendError as E;
    match e {
        E::ExceedsMaxActiveRequests => {
            Error::new(StatusCode::ResourceExhausted, "too many requests in flight from this client")
        }
        e => Error::lost(format!("send: {e:?}")),
    }
}

fn daemon_alive(node: &Node<Ipc>, conn: &Connection) -> bool {
    let Some(id) = conn.daemon else { return true };
    match Node::<Ipc>::state_of(node.config(), id) {
        Ok(Some(NodeState::Alive(_))) | Ok(Some(NodeState::Inaccessible(_))) | Err(_) => true,
        Ok(Some(NodeState::Dead(_))) => false,
        Ok(Some(NodeState::Undefined(_))) | Ok(None) => false,
    }
}

fn status(h: &ResponseHeader) -> Result<(), Error> {
    match StatusCode::from_u32(h.status) {
        StatusCode::Ok => Ok(()),
        code => Err(Error::new(code, proto::text_lossy(&h.message))),
    }
}

fn apply_cloud_options(h: &mut RequestHeader, category: &str, o: &CloudOptions) {
    h.category = proto::str_to_text(category);
    if category.len() > 32 {
        // Too long for the field: send bytes the daemon rejects rather than a truncated name.
        h.category = [0xff; 32];
    }
    h.cloud_frame = proto::str_to_text(&o.cloud_frame);
    h.up_in_cloud = o.up.unwrap_or([0.0; 3]);
    if let Some(v) = o.viewpoint {
        h.flags |= proto::flags::VIEWPOINT;
        h.viewpoint_in_cloud_m = v;
    }
    if let Some(v) = o.second_viewpoint {
        h.flags |= proto::flags::SECOND_VIEWPOINT;
        h.second_viewpoint_in_cloud_m = v;
    }
    h.seed = o.seed;
    match o.table {
        None => h.table_mode = proto::table_mode::AUTO,
        Some(Table::None) => h.table_mode = proto::table_mode::NONE,
        Some(Table::At(z)) => {
            h.table_mode = proto::table_mode::GIVEN;
            h.table_z_m = z;
        }
    }
    h.pregrasp_backoff_m = o.pregrasp_backoff_m.unwrap_or(0.0);
    h.pregrasp_joint_fraction = o.pregrasp_joint_fraction.unwrap_or(0.0);
}

fn registration(r: &proto::Registration, category: &str, frame: &str) -> Registration {
    Registration {
        category: category.to_owned(),
        cloud_frame: frame.to_owned(),
        points: r.points,
        latent: r.latent[..(r.latent_dim as usize).min(proto::MAX_LATENT)].to_vec(),
        pose: Pose {
            frame: "cloud_from_canonical".into(),
            translation: r.translation_cloud_from_canonical_m,
            rotation_xyzw: r.rotation_cloud_from_canonical_xyzw,
        },
        scale: r.scale,
        sigma2_m2: r.sigma2_m2,
        fit: Fit {
            inlier_fraction: r.inlier_fraction,
            residual_m: r.residual_m,
            inlier_threshold_m: r.inlier_threshold_m,
            confident: r.confident != 0,
            ambiguous_pose: r.ambiguous_pose != 0,
            stray_points: r.stray_points,
            table_points: r.table_points,
            coverage: r.coverage,
            view_width_m: r.view_width_m,
            latent_mahalanobis: r.latent_mahalanobis,
            contradicted_fraction: (r.contradicted_fraction >= 0.0).then_some(r.contradicted_fraction),
            yaw_half_width_rad: (r.yaw_half_width_rad >= 0.0).then_some(f64::from(r.yaw_half_width_rad)),
        },
        keypoints: r.keypoints[..(r.keypoint_count as usize).min(proto::MAX_KEYPOINTS)]
            .iter()
            .map(|k| NamedPoint { name: proto::text_lossy(&k.name), position: k.position_cloud_m })
            .collect(),
        viewpoint: match r.viewpoint_source {
            proto::viewpoint_source::GIVEN => Viewpoint::Given { position: r.viewpoint_cloud_m },
            proto::viewpoint_source::ESTIMATED => Viewpoint::Estimated { position: r.viewpoint_cloud_m },
            _ => Viewpoint::None,
        },
    }
}

fn hand(c: &proto::HandConfiguration, actuated: &[String], joints: &[String]) -> HandConfiguration {
    HandConfiguration {
        wrist_pose: Pose {
            frame: "cloud_from_wrist".into(),
            translation: c.translation_cloud_from_wrist_m,
            rotation_xyzw: c.rotation_cloud_from_wrist_xyzw,
        },
        actuated: actuated.iter().cloned().zip(c.actuated.iter().copied()).collect(),
        joints: joints.iter().cloned().zip(c.joints.iter().copied()).collect(),
    }
}

fn grasp(g: &proto::GraspResponse, category: &str, frame: &str) -> Grasp {
    let names = |v: &[proto::Name], n: u32| -> Vec<String> {
        v[..(n as usize).min(proto::MAX_JOINTS)].iter().map(|x| proto::text_lossy(x)).collect()
    };
    let (a, j) = (names(&g.actuated_names, g.actuated_count), names(&g.joint_names, g.joint_count));
    let mut warnings = Vec::new();
    if g.warnings & proto::grasp_warning::REGISTRATION_NOT_CONFIDENT != 0 {
        warnings.push("the registration is not confident: the cloud may not be a tool of this category");
    }
    if g.warnings & proto::grasp_warning::PREGRASP_IN_COLLISION != 0 {
        warnings.push("the pre-grasp touches the scene; try a larger back-off");
    }
    if g.warnings & proto::grasp_warning::NO_TABLE_FRAME_NOT_Z_UP != 0 {
        warnings.push("no table: the cloud's frame is not z up");
    }
    Grasp {
        registration: registration(&g.registration, category, frame),
        grasp: hand(&g.grasp, &a, &j),
        pregrasp: hand(&g.pregrasp, &a, &j),
        task_space_distance_m: g.task_space_distance_m,
        residual_mean_m: g.residual_mean_m,
        residual_max_m: g.residual_max_m,
        penetration_m: g.penetration_m,
        pregrasp_min_clearance_m: g.pregrasp_min_clearance_m,
        pregrasp_collision_free: g.pregrasp_collision_free != 0,
        table_z_m: (g.table_used != 0).then_some(g.table_z_m),
        warnings,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_client_can_move_between_threads() {
        fn send<T: Send>() {}
        send::<Client>();
        send::<Error>();
    }

    #[test]
    fn no_daemon_is_unavailable_not_a_hang() {
        let opts =
            ClientOptions { prefix: format!("graspd_no_daemon_{}", std::process::id()), ..ClientOptions::default() };
        let e = Client::connect(opts).err().expect("no daemon");
        assert_eq!(e.code, StatusCode::Unavailable, "{e}");
    }

    #[test]
    fn long_category_names_are_sent_as_invalid_bytes_not_truncated() {
        let mut h = RequestHeader::zeroed();
        apply_cloud_options(&mut h, &"x".repeat(40), &CloudOptions::default());
        assert!(proto::name_to_str(&h.category).is_err());
        apply_cloud_options(&mut h, "mug", &CloudOptions::default());
        assert_eq!(proto::name_to_str(&h.category).unwrap(), "mug");
        assert_eq!(h.up_in_cloud, [0.0, 0.0, 1.0]);
    }
}

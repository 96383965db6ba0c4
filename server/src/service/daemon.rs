//! The daemon: iceoryx2 services, the dispatcher loop and the engine workers.
//!
//! One dispatcher thread owns the server ports. It receives every request,
//! validates its header (cheap, bounded work), answers Health,
//! ListCategories, Stats and every invalid request at once, and hands valid
//! Register/Grasp requests to a bounded queue. Worker threads take a request
//! from the queue, read its cloud straight from shared memory, run the
//! engine and send the response themselves (the daemon uses iceoryx2's
//! thread-safe service variant, so a request may move to a worker). A slow or
//! huge request therefore occupies one worker, never the dispatcher, and one
//! client holds at most `max_in_flight_per_client` requests.

use super::config::{Config, Waiting};
use super::engine::{Engine, Status};
use super::janitor::{cleanup_dead_peers_guarded, ipc_config, start_janitors};
use super::stats::{rss_bytes, Stats};
use graspd_proto::{self as proto, Method, NoPayload, Point, RequestHeader, ResponseHeader, StatusCode};
use iceoryx2::active_request::ActiveRequest;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::server::Server;
use iceoryx2::prelude::*;
use iceoryx2::response_mut_uninit::ResponseMutUninit;
use iceoryx2::service::port_factory::{event as event_factory, request_response as rr_factory};
use iceoryx2::waitset::WaitSetRunResult;
use std::collections::{HashMap, VecDeque};
use std::fmt::Debug;
use std::mem::MaybeUninit;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// iceoryx2's thread-safe IPC variant: requests can move to worker threads.
pub type Ipc = ipc_threadsafe::Service;

type ReqOf<P, R> = ActiveRequest<Ipc, P, RequestHeader, R, ResponseHeader>;
type CloudReq<R> = ReqOf<[Point], R>;
type ServerOf<P, R> = Server<Ipc, P, RequestHeader, R, ResponseHeader>;
type RrFactory<P, R> = rr_factory::PortFactory<Ipc, P, RequestHeader, R, ResponseHeader>;
/// A response in shared memory, loaned and not yet written.
type ResponseLoan<R> = ResponseMutUninit<Ipc, MaybeUninit<R>, ResponseHeader>;

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Config(#[from] super::config::ConfigError),
    #[error(transparent)]
    Engine(#[from] super::engine::EngineError),
    #[error("iceoryx2: {0}")]
    Ipc(String),
}

macro_rules! ipc {
    ($e:expr, $what:expr) => {
        $e.map_err(|e| ServeError::Ipc(format!("{}: {:?}", $what, e)))
    };
}

/// What a finished `serve` reports.
#[derive(Debug, serde::Serialize)]
pub struct ServeReport {
    pub startup_ms: f64,
    pub uptime_s: f64,
    pub requests: u64,
    /// Requests still unanswered when the shutdown grace ran out.
    pub abandoned: usize,
}

pub fn now_unix_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

/// A job for a worker: a validated Register or Grasp request.
enum Job {
    Register(CloudJob<proto::RegisterResponse>),
    Grasp(CloudJob<proto::GraspResponse>),
}

/// A cloud request with its response already loaned.
///
/// The receiving thread loans the response when it admits the request: the
/// server port's state is then in its cache and no other thread holds the
/// port's lock. Loaned by the worker after the engine's 10 ms, while the
/// leader polls the same port, the loan alone took 25-30 µs p50 of a 60 µs
/// transport overhead (mug, 20,000 points, poll mode, 2 cores; probes around
/// each step, 12-02). A loan that fails is answered before any work is done.
struct CloudJob<R: Debug + ZeroCopySend + 'static> {
    req: CloudReq<R>,
    response: ResponseLoan<R>,
    meta: JobMeta,
}

struct JobMeta {
    header: RequestHeader,
    category: usize,
    client: u128,
    received: Instant,
    /// Waited in the queue (the client may have gone meanwhile).
    queued: bool,
}

/// A client's reply notifier: being opened, open, or not openable (retried later).
// One a client: boxing the open variant would buy nothing.
#[allow(clippy::large_enum_variant)]
enum Reply {
    Opening {
        notify_when_open: bool,
    },
    /// The service handle keeps the client's event service open while we notify it.
    Open(#[allow(dead_code)] event_factory::PortFactory<Ipc>, Notifier<Ipc>),
    Failed,
}

/// Reply notifiers, one per client token. Opening a client's event service
/// takes milliseconds, so a background thread does it (the caller never
/// waits) and delivers the notification that asked for it.
struct Notifiers {
    /// token → state, last use.
    entries: HashMap<u64, (Reply, Instant)>,
    capacity: usize,
    opener: std::sync::mpsc::Sender<u64>,
}

impl Notifiers {
    fn notify(&mut self, token: u64) {
        let now = Instant::now();
        let reopen = match self.entries.get_mut(&token) {
            Some((Reply::Open(_, n), t)) => {
                *t = now;
                match n.notify() {
                    Ok(listeners) if listeners > 0 => return,
                    // The client's listener is gone: forget it (a new one is opened on demand).
                    _ => {
                        self.entries.remove(&token);
                        return;
                    }
                }
            }
            Some((Reply::Opening { notify_when_open }, _)) => {
                *notify_when_open = true;
                return;
            }
            Some((Reply::Failed, t)) => now.duration_since(*t) > Duration::from_secs(1),
            None => true,
        };
        if reopen {
            if self.entries.len() >= self.capacity {
                if let Some(oldest) = self.entries.iter().min_by_key(|(_, (_, t))| *t).map(|(k, _)| *k) {
                    self.entries.remove(&oldest);
                }
            }
            self.entries.insert(token, (Reply::Opening { notify_when_open: true }, now));
            let _ = self.opener.send(token);
        }
    }

    fn opened(&mut self, token: u64, result: Option<(event_factory::PortFactory<Ipc>, Notifier<Ipc>)>) {
        let now = Instant::now();
        let wanted = matches!(self.entries.get(&token), Some((Reply::Opening { notify_when_open: true }, _)));
        match result {
            Some((svc, n)) => {
                if wanted {
                    let _ = n.notify();
                }
                self.entries.insert(token, (Reply::Open(svc, n), now));
            }
            None => {
                tracing::debug!("no reply event service for token {token:016x}");
                self.entries.insert(token, (Reply::Failed, now));
            }
        }
    }

    fn evict_idle(&mut self, idle: Duration) {
        let now = Instant::now();
        self.entries.retain(|_, (r, t)| matches!(r, Reply::Opening { .. }) || now.duration_since(*t) < idle);
    }
}

/// The thread that opens reply notifiers (see [`Notifiers`]).
fn reply_opener(node: Node<Ipc>, prefix: String, rx: std::sync::mpsc::Receiver<u64>, shared: std::sync::Weak<Shared>) {
    loop {
        let token = match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(t) => t,
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => match shared.upgrade() {
                Some(s) if !s.stop_workers.load(Ordering::Acquire) => continue,
                _ => return,
            },
            Err(_) => return,
        };
        let opened = proto::reply_service_name(&prefix, token)
            .as_str()
            .try_into()
            .ok()
            .and_then(|name: ServiceName| node.service_builder(&name).event().open().ok())
            .and_then(|svc| svc.notifier_builder().create().ok().map(|n| (svc, n)));
        match shared.upgrade() {
            Some(s) => lock(&s.notifiers).opened(token, opened),
            None => return,
        }
    }
}

/// State shared by the dispatcher and the workers.
struct Shared {
    config: Config,
    engine: Engine,
    stats: Mutex<Stats>,
    in_flight: Mutex<HashMap<u128, u32>>,
    notifiers: Mutex<Notifiers>,
    /// Admitted requests no thread could take yet (all `workers` busy).
    queue: Mutex<VecDeque<Job>>,
    queue_capacity: usize,
    /// Threads running an engine job, at most `max_running` (the `workers` option).
    running: AtomicUsize,
    max_running: usize,
    /// Threads receiving in [`linger_for`] after a job.
    lingering: AtomicUsize,
    /// Cores this process may run on (see [`Shared::leader_should_nap`]).
    cores: usize,
    /// Held by the one thread that receives requests (the leader).
    leadership: Mutex<LeaderState>,
    stop_workers: AtomicBool,
    draining: AtomicBool,
    drain_started: Mutex<Option<Instant>>,
    fatal: Mutex<Option<String>>,
    slow_ns: u64,
    started: Instant,
    startup_ns: u64,
}

/// Housekeeping clocks, kept by whichever thread leads.
struct LeaderState {
    last_house: Instant,
    last_metrics: Instant,
}

/// Locks a mutex; a poisoned one (a panic while held, which the workers'
/// catch_unwind makes unlikely) is used as is: counters stay usable.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Shared {
    fn response_header(
        &self,
        h: &RequestHeader,
        status: &Status,
        received: Instant,
        compute_ns: u64,
    ) -> ResponseHeader {
        let mut r = ResponseHeader::zeroed();
        r.request_id = h.request_id;
        r.status = status.code as u32;
        r.protocol_version = proto::PROTOCOL_VERSION;
        r.message = proto::str_to_text(&status.message);
        r.compute_ns = compute_ns;
        r.server_ns = received.elapsed().as_nanos() as u64;
        r
    }

    /// Sends a response (body zero unless OK), notifies the client, records it.
    fn answer<P: Debug + IceoryxSend + ?Sized, R: Debug + ZeroCopySend + Copy + Default>(
        &self,
        method: Method,
        req: &ReqOf<P, R>,
        status: Status,
        body: Option<&R>,
        received: Instant,
        compute_ns: u64,
    ) {
        let loan = req.loan_uninit().map_err(|e| format!("{e:?}"));
        self.answer_in(method, req.user_header(), loan, status, body, received, compute_ns);
    }

    /// [`Self::answer`] into a response loaned earlier.
    #[allow(clippy::too_many_arguments)]
    fn answer_in<R: Debug + ZeroCopySend + Copy + Default>(
        &self,
        method: Method,
        h: &RequestHeader,
        loan: Result<ResponseLoan<R>, String>,
        status: Status,
        body: Option<&R>,
        received: Instant,
        compute_ns: u64,
    ) {
        let h = *h;
        let hdr = self.response_header(&h, &status, received, compute_ns);
        // Counted before the client can see the answer (a Stats call right after it includes it).
        let slow = lock(&self.stats).record(method, status.code, hdr.server_ns, compute_ns, self.slow_ns);
        match loan {
            Ok(mut r) => {
                *r.user_header_mut() = hdr;
                let r = r.write_payload(body.copied().unwrap_or_default());
                if let Err(e) = r.send() {
                    // The client is gone or its buffer is full: nothing more can be done for it.
                    tracing::debug!(
                        "{}: could not send the response to request {}: {e:?}",
                        method.name(),
                        h.request_id
                    );
                }
            }
            // The daemon's own response memory ran out: the client waits out its
            // deadline, so this is the operator's to see (cloud requests loan
            // theirs at admission and are answered RESOURCE_EXHAUSTED instead).
            Err(e) => tracing::warn!(
                "{}: no shared memory for the response to request {} (status {:?} not sent): {e}",
                method.name(),
                h.request_id,
                status.code
            ),
        }
        if h.notify_token != 0 {
            lock(&self.notifiers).notify(h.notify_token);
        }
        if slow {
            tracing::warn!(
                method = method.name(),
                request_id = h.request_id,
                status = status.code.name(),
                server_ms = hdr.server_ns as f64 * 1e-6,
                compute_ms = compute_ns as f64 * 1e-6,
                "slow request"
            );
        }
    }

    fn release(&self, method: Method, client: u128) {
        let mut f = lock(&self.in_flight);
        if let Some(n) = f.get_mut(&client) {
            *n -= 1;
            if *n == 0 {
                f.remove(&client);
            }
        }
        drop(f);
        let mut s = lock(&self.stats);
        let m = &mut s.methods[method as usize];
        m.in_flight = m.in_flight.saturating_sub(1);
    }

    fn deadline_passed(h: &RequestHeader) -> bool {
        h.deadline_unix_ns != 0 && now_unix_ns() > h.deadline_unix_ns
    }

    /// Header checks common to every method.
    fn check_header(&self, h: &RequestHeader) -> Result<(), Status> {
        if h.protocol_version != proto::PROTOCOL_VERSION {
            return Err(Status::invalid(format!(
                "protocol_version {}; this daemon speaks {}",
                h.protocol_version,
                proto::PROTOCOL_VERSION
            )));
        }
        if h.flags & !proto::flags::ALL != 0 {
            return Err(Status::invalid(format!(
                "flags {:#x}: unknown bits (known: {:#x})",
                h.flags,
                proto::flags::ALL
            )));
        }
        if h.reserved != 0 {
            return Err(Status::invalid(format!(
                "reserved {:#x}: must be 0 (a newer protocol's field this daemon does not know?)",
                h.reserved
            )));
        }
        if Self::deadline_passed(h) {
            return Err(Status::new(StatusCode::DeadlineExceeded, "deadline passed before the request was read"));
        }
        if self.draining.load(Ordering::Relaxed) {
            return Err(Status::new(StatusCode::Unavailable, "the daemon is shutting down"));
        }
        Ok(())
    }

    /// Checks of a cloud request; returns the category index.
    fn check_cloud(&self, method: Method, h: &RequestHeader, points: usize) -> Result<usize, Status> {
        let name = proto::name_to_str(&h.category).map_err(|e| Status::invalid(format!("category: {e}")))?;
        proto::name_to_str(&h.cloud_frame).map_err(|e| Status::invalid(format!("cloud_frame: {e}")))?;
        let category = self.engine.find(name).ok_or_else(|| {
            Status::new(
                StatusCode::NotFound,
                format!("category {name:?} is not served (served: {})", self.engine.names().join(", ")),
            )
        })?;
        if points == 0 {
            return Err(Status::invalid("empty cloud"));
        }
        if points > self.config.max_points as usize {
            return Err(Status::new(
                StatusCode::ResourceExhausted,
                format!("{points} points; this daemon accepts at most {}", self.config.max_points),
            ));
        }
        let [x, y, z] = h.up_in_cloud;
        if !(x.is_finite() && y.is_finite() && z.is_finite()) {
            return Err(Status::invalid("up_in_cloud is not finite"));
        }
        if method == Method::Grasp {
            if h.table_mode > proto::table_mode::GIVEN {
                return Err(Status::invalid(format!("table_mode {}: 0 AUTO, 1 NONE, 2 GIVEN", h.table_mode)));
            }
            if !h.table_z_m.is_finite() {
                return Err(Status::invalid("table_z_m is not finite"));
            }
            super::engine::pregrasp_options(h)?;
            if let Err(e) = &self.engine.categories[category].grasp {
                return Err(Status::new(
                    StatusCode::FailedPrecondition,
                    format!("grasp not available for {name}: {e}"),
                ));
            }
        }
        Ok(category)
    }

    /// Reserves an in-flight slot for the client.
    fn admit(&self, method: Method, client: u128) -> Result<(), Status> {
        let mut f = lock(&self.in_flight);
        let n = f.entry(client).or_insert(0);
        if *n >= self.config.max_in_flight_per_client {
            let limit = self.config.max_in_flight_per_client;
            if *n == 0 {
                f.remove(&client);
            }
            return Err(Status::new(
                StatusCode::ResourceExhausted,
                format!("more than {limit} requests in flight from this client"),
            ));
        }
        *n += 1;
        drop(f);
        lock(&self.stats).methods[method as usize].in_flight += 1;
        Ok(())
    }

    fn health(&self, startup_ns: u64) -> proto::HealthResponse {
        let mut r = proto::HealthResponse::zeroed();
        r.uptime_ns = self.started.elapsed().as_nanos() as u64;
        r.startup_ns = startup_ns;
        r.pid = std::process::id();
        r.protocol_version = proto::PROTOCOL_VERSION;
        r.serving =
            if self.draining.load(Ordering::Relaxed) { proto::serving::DRAINING } else { proto::serving::SERVING };
        r.waiting = match self.config.waiting {
            Waiting::Event => proto::waiting::EVENT,
            Waiting::Poll => proto::waiting::POLL,
        };
        r.categories = self.engine.categories.len() as u32;
        r.max_points = self.config.max_points;
        r.max_in_flight_per_client = self.config.max_in_flight_per_client;
        // Not `config.worker_count()`: with `workers = 0` that asks the OS
        // (cgroup files) on every call, measured 20 µs of each Health.
        r.workers = self.max_running as u32;
        r.grasp_available = self.engine.grasp_available() as u32;
        r.server_version = proto::str_to_text(env!("CARGO_PKG_VERSION"));
        if let Some((name, actuated)) = self.engine.hand() {
            r.hand_name = proto::str_to_text(name);
            r.hand_actuated_joints = actuated as u32;
        }
        r
    }

    fn categories(&self) -> proto::CategoriesResponse {
        let mut r = proto::CategoriesResponse::zeroed();
        r.count = self.engine.categories.len() as u32;
        for (slot, c) in r.categories.iter_mut().zip(&self.engine.categories) {
            *slot = c.info;
        }
        r
    }

    fn stats(&self, clients: u64) -> proto::StatsResponse {
        let queued = lock(&self.queue).len() as u32;
        lock(&self.stats).to_wire(self.started.elapsed().as_nanos() as u64, rss_bytes(), clients, queued)
    }

    fn in_flight_total(&self) -> usize {
        lock(&self.in_flight).values().map(|n| *n as usize).sum()
    }

    /// Runs one job on a worker: deadline, engine (panics contained), answer.
    fn run_job(&self, job: Job) {
        match job {
            Job::Register(job) => {
                let c = job.meta.category;
                let out = self.run_cloud(Method::Register, &job, |pts, h| self.engine.register(c, pts, h));
                self.finish(Method::Register, job, out);
            }
            Job::Grasp(job) => {
                let c = job.meta.category;
                let out = self.run_cloud(Method::Grasp, &job, |pts, h| self.engine.grasp(c, pts, h));
                self.finish(Method::Grasp, job, out);
            }
        }
    }

    /// Frees the client's in-flight slot, then answers: a client that sends its
    /// next request as soon as it has the answer must find the slot free.
    fn finish<R: Debug + ZeroCopySend + Copy + Default>(
        &self,
        method: Method,
        job: CloudJob<R>,
        out: Option<(Status, Option<R>, u64)>,
    ) {
        self.release(method, job.meta.client);
        if let Some((status, body, compute_ns)) = out {
            let h = &job.meta.header;
            self.answer_in(method, h, Ok(job.response), status, body.as_ref(), job.meta.received, compute_ns);
        }
    }

    /// Frees the client's slot and answers an admitted job with `status` and no body.
    fn reject<R: Debug + ZeroCopySend + Copy + Default>(&self, method: Method, job: CloudJob<R>, status: Status) {
        self.release(method, job.meta.client);
        self.answer_in(method, &job.meta.header, Ok(job.response), status, None, job.meta.received, 0);
    }

    /// The work of a cloud request: (status, body, engine ns), or None when the client is gone.
    fn run_cloud<R: Debug + ZeroCopySend + Copy + Default>(
        &self,
        method: Method,
        job: &CloudJob<R>,
        work: impl FnOnce(&[Point], &RequestHeader) -> Result<R, Status>,
    ) -> Option<(Status, Option<R>, u64)> {
        let (req, meta) = (&job.req, &job.meta);
        // A request taken as it arrived has a client; one that waited in the queue may not.
        if meta.queued && !req.is_connected() {
            tracing::debug!("{}: client gone before request {} was worked on", method.name(), meta.header.request_id);
            return None;
        }
        if Self::deadline_passed(&meta.header) {
            return Some((
                Status::new(StatusCode::DeadlineExceeded, "deadline passed while the request waited for a worker"),
                None,
                0,
            ));
        }
        let t0 = Instant::now();
        // The cloud is read in place from shared memory (the engine converts it once).
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| work(req.payload(), &meta.header)));
        let compute_ns = t0.elapsed().as_nanos() as u64;
        Some(match result {
            Ok(Ok(_)) if Self::deadline_passed(&meta.header) => {
                (Status::new(StatusCode::DeadlineExceeded, "deadline passed during the computation"), None, compute_ns)
            }
            Ok(Ok(body)) => (Status::new(StatusCode::Ok, ""), Some(body), compute_ns),
            Ok(Err(s)) => (s, None, compute_ns),
            Err(panic) => {
                let what = panic
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| panic.downcast_ref::<String>().cloned())
                    .unwrap_or_default();
                tracing::error!("{}: request {} panicked in the engine: {what}", method.name(), meta.header.request_id);
                (Status::new(StatusCode::Internal, format!("internal error: {what}")), None, compute_ns)
            }
        })
    }

    /// A polling leader naps instead of spinning while other threads of the
    /// daemon are busy (an engine job, or lingering for the client's next
    /// request) and the cores could not hold them, the spinning leader and a
    /// spinning client each on their own. On two cores the leader's spin took
    /// turns with the engine thread and the client: `graspctl bench --wait
    /// spin` against a polling daemon, 2-core AMD EPYC, 2026-12-06, transport
    /// overhead without the fill p50 26-37 µs, of which 15-21 µs inside the
    /// daemon, against 8 µs event-driven. A request that arrives during a nap
    /// waits for its end (about 60 µs with Linux's timer slack); with the
    /// cores to spare, the leader never naps.
    fn leader_should_nap(&self) -> bool {
        let busy = self.running.load(Ordering::Relaxed) + self.lingering.load(Ordering::Relaxed);
        busy > 0 && self.cores < busy + 2
    }

    /// Reserves one of the `workers` engine slots.
    fn try_reserve(&self) -> bool {
        self.running
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| (n < self.max_running).then_some(n + 1))
            .is_ok()
    }

    fn unreserve(&self) {
        self.running.fetch_sub(1, Ordering::AcqRel);
    }

    /// A queued job with a reserved engine slot.
    fn pop_reserved(&self) -> Option<Job> {
        let mut q = lock(&self.queue);
        if q.is_empty() || !self.try_reserve() {
            return None;
        }
        q.pop_front()
    }

    /// Queues a job, or hands it back (to be answered) when the queue is full.
    #[allow(clippy::result_large_err)]
    fn submit(&self, job: Job) -> Result<(), (Job, Status)> {
        let mut q = lock(&self.queue);
        if q.len() >= self.queue_capacity {
            return Err((job, Status::new(StatusCode::ResourceExhausted, "the daemon's work queue is full")));
        }
        q.push_back(job);
        Ok(())
    }

    fn begin_drain(&self) {
        let mut t = lock(&self.drain_started);
        if t.is_none() {
            *t = Some(Instant::now());
            self.draining.store(true, Ordering::Relaxed);
            tracing::info!(in_flight = self.in_flight_total(), "shutting down: finishing the requests in flight");
        }
    }

    fn fail(&self, e: String) {
        tracing::error!("{e}; shutting down");
        lock(&self.fatal).get_or_insert(e);
        self.begin_drain();
    }

    /// Answers every queued request UNAVAILABLE (the grace period is over).
    fn reject_queued(&self) {
        let leftover: Vec<Job> = lock(&self.queue).drain(..).collect();
        for job in leftover {
            let s = || Status::new(StatusCode::Unavailable, "the daemon shut down before this request was worked on");
            match job {
                Job::Register(job) => self.reject(Method::Register, job, s()),
                Job::Grasp(job) => self.reject(Method::Grasp, job, s()),
            }
        }
    }

    /// Once draining: true when everything accepted is answered or the grace period is over.
    fn drained(&self) -> bool {
        let Some(t) = *lock(&self.drain_started) else { return false };
        if self.in_flight_total() == 0 {
            return true;
        }
        if t.elapsed() > Duration::from_secs_f64(self.config.shutdown_grace_s) {
            self.reject_queued();
            return true;
        }
        false
    }
}

/// One method's service: the server port, the paired event listener.
struct Endpoint<P: Debug + IceoryxSend + ?Sized + 'static, R: Debug + ZeroCopySend + 'static> {
    _service: RrFactory<P, R>,
    server: ServerOf<P, R>,
    _event: event_factory::PortFactory<Ipc>,
    listener: Listener<Ipc>,
}

/// The service limits and attributes every request-response service gets.
struct ServiceSpec {
    name: String,
    sname: ServiceName,
    attrs: AttributeVerifier,
    clients: usize,
    active: usize,
}

fn service_spec(cfg: &Config, method: Method) -> Result<ServiceSpec, ServeError> {
    let name = method.service_name(&cfg.service_prefix);
    let sname: ServiceName = ipc!(name.as_str().try_into(), format!("service name {name}"))?;
    let key: iceoryx2::service::attribute::AttributeKey =
        ipc!(proto::attribute::PROTOCOL_VERSION.try_into(), "attribute key")?;
    let value: iceoryx2::service::attribute::AttributeValue =
        ipc!(proto::PROTOCOL_VERSION.to_string().as_str().try_into(), "attribute value")?;
    let attrs = ipc!(AttributeVerifier::new().require(&key, &value), "attributes")?;
    Ok(ServiceSpec {
        name,
        sname,
        attrs,
        clients: cfg.max_clients as usize,
        active: cfg.max_in_flight_per_client as usize + 4,
    })
}

/// Opens or creates a request-response service with the daemon's limits (a
/// macro: iceoryx2 implements `create` separately for fixed and slice payloads).
/// Opening matters after a crash: clients that still hold the old service keep
/// it alive, and the restarted daemon becomes its server again. A second live
/// daemon on the same prefix fails at the server port (one server per service).
macro_rules! create_rr {
    ($node:expr, $spec:expr, $req:ty, $resp:ty) => {{
        let spec: &ServiceSpec = $spec;
        $node
            .service_builder(&spec.sname)
            .request_response::<$req, $resp>()
            .request_user_header::<RequestHeader>()
            .response_user_header::<ResponseHeader>()
            .max_servers(1)
            .max_clients(spec.clients)
            .max_nodes(spec.clients + 2)
            .max_active_requests_per_client(spec.active)
            .max_loaned_requests(2)
            .open_or_create_with_attributes(&spec.attrs)
            .map_err(|e| {
                ServeError::Ipc(format!(
                    "cannot open or create {}: {e:?} (services of another graspd version, or held by clients of a daemon with other limits?)",
                    spec.name
                ))
            })
    }};
}

fn endpoint<P: Debug + IceoryxSend + ?Sized + 'static, R: Debug + ZeroCopySend + 'static>(
    node: &Node<Ipc>,
    cfg: &Config,
    method: Method,
    service: RrFactory<P, R>,
) -> Result<Endpoint<P, R>, ServeError> {
    let name = method.service_name(&cfg.service_prefix);
    let server = service.server_builder().create().map_err(|e| {
        ServeError::Ipc(format!(
            "cannot serve {name}: {e:?} (is another graspd serving prefix {:?}?)",
            cfg.service_prefix
        ))
    })?;
    let ename = method.notify_service_name(&cfg.service_prefix);
    let esname: ServiceName = ipc!(ename.as_str().try_into(), format!("service name {ename}"))?;
    let clients = cfg.max_clients as usize;
    let event = ipc!(
        node.service_builder(&esname)
            .event()
            .max_notifiers(clients + 4)
            .max_listeners(2)
            .max_nodes(clients + 4)
            .open_or_create(),
        format!("cannot create {ename}")
    )?;
    let listener = ipc!(event.listener_builder().create(), format!("listener of {ename}"))?;
    Ok(Endpoint { _service: service, server, _event: event, listener })
}

/// All five methods' endpoints.
struct Endpoints {
    health: Endpoint<NoPayload, proto::HealthResponse>,
    categories: Endpoint<NoPayload, proto::CategoriesResponse>,
    register: Endpoint<[Point], proto::RegisterResponse>,
    grasp: Endpoint<[Point], proto::GraspResponse>,
    stats: Endpoint<NoPayload, proto::StatsResponse>,
}

impl Endpoints {
    fn listeners(&self) -> [&Listener<Ipc>; 5] {
        [
            &self.health.listener,
            &self.categories.listener,
            &self.register.listener,
            &self.grasp.listener,
            &self.stats.listener,
        ]
    }

    fn clients_connected(&self) -> u64 {
        self._health_service().dynamic_config().number_of_clients() as u64
    }

    fn _health_service(&self) -> &RrFactory<NoPayload, proto::HealthResponse> {
        &self.health._service
    }
}

/// A received request; a receive error is logged (at most once a second) and ends this pass.
fn received<T, E: Debug>(method: Method, r: Result<Option<T>, E>) -> Option<T> {
    static LAST_LOG_S: AtomicUsize = AtomicUsize::new(0);
    match r {
        Ok(v) => v,
        Err(e) => {
            let now = SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs() as usize).unwrap_or(0);
            if LAST_LOG_S.swap(now, Ordering::Relaxed) != now {
                tracing::warn!("{}: receiving a request failed: {e:?}", method.name());
            }
            None
        }
    }
}

/// One pass over every server: answers plain requests and invalid ones, and
/// admits valid Register/Grasp requests. With `take`, the first admitted one
/// that finds a free engine slot is returned for the calling thread to run
/// (the pass stops there; the next leader carries on); the others are queued.
/// Returns the number of requests handled and the job taken.
fn dispatch(shared: &Shared, ep: &Endpoints, take: bool) -> (usize, Option<Job>) {
    let mut handled = 0;
    // Plain methods: answered here.
    while let Some(req) = received(Method::Health, ep.health.server.receive()) {
        handled += 1;
        let t = Instant::now();
        let body = shared.health(shared.startup_ns);
        // Health is answered even while draining (it reports DRAINING).
        let h = *req.user_header();
        let status = match shared.check_header(&h) {
            Err(s) if s.code != StatusCode::Unavailable => s,
            _ => Status::new(StatusCode::Ok, ""),
        };
        let ok = status.code == StatusCode::Ok;
        shared.answer(Method::Health, &req, status, ok.then_some(&body), t, 0);
    }
    while let Some(req) = received(Method::ListCategories, ep.categories.server.receive()) {
        handled += 1;
        let t = Instant::now();
        match shared.check_header(req.user_header()) {
            Ok(()) => shared.answer(
                Method::ListCategories,
                &req,
                Status::new(StatusCode::Ok, ""),
                Some(&shared.categories()),
                t,
                0,
            ),
            Err(s) => shared.answer(Method::ListCategories, &req, s, None, t, 0),
        }
    }
    while let Some(req) = received(Method::Stats, ep.stats.server.receive()) {
        handled += 1;
        let t = Instant::now();
        match shared.check_header(req.user_header()) {
            Ok(()) => {
                let body = shared.stats(ep.clients_connected());
                shared.answer(Method::Stats, &req, Status::new(StatusCode::Ok, ""), Some(&body), t, 0)
            }
            Err(s) => shared.answer(Method::Stats, &req, s, None, t, 0),
        }
    }
    // Cloud methods: validated here; run by this thread or queued.
    macro_rules! cloud {
        ($server:expr, $method:expr, $variant:ident) => {
            while let Some(req) = received($method, $server.receive()) {
                handled += 1;
                let t = Instant::now();
                let h = *req.user_header();
                let client = req.origin().value();
                let checked = shared
                    .check_header(&h)
                    .and_then(|_| shared.check_cloud($method, &h, req.payload().len()))
                    .and_then(|c| shared.admit($method, client).map(|_| c));
                let loaned = checked.and_then(|category| match req.loan_uninit() {
                    Ok(response) => Ok((category, response)),
                    Err(e) => {
                        shared.release($method, client);
                        Err(Status::new(
                            StatusCode::ResourceExhausted,
                            format!("no shared memory for the response: {e:?}"),
                        ))
                    }
                });
                match loaned {
                    Err(s) => shared.answer($method, &req, s, None, t, 0),
                    Ok((category, response)) => {
                        let taken = take && shared.try_reserve();
                        let meta = JobMeta { header: h, category, client, received: t, queued: !taken };
                        let job = Job::$variant(CloudJob { req, response, meta });
                        if taken {
                            return (handled, Some(job));
                        }
                        if let Err((Job::$variant(job), s)) = shared.submit(job) {
                            shared.reject($method, job, s);
                        }
                    }
                }
            }
        };
    }
    cloud!(ep.register.server, Method::Register, Register);
    cloud!(ep.grasp.server, Method::Grasp, Grasp);
    (handled, None)
}

/// Options given on the command line on top of the configuration.
#[derive(Clone, Debug, Default)]
pub struct ServeOptions {
    /// When the process started (for the startup time); default: now.
    pub process_start: Option<Instant>,
    /// Called once when serving starts, with the startup report.
    pub ready_line: bool,
}

fn default_cache_dir() -> PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces")
}

/// Runs the daemon until SIGINT/SIGTERM; returns after in-flight requests finished.
pub fn serve(config: Config, opts: ServeOptions) -> Result<ServeReport, ServeError> {
    config.validate()?;
    // iceoryx2's own log (stderr): errors only unless IOX2_LOG_LEVEL says otherwise.
    iceoryx2::prelude::set_log_level_from_env_or(LogLevel::Error);
    let process_start = opts.process_start.unwrap_or_else(Instant::now);
    let prefix = config.service_prefix.clone();

    let node_name: NodeName = ipc!("graspd".try_into(), "node name")?;
    let ipc_config = ipc_config();
    // Stale resources of crashed peers (a crashed daemon's server port would
    // keep this daemon from serving) are removed before anything is created.
    cleanup_dead_peers_guarded(&ipc_config);
    let node = ipc!(
        NodeBuilder::new()
            .name(&node_name)
            .config(&ipc_config)
            .signal_handling_mode(SignalHandlingMode::HandleTerminationRequests)
            .create::<Ipc>(),
        "cannot create the iceoryx2 node"
    )?;
    // Registers the SIGINT/SIGTERM handlers now (a signal during loading is honoured after it).
    let _ = termination_requested();

    let cache_dir = config.cache_dir.clone().unwrap_or_else(default_cache_dir);
    let (engine, times) = Engine::load(&config.categories, &cache_dir, &config.grasp_sources())?;
    for (name, ms) in &times {
        tracing::info!("loaded {name} in {ms:.1} ms");
    }

    let spec = |m| service_spec(&config, m);
    let ep = Endpoints {
        health: endpoint(
            &node,
            &config,
            Method::Health,
            create_rr!(node, &spec(Method::Health)?, NoPayload, proto::HealthResponse)?,
        )?,
        categories: endpoint(
            &node,
            &config,
            Method::ListCategories,
            create_rr!(node, &spec(Method::ListCategories)?, NoPayload, proto::CategoriesResponse)?,
        )?,
        register: endpoint(
            &node,
            &config,
            Method::Register,
            create_rr!(node, &spec(Method::Register)?, [Point], proto::RegisterResponse)?,
        )?,
        grasp: endpoint(
            &node,
            &config,
            Method::Grasp,
            create_rr!(node, &spec(Method::Grasp)?, [Point], proto::GraspResponse)?,
        )?,
        stats: endpoint(
            &node,
            &config,
            Method::Stats,
            create_rr!(node, &spec(Method::Stats)?, NoPayload, proto::StatsResponse)?,
        )?,
    };

    let reply_node = ipc!(
        NodeBuilder::new()
            .name(&node_name)
            .config(&ipc_config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>(),
        "reply node"
    )?;
    let janitors = start_janitors(&ipc_config, Duration::from_millis(config.housekeeping_ms))?;
    let workers = config.worker_count();
    let (opener_tx, opener_rx) = std::sync::mpsc::channel();
    let startup_ns = process_start.elapsed().as_nanos() as u64;
    let shared = Arc::new(Shared {
        queue_capacity: (config.max_clients as usize * config.max_in_flight_per_client as usize).max(1),
        running: AtomicUsize::new(0),
        max_running: workers,
        lingering: AtomicUsize::new(0),
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        leadership: Mutex::new(LeaderState { last_house: Instant::now(), last_metrics: Instant::now() }),
        drain_started: Mutex::new(None),
        fatal: Mutex::new(None),
        startup_ns,
        slow_ns: (config.slow_request_ms * 1e6) as u64,
        notifiers: Mutex::new(Notifiers {
            entries: HashMap::new(),
            capacity: 4 * config.max_clients as usize,
            opener: opener_tx,
        }),
        engine,
        config,
        stats: Mutex::new(Stats::new()),
        in_flight: Mutex::new(HashMap::new()),
        queue: Mutex::new(VecDeque::new()),
        stop_workers: AtomicBool::new(false),
        draining: AtomicBool::new(false),
        started: Instant::now(),
    });
    {
        let (weak, prefix) = (Arc::downgrade(&shared), prefix.clone());
        std::thread::Builder::new()
            .name("graspd-reply".into())
            .spawn(move || reply_opener(reply_node, prefix, opener_rx, weak))
            .map_err(|e| ServeError::Ipc(format!("cannot start the reply thread: {e}")))?;
    }
    let _uds = match &shared.config.uds_baseline {
        Some(path) => Some(
            super::uds::start(path, shared_engine_handle(&shared))
                .map_err(|e| ServeError::Ipc(format!("uds baseline {}: {e}", path.display())))?,
        ),
        None => None,
    };
    tracing::info!(
        prefix = %prefix,
        waiting = ?shared.config.waiting,
        workers,
        categories = %shared.engine.names().join(","),
        startup_ms = startup_ns as f64 * 1e-6,
        // Which E-step kernels this CPU runs (GRASPD_SIMD caps them): the
        // first thing to know when fits are slower than the figures say.
        estep_kernels = ?crate::simd::Simd::detect(crate::simd::Simd::Avx512),
        "serving"
    );
    if opts.ready_line {
        // A machine-readable line for supervisors and tests.
        println!(
            "{}",
            serde_json::json!({"ready": true, "prefix": prefix, "startup_ms": startup_ns as f64 * 1e-6, "pid": std::process::id()})
        );
        use std::io::Write;
        let _ = std::io::stdout().flush();
    }

    // `workers` engine slots, one more thread so that one always receives:
    // the thread that receives a Register/Grasp runs it itself and hands
    // receiving to another (no hand-off on the request's path).
    let ep = Arc::new(ep);
    let mut handles = Vec::new();
    for i in 0..workers {
        let (s, e) = (shared.clone(), ep.clone());
        let h = std::thread::Builder::new()
            .name(format!("graspd-{i}"))
            .spawn(move || thread_main(&s, &e))
            .map_err(|e| ServeError::Ipc(format!("cannot start a thread: {e}")))?;
        handles.push(h);
    }
    thread_main(&shared, &ep);

    let abandoned = shared.in_flight_total();
    shared.stop_workers.store(true, Ordering::Release);
    janitors.stop(Duration::from_secs(1));
    if abandoned == 0 {
        for h in handles {
            let _ = h.join();
        }
    } else {
        tracing::warn!(abandoned, "shutdown grace period over with requests still running; leaving them");
    }
    let requests = lock(&shared.stats).methods.iter().map(|m| m.requests).sum();
    let report = ServeReport {
        startup_ms: startup_ns as f64 * 1e-6,
        uptime_s: shared.started.elapsed().as_secs_f64(),
        requests,
        abandoned,
    };
    tracing::info!(requests, uptime_s = report.uptime_s, "stopped");
    let fatal = lock(&shared.fatal).take();
    match fatal {
        Some(e) => Err(ServeError::Ipc(e)),
        None => Ok(report),
    }
}

/// The engine for the Unix-socket baseline. Weak: its accept thread is never
/// joined, and a strong handle would keep `Shared` (and through its reply
/// notifiers the daemon's iceoryx2 node) alive past the daemon's end, leaving
/// the node behind for the next daemon to clean as a dead peer's.
fn shared_engine_handle(shared: &Arc<Shared>) -> super::uds::EngineHandle {
    let weak = Arc::downgrade(shared);
    super::uds::EngineHandle {
        max_points: shared.config.max_points as usize,
        register: Box::new(move |pts: &[Point], h: &RequestHeader| {
            let s = weak.upgrade().ok_or_else(|| Status::new(StatusCode::Unavailable, "the daemon has stopped"))?;
            let category = proto::name_to_str(&h.category)
                .map_err(|e| Status::invalid(format!("category: {e}")))
                .and_then(|n| {
                    s.engine
                        .find(n)
                        .ok_or_else(|| Status::new(StatusCode::NotFound, format!("category {n:?} is not served")))
                })?;
            s.engine.register(category, pts, h)
        }),
    }
}

/// Whether SIGINT/SIGTERM arrived since the last call (iceoryx2's handler sets
/// the flag; reading it clears it, so the caller must act on a true).
fn termination_requested() -> bool {
    iceoryx2_bb_posix::signal::SignalHandler::termination_requested()
}

/// Every serving thread: run the engine job it holds, else lead (receive) or
/// wait to lead. Returns when the daemon stops.
fn thread_main(shared: &Shared, ep: &Endpoints) {
    let waitset = match shared.config.waiting {
        Waiting::Event => match WaitSetBuilder::new()
            .signal_handling_mode(SignalHandlingMode::HandleTerminationRequests)
            .create::<Ipc>()
        {
            Ok(ws) => Some(ws),
            Err(e) => return shared.fail(format!("waitset: {e:?}")),
        },
        Waiting::Poll => None,
    };
    let mut guards = Vec::new();
    let mut tick = None;
    if let Some(ws) = &waitset {
        for l in ep.listeners() {
            match ws.attach_notification(l) {
                Ok(g) => guards.push(g),
                Err(e) => return shared.fail(format!("waitset attach: {e:?}")),
            }
        }
        match ws.attach_interval(Duration::from_millis(shared.config.housekeeping_ms)) {
            Ok(g) => tick = Some(g),
            Err(e) => return shared.fail(format!("waitset interval: {e:?}")),
        }
    }
    let _attached = (&guards, &tick);
    let linger = Duration::from_micros(shared.config.linger_us);
    let mut worked = false;
    loop {
        if shared.stop_workers.load(Ordering::Acquire) {
            return;
        }
        let lingered = if worked && !linger.is_zero() { linger_for(shared, ep, linger) } else { None };
        let job = match lingered {
            Some(job) => Some(job),
            None => {
                let mut st = lock(&shared.leadership);
                lead(shared, ep, waitset.as_ref(), &mut st)
            }
        };
        let Some(job) = job else { return };
        // Leadership is released: another thread receives while this one works.
        shared.run_job(job);
        shared.unreserve();
        while let Some(job) = shared.pop_reserved() {
            shared.run_job(job);
            shared.unreserve();
        }
        worked = true;
    }
}

/// After a job: receives for `window` without leadership, spinning, and
/// returns the first Register/Grasp taken.
///
/// Event-driven, the leader meanwhile sleeps in its WaitSet, and waking it costs the
/// client's next request 100-120 µs on a virtual machine's idle core (the
/// request leg of `graspctl bench` against an event-driven daemon, 12-05,
/// a 2-core AMD EPYC), more than the 100 µs the whole round trip may add.
/// This thread is running and its cache holds the ports: a client that
/// calls again at once is received here in a few microseconds. Two threads
/// may then receive at once, which iceoryx2's thread-safe ports allow; the
/// leader, woken by the same request's notification, finds nothing and
/// sleeps again. Polling, the leader naps meanwhile where the cores are
/// short ([`Shared::leader_should_nap`]), and this thread, its cache warm,
/// takes the client's next request.
fn linger_for(shared: &Shared, ep: &Endpoints, window: Duration) -> Option<Job> {
    shared.lingering.fetch_add(1, Ordering::AcqRel);
    let job = linger_loop(shared, ep, window);
    shared.lingering.fetch_sub(1, Ordering::AcqRel);
    job
}

fn linger_loop(shared: &Shared, ep: &Endpoints, window: Duration) -> Option<Job> {
    let until = Instant::now() + window;
    while Instant::now() < until {
        if shared.stop_workers.load(Ordering::Acquire) || shared.draining.load(Ordering::Relaxed) {
            return None;
        }
        let (_, job) = dispatch(shared, ep, true);
        if job.is_some() {
            return job;
        }
        if let Some(job) = shared.pop_reserved() {
            return Some(job);
        }
        std::hint::spin_loop();
    }
    None
}

/// Receives until a Register/Grasp is taken (returned, to run) or the daemon stops (None).
fn lead(shared: &Shared, ep: &Endpoints, waitset: Option<&WaitSet<Ipc>>, st: &mut LeaderState) -> Option<Job> {
    let housekeeping = Duration::from_millis(shared.config.housekeeping_ms);
    let metrics =
        (shared.config.metrics_interval_s > 0.0).then(|| Duration::from_secs_f64(shared.config.metrics_interval_s));
    let mut last_signal_check = Instant::now();
    let (mut idle_spins, mut idle_since): (u32, Option<Instant>) = (0, None);
    loop {
        if shared.stop_workers.load(Ordering::Acquire) {
            return None;
        }
        if waitset.is_some() {
            // Consume the wake-ups now: requests are all received below.
            for l in ep.listeners() {
                let _ = l.try_wait(|_| {});
            }
        }
        let (handled, job) = dispatch(shared, ep, true);
        if job.is_some() {
            return job;
        }
        if let Some(job) = shared.pop_reserved() {
            return Some(job);
        }
        if shared.draining.load(Ordering::Relaxed) && shared.drained() {
            shared.stop_workers.store(true, Ordering::Release);
            return None;
        }
        if st.last_house.elapsed() >= housekeeping {
            st.last_house = Instant::now();
            lock(&shared.notifiers).evict_idle(Duration::from_secs(30));
            if let Some(every) = metrics {
                if st.last_metrics.elapsed() >= every {
                    st.last_metrics = Instant::now();
                    tracing::info!(target: "graspd::metrics", "{}", proto::json::stats_json(&shared.stats(ep.clients_connected())));
                }
            }
        }
        if handled > 0 {
            idle_spins = 0;
            idle_since = None;
            continue;
        }
        match waitset {
            _ if shared.draining.load(Ordering::Relaxed) => std::thread::sleep(Duration::from_millis(1)),
            Some(ws) => {
                // A signal that arrived while we were busy is not seen by the wait below.
                if termination_requested() {
                    shared.begin_drain();
                    continue;
                }
                match ws.wait_and_process_once(|_| CallbackProgression::Continue) {
                    Ok(WaitSetRunResult::TerminationRequest) | Ok(WaitSetRunResult::Interrupt) => shared.begin_drain(),
                    Ok(_) => {}
                    Err(e) => {
                        if termination_requested() {
                            shared.begin_drain();
                        } else {
                            shared.fail(format!("waitset: {e:?}"));
                        }
                    }
                }
            }
            None => {
                // Spin; after 50 µs without work, yield the core between looks (a
                // runnable engine thread or client on a busy machine gets it; on an
                // idle core a yield returns at once). Nap while the cores are
                // needed by the daemon's busy threads and a client.
                idle_spins += 1;
                if shared.leader_should_nap() {
                    std::thread::sleep(Duration::from_micros(20));
                } else if idle_spins > 512
                    && idle_since.get_or_insert_with(Instant::now).elapsed() > Duration::from_micros(50)
                {
                    std::thread::yield_now();
                } else {
                    std::hint::spin_loop();
                }
                if last_signal_check.elapsed() >= Duration::from_millis(2) {
                    last_signal_check = Instant::now();
                    if termination_requested() {
                        shared.begin_drain();
                    }
                }
            }
        }
    }
}

//! The graspd service contract: zero-copy message types, service names and
//! status codes shared by the daemon (`graspd serve`) and its clients.
//!
//! Every type here is `#[repr(C)]`, holds only integers, floats and fixed
//! arrays of them (any bit pattern is a valid value, all zeros is a valid
//! value), has no implicit padding, and carries a stable iceoryx2 type name
//! (`graspd.v4.*`) so that clients in other languages can open the same
//! services. README.md in this crate is the reference for each field, unit
//! and frame; the layout tests at the bottom pin sizes and offsets.
//! `include/graspd.h` declares the same types for C and C++;
//! `tests/c_header.rs` holds it to these definitions field by field.
//!
//! Conventions: SI units (metres, radians, seconds / nanoseconds), right-handed
//! frames, quaternions as (x, y, z, w), the frame of every pose in its field
//! name (`rotation_cloud_from_canonical_xyzw` maps canonical coordinates into
//! the cloud's frame).

use iceoryx2::prelude::ZeroCopySend;

#[cfg(feature = "json")]
pub mod json;

/// Bumped whenever a message layout or a field's meaning changes. The type
/// names carry the major version too (`graspd.v4.*`), so a client built
/// against another layout cannot even open the services.
///
/// Version 2 (2026-12-03): `MAX_LATENT` 8 → 16 (a space keeps every mode its
/// training tools give: 9 for the built-in families, worth 0.1 mm on the
/// drill's keypoints), and `Registration` carries the camera position the
/// fit used (`viewpoint_cloud_m`, `viewpoint_source`).
///
/// Version 3 (2026-12-07): `Registration` carries every verdict of the fit
/// that `graspd register --json` prints (`coverage`, `view_width_m`,
/// `latent_mahalanobis`, `contradicted_fraction`, and `table_points` of the
/// stray ones); Health names the hand Grasp solves for; each category says
/// whether Grasp serves it.
///
/// Version 4 (2026-12-07): `RequestHeader` carries a second camera's
/// position (`second_viewpoint_in_cloud_m`, flag SECOND_VIEWPOINT) for a
/// cloud that merges two cameras' views, and a `reserved` u32 that must be
/// zero (a later field can take it without a new version).
pub const PROTOCOL_VERSION: u32 = 4;

/// Service names are `<prefix>/v4/<method>`; the prefix is configurable so
/// that several daemons (or parallel tests) can share one machine.
pub const DEFAULT_PREFIX: &str = "graspd";
/// The path segment of this protocol's major version.
pub const VERSION_SEGMENT: &str = "v4";

/// Fixed-size UTF-8 name: the bytes of the string, NUL padded. A name of
/// exactly 32 bytes has no terminator.
pub type Name = [u8; 32];

pub const MAX_KEYPOINTS: usize = 8;
pub const MAX_LATENT: usize = 16;
pub const MAX_CATEGORIES: usize = 8;
pub const MAX_JOINTS: usize = 16;
pub const MAX_METHODS: usize = 8;
pub const MESSAGE_LEN: usize = 128;
pub const FRAME_TEXT_LEN: usize = 384;

/// Attribute keys the daemon sets on every request-response service.
pub mod attribute {
    /// Value: PROTOCOL_VERSION in decimal.
    pub const PROTOCOL_VERSION: &str = "graspd.protocol_version";
}

/// The methods the daemon serves. The discriminant is the index of the
/// method in [`StatsResponse::methods`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Method {
    Health = 0,
    ListCategories = 1,
    Register = 2,
    Grasp = 3,
    Stats = 4,
}

impl Method {
    pub const ALL: [Method; 5] =
        [Method::Health, Method::ListCategories, Method::Register, Method::Grasp, Method::Stats];

    pub fn name(self) -> &'static str {
        match self {
            Method::Health => "health",
            Method::ListCategories => "list_categories",
            Method::Register => "register",
            Method::Grasp => "grasp",
            Method::Stats => "stats",
        }
    }

    /// `<prefix>/v4/<method>`: the request-response service.
    pub fn service_name(self, prefix: &str) -> String {
        format!("{prefix}/{VERSION_SEGMENT}/{}", self.name())
    }

    /// `<prefix>/v4/<method>/notify`: the event service a client notifies
    /// after sending a request, so that an event-driven daemon wakes up.
    pub fn notify_service_name(self, prefix: &str) -> String {
        format!("{prefix}/{VERSION_SEGMENT}/{}/notify", self.name())
    }
}

/// `<prefix>/v4/reply/<token as 16 lower-case hex digits>`: the event service
/// a client creates (one listener: the client) and names in
/// [`RequestHeader::notify_token`]; the daemon notifies it after each response.
pub fn reply_service_name(prefix: &str, token: u64) -> String {
    format!("{prefix}/{VERSION_SEGMENT}/reply/{token:016x}")
}

/// Status of a response, with gRPC's numeric codes (u32 on the wire).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum StatusCode {
    Ok = 0,
    InvalidArgument = 3,
    DeadlineExceeded = 4,
    NotFound = 5,
    ResourceExhausted = 8,
    FailedPrecondition = 9,
    Internal = 13,
    Unavailable = 14,
}

impl StatusCode {
    pub const ALL: [StatusCode; 8] = [
        StatusCode::Ok,
        StatusCode::InvalidArgument,
        StatusCode::DeadlineExceeded,
        StatusCode::NotFound,
        StatusCode::ResourceExhausted,
        StatusCode::FailedPrecondition,
        StatusCode::Internal,
        StatusCode::Unavailable,
    ];

    /// The wire value; unknown values map to `Internal` (a newer daemon's code).
    pub fn from_u32(v: u32) -> StatusCode {
        Self::ALL.iter().copied().find(|c| *c as u32 == v).unwrap_or(StatusCode::Internal)
    }

    /// gRPC's name (`OK`, `INVALID_ARGUMENT`, ...).
    pub fn name(self) -> &'static str {
        match self {
            StatusCode::Ok => "OK",
            StatusCode::InvalidArgument => "INVALID_ARGUMENT",
            StatusCode::DeadlineExceeded => "DEADLINE_EXCEEDED",
            StatusCode::NotFound => "NOT_FOUND",
            StatusCode::ResourceExhausted => "RESOURCE_EXHAUSTED",
            StatusCode::FailedPrecondition => "FAILED_PRECONDITION",
            StatusCode::Internal => "INTERNAL",
            StatusCode::Unavailable => "UNAVAILABLE",
        }
    }
}

impl core::fmt::Display for StatusCode {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name())
    }
}

/// Values of [`RequestHeader::table_mode`] (Grasp; GIVEN also Register).
pub mod table_mode {
    /// Grasp: table plane at the height a segmentation leaking onto it
    /// shows, else at the lowest point of the cloud (its stray points set
    /// aside: see `Registration::stray_points`) or of the registered shape, when the cloud's frame is z up (`up_in_cloud` = (0,
    /// 0, 1)); no table otherwise. The registration is not told of it.
    pub const AUTO: u32 = 0;
    pub const NONE: u32 = 1;
    /// Table plane z = `table_z_m` in the cloud's frame. When that frame is z
    /// up, the tool is taken to rest on it: Register and Grasp hold the
    /// registered shape's lowest point on the plane.
    pub const GIVEN: u32 = 2;
}

/// Bits of [`GraspResponse::warnings`].
pub mod grasp_warning {
    /// The registration is not confident: the cloud may not be a tool of this category.
    pub const REGISTRATION_NOT_CONFIDENT: u32 = 1;
    /// The pre-grasp touches the scene; a larger back-off may help.
    pub const PREGRASP_IN_COLLISION: u32 = 2;
    /// table_mode AUTO but the cloud's frame is not z up: no table was used.
    pub const NO_TABLE_FRAME_NOT_Z_UP: u32 = 4;
}

/// Values of [`Registration::viewpoint_source`].
pub mod viewpoint_source {
    /// The fit used no camera position: none was given and the view did not
    /// settle one (a flat tool seen from a wide cone, a whole-surface cloud).
    pub const NONE: u32 = 0;
    /// The request's `viewpoint_in_cloud_m` (flag VIEWPOINT).
    pub const GIVEN: u32 = 1;
    /// Estimated from the view.
    pub const ESTIMATED: u32 = 2;
}

/// Values of [`HealthResponse::serving`].
pub mod serving {
    pub const SERVING: u32 = 1;
    /// Shutting down: in-flight requests finish, new ones get UNAVAILABLE.
    pub const DRAINING: u32 = 2;
}

/// Values of [`HealthResponse::waiting`].
pub mod waiting {
    pub const EVENT: u32 = 0;
    pub const POLL: u32 = 1;
}

/// Plain wire data: `#[repr(C)]`, only integers, floats and arrays of them,
/// no padding, so every byte pattern of the right length is a valid value.
///
/// # Safety
/// Implement only for types with exactly those properties.
pub unsafe trait Plain: Copy + Sized {
    /// The value's bytes, as they lie in shared memory.
    fn as_bytes(&self) -> &[u8] {
        // SAFETY: Plain types have no padding; every byte is initialised.
        unsafe { core::slice::from_raw_parts(self as *const Self as *const u8, core::mem::size_of::<Self>()) }
    }
    /// A value from exactly `size_of::<Self>()` bytes (any alignment); None for another length.
    fn from_bytes(bytes: &[u8]) -> Option<Self> {
        if bytes.len() != core::mem::size_of::<Self>() {
            return None;
        }
        // SAFETY: any byte pattern is a valid Plain value; read_unaligned copes with alignment.
        Some(unsafe { core::ptr::read_unaligned(bytes.as_ptr() as *const Self) })
    }
}

macro_rules! zeroed {
    ($($t:ty),*) => {$(
        impl $t {
            /// All fields zero (a valid value of every field).
            pub fn zeroed() -> Self {
                // SAFETY: the type is repr(C) and holds only integers, floats
                // and arrays of them, for which all-zero bytes are valid.
                unsafe { core::mem::zeroed() }
            }
        }
        impl Default for $t {
            fn default() -> Self {
                Self::zeroed()
            }
        }
        // SAFETY: repr(C), integers/floats/arrays only, no padding (sizes pinned in the tests).
        unsafe impl Plain for $t {}
    )*};
}

// SAFETY: as above.
unsafe impl Plain for Point {}
unsafe impl Plain for NoPayload {}

/// The request user header of every method (iceoryx2 "user header"), 160 bytes.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.RequestHeader")]
#[repr(C)]
pub struct RequestHeader {
    /// Chosen by the client, echoed in the response.
    pub request_id: u64,
    /// Absolute deadline, nanoseconds since the Unix epoch (CLOCK_REALTIME);
    /// 0 = none. An expired request is answered DEADLINE_EXCEEDED, not worked on.
    pub deadline_unix_ns: u64,
    /// Non-zero: the daemon notifies the event service
    /// [`reply_service_name`]`(prefix, notify_token)` after responding.
    pub notify_token: u64,
    /// Seed of the randomised parts of registration (deterministic per seed).
    pub seed: u64,
    /// Must equal [`PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// Bits of [`flags`]; unknown bits are refused (INVALID_ARGUMENT).
    pub flags: u32,
    /// Category name (Register, Grasp), e.g. "mug"; see ListCategories.
    pub category: Name,
    /// Name of the cloud's frame (free text, e.g. "camera_color_optical");
    /// echoed in responses. Points and result poses are in this frame.
    pub cloud_frame: Name,
    /// World up direction expressed in the cloud's frame (need not be unit
    /// length); all zero = unknown. (0, 0, 1) for a z-up world-frame cloud.
    pub up_in_cloud: [f32; 3],
    /// Grasp, and Register with GIVEN: one of [`table_mode`].
    pub table_mode: u32,
    /// table_mode GIVEN: table top height in the cloud's frame, metres.
    pub table_z_m: f32,
    /// Grasp: pre-grasp back-off along the palm normal, metres; 0 = daemon default.
    pub pregrasp_backoff_m: f32,
    /// Grasp: pre-grasp joints as a share of the way from the open hand to the
    /// grasp, in (0, 1]; 0 = daemon default.
    pub pregrasp_joint_fraction: f32,
    /// With flag VIEWPOINT: the camera's origin in the cloud's frame, metres
    /// ((0, 0, 0) for a cloud in the camera's frame). Model surfaces facing away
    /// from it are not expected in the view.
    pub viewpoint_in_cloud_m: [f32; 3],
    /// With flags VIEWPOINT and SECOND_VIEWPOINT: a second camera's origin in
    /// the cloud's frame, metres, when the cloud merges two cameras' views
    /// (a second look at the tool). Model surfaces facing it are expected too.
    pub second_viewpoint_in_cloud_m: [f32; 3],
    /// Must be 0 (INVALID_ARGUMENT otherwise): a later protocol may give it a
    /// meaning, which this daemon would otherwise ignore.
    pub reserved: u32,
}

/// Bits of [`RequestHeader::flags`].
pub mod flags {
    /// `viewpoint_in_cloud_m` is set.
    pub const VIEWPOINT: u32 = 1;
    /// `second_viewpoint_in_cloud_m` is set (needs VIEWPOINT).
    pub const SECOND_VIEWPOINT: u32 = 2;
    pub const ALL: u32 = VIEWPOINT | SECOND_VIEWPOINT;
}

/// One point of a cloud: (x, y, z) in metres in the request's `cloud_frame`.
/// Layout identical to `[f32; 3]` / `float[3]` (12 bytes, alignment 4).
#[derive(Clone, Copy, Debug, Default, PartialEq, ZeroCopySend)]
#[type_name("graspd.v4.Point")]
#[repr(C)]
pub struct Point(pub [f32; 3]);

impl Point {
    /// Views plain `[f32; 3]` points as wire points (same layout, no copy).
    pub fn from_arrays(points: &[[f32; 3]]) -> &[Point] {
        // SAFETY: Point is repr(C) with a single [f32; 3] field: same size,
        // alignment and validity as [f32; 3].
        unsafe { core::slice::from_raw_parts(points.as_ptr() as *const Point, points.len()) }
    }
}

/// The request payload of methods without one (Health, ListCategories, Stats).
#[derive(Clone, Copy, Debug, Default, ZeroCopySend)]
#[type_name("graspd.v4.NoPayload")]
#[repr(C)]
pub struct NoPayload {
    pub reserved: u64,
}

/// The response user header of every method, 160 bytes.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.ResponseHeader")]
#[repr(C)]
pub struct ResponseHeader {
    /// The request's `request_id`.
    pub request_id: u64,
    /// Time in the daemon from receiving the request to handing the response
    /// to the transport, nanoseconds (queueing included).
    pub server_ns: u64,
    /// Time of the engine's work (cloud conversion, validation, registration,
    /// grasp), nanoseconds; 0 when no engine work was done.
    pub compute_ns: u64,
    /// A [`StatusCode`] value. The body is meaningful only when OK (0).
    pub status: u32,
    /// The daemon's [`PROTOCOL_VERSION`].
    pub protocol_version: u32,
    /// Human-readable detail, UTF-8, NUL padded (empty when OK).
    pub message: [u8; MESSAGE_LEN],
}

/// Health response body.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.HealthResponse")]
#[repr(C)]
pub struct HealthResponse {
    pub uptime_ns: u64,
    /// Time from process start until serving, nanoseconds.
    pub startup_ns: u64,
    pub pid: u32,
    pub protocol_version: u32,
    /// One of [`serving`].
    pub serving: u32,
    /// One of [`waiting`].
    pub waiting: u32,
    /// Categories loaded (see ListCategories).
    pub categories: u32,
    /// Largest cloud accepted, points.
    pub max_points: u32,
    /// Requests one client may have in flight; more get RESOURCE_EXHAUSTED.
    pub max_in_flight_per_client: u32,
    pub workers: u32,
    /// 1 when Grasp serves at least one category (see
    /// [`CategoryInfo::grasp_available`]), 0 when Grasp answers FAILED_PRECONDITION.
    pub grasp_available: u32,
    /// Actuated joints of the hand Grasp solves for (0 when no hand loaded).
    pub hand_actuated_joints: u32,
    /// The daemon's version, e.g. "0.1.0".
    pub server_version: Name,
    /// The name of the hand Grasp solves for (its URDF robot name, e.g.
    /// "sih_right"); empty when no hand loaded.
    pub hand_name: Name,
}

/// One category the daemon serves.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.CategoryInfo")]
#[repr(C)]
pub struct CategoryInfo {
    pub name: Name,
    /// Dimension of the latent shape vector (≤ MAX_LATENT).
    pub latent_dim: u32,
    pub keypoint_count: u32,
    /// Names of the keypoints Register returns, in order.
    pub keypoint_names: [Name; MAX_KEYPOINTS],
    /// The category's canonical frame in words (UTF-8, NUL padded, may be truncated).
    pub canonical_frame: [u8; FRAME_TEXT_LEN],
    /// 1 when Grasp serves this category (the hand and its demonstration
    /// loaded), 0 when Grasp answers FAILED_PRECONDITION for it.
    pub grasp_available: u32,
    pub reserved: u32,
}

/// ListCategories response body.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.CategoriesResponse")]
#[repr(C)]
pub struct CategoriesResponse {
    pub count: u32,
    pub reserved: u32,
    pub categories: [CategoryInfo; MAX_CATEGORIES],
}

/// A named point of a registration (a transferred keypoint).
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.Keypoint")]
#[repr(C)]
pub struct Keypoint {
    pub name: Name,
    /// Position in the cloud's frame, metres.
    pub position_cloud_m: [f64; 3],
}

/// A registration of a category's shape space to a cloud.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.Registration")]
#[repr(C)]
pub struct Registration {
    /// Latent shape coordinates (first `latent_dim` used; the rest zero).
    pub latent: [f64; MAX_LATENT],
    /// Rotation of the category's canonical frame into the cloud's frame, (x, y, z, w).
    pub rotation_cloud_from_canonical_xyzw: [f64; 4],
    /// Origin of the canonical frame in the cloud's frame, metres.
    pub translation_cloud_from_canonical_m: [f64; 3],
    /// Uniform scale relative to the canonical size (p_cloud = R (s · p_canonical) + t).
    pub scale: f64,
    /// Final CPD variance, m².
    pub sigma2_m2: f64,
    /// Fraction of the (sub-sampled) cloud within `inlier_threshold_m` of the fitted shape.
    pub inlier_fraction: f64,
    /// RMS distance of the inliers to the fitted shape, metres.
    pub residual_m: f64,
    pub inlier_threshold_m: f64,
    /// The camera position the fit used, in the cloud's frame, metres: the
    /// request's `viewpoint_in_cloud_m`, or the one the daemon estimated from
    /// the view; zero when `viewpoint_source` is NONE.
    pub viewpoint_cloud_m: [f64; 3],
    /// Fraction of the completed shape's surface near a point of the cloud:
    /// how much of the tool the view shows (one camera view: 0.25-0.5; a
    /// line or a blob of points: a few percent, never confident).
    pub coverage: f64,
    /// The view's width across its longest direction, metres (a line of
    /// points has none).
    pub view_width_m: f64,
    /// How far the fitted latent lies outside the category's family, in
    /// standard deviations of the shape space's prior (√Σ ℓⱼ²/varⱼ).
    pub latent_mahalanobis: f64,
    /// Share of the fitted shape's camera-facing surface the view
    /// contradicts (where the camera saw nothing, or saw past it); −1 when
    /// not assessed (no camera position, given or estimated). Right fits of
    /// clear views: 0.00-0.06; something in front of the tool: 0.1-0.6 (see
    /// README.md).
    pub contradicted_fraction: f64,
    pub latent_dim: u32,
    pub keypoint_count: u32,
    /// 1 when the fit explains the cloud (inlier fraction ≥ 0.7) and the
    /// cloud shows enough of a tool (coverage, width and latent: see
    /// README.md), else 0.
    pub confident: u32,
    /// Points received in the request.
    pub points: u32,
    /// 1 when another pose, at least 30° away, explains the view almost as well
    /// (a mug whose handle is hidden): the orientation is not determined by this view.
    pub ambiguous_pose: u32,
    /// Points set aside before the fit, of `points`: isolated points (flying
    /// pixels, speckle, segmentation leaks), points far from the cloud's
    /// bulk, and a leaking segmentation's table (see README.md).
    pub stray_points: u32,
    /// One of [`viewpoint_source`].
    pub viewpoint_source: u32,
    /// The turns about the tool's upright axis that explain the view about
    /// as well as the reported pose reach this far either way of it,
    /// radians (a mug whose handle is hidden: ±30-60°); 0 when the view
    /// settles the turn; −1 when it was not assessed (no up direction, or
    /// a tool off its rest pose whose pose is the race's runner-up, fitted
    /// after the sweep: see README.md).
    /// The axis: the canonical axis nearest the request's up direction,
    /// through `translation_cloud_from_canonical_m` (see README.md). The arc
    /// spans turns near the reported pose only; with `ambiguous_pose` set,
    /// another pose explains the view as well even where it reads 0.
    pub yaw_half_width_rad: f32,
    /// Of `stray_points`, those set aside as the table a leaking
    /// segmentation included (0 when no up direction or table is known).
    pub table_points: u32,
    pub reserved: u32,
    /// Canonical keypoints moved through the fitted deformation and pose.
    pub keypoints: [Keypoint; MAX_KEYPOINTS],
}

/// Register response body.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.RegisterResponse")]
#[repr(C)]
pub struct RegisterResponse {
    pub registration: Registration,
}

/// A hand configuration: wrist (palm root link) pose and joint positions.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.HandConfiguration")]
#[repr(C)]
pub struct HandConfiguration {
    /// Rotation of the hand's root (palm) frame into the cloud's frame, (x, y, z, w).
    pub rotation_cloud_from_wrist_xyzw: [f64; 4],
    /// Origin of the hand's root frame in the cloud's frame, metres.
    pub translation_cloud_from_wrist_m: [f64; 3],
    /// Actuated joints, order [`GraspResponse::actuated_names`]; rad (revolute) or m (prismatic).
    pub actuated: [f64; MAX_JOINTS],
    /// Every moving joint (mimic joints expanded), order [`GraspResponse::joint_names`].
    pub joints: [f64; MAX_JOINTS],
}

/// Grasp response body: registration, grasp and pre-grasp in one round trip.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.GraspResponse")]
#[repr(C)]
pub struct GraspResponse {
    pub registration: Registration,
    pub grasp: HandConfiguration,
    pub pregrasp: HandConfiguration,
    pub actuated_names: [Name; MAX_JOINTS],
    pub joint_names: [Name; MAX_JOINTS],
    /// Task-space distance between the hand's and the transferred target keypoints, metres.
    pub task_space_distance_m: f64,
    /// Mean and largest keypoint residual of the solve, metres.
    pub residual_mean_m: f64,
    pub residual_max_m: f64,
    /// Deepest penetration of the hand into the tool or table, metres.
    pub penetration_m: f64,
    /// Smallest clearance of the pre-grasp to the scene, metres (negative: penetration).
    pub pregrasp_min_clearance_m: f64,
    /// Table plane used (cloud frame), when `table_used` = 1.
    pub table_z_m: f64,
    pub actuated_count: u32,
    pub joint_count: u32,
    pub table_used: u32,
    pub pregrasp_collision_free: u32,
    /// Bits of [`grasp_warning`].
    pub warnings: u32,
    pub reserved: u32,
}

/// Counters and latencies of one method.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.MethodStats")]
#[repr(C)]
pub struct MethodStats {
    pub name: Name,
    /// Requests answered (any status).
    pub requests: u64,
    /// Responses by status code: index = [`StatusCode`] value (0..16).
    pub by_status: [u64; 16],
    /// Requests answered later than `slow_request_ms` (each also logged).
    pub slow: u64,
    /// Server time (receipt to response) over the last `window` requests, microseconds.
    pub latency_p50_us: f64,
    pub latency_p90_us: f64,
    pub latency_p99_us: f64,
    pub latency_max_us: f64,
    /// Engine time over the same window, microseconds.
    pub compute_p50_us: f64,
    pub compute_p99_us: f64,
    /// Requests in the percentile window.
    pub window: u32,
    /// Requests received and not yet answered.
    pub in_flight: u32,
}

/// Stats response body.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[type_name("graspd.v4.StatsResponse")]
#[repr(C)]
pub struct StatsResponse {
    pub uptime_ns: u64,
    /// Resident set size of the daemon, bytes.
    pub rss_bytes: u64,
    /// Clients connected now (client ports on the Health service; the Rust SDK opens one per client).
    pub clients_connected: u64,
    /// Requests waiting for a worker.
    pub queued: u32,
    pub method_count: u32,
    /// Index = [`Method`] discriminant.
    pub methods: [MethodStats; MAX_METHODS],
}

zeroed!(
    RequestHeader,
    ResponseHeader,
    HealthResponse,
    CategoryInfo,
    CategoriesResponse,
    Keypoint,
    Registration,
    RegisterResponse,
    HandConfiguration,
    GraspResponse,
    MethodStats,
    StatsResponse
);

/// Shared-memory hygiene around an iceoryx2 0.10 weakness, used by the daemon
/// and the SDK.
///
/// A process killed between creating an iceoryx2 shared-memory object and
/// sizing it leaves an empty, write-only object in /dev/shm. Any later
/// dead-node cleanup that opens it waits for it to be initialised, forever
/// (`posix_shared_memory::Builder::open_impl` retries `MappingSizeIsZero`
/// without a timeout). Such an object is abandoned once it is older than a
/// moment (creation takes microseconds), so removing it is safe, and it
/// releases any cleanup already stuck on it.
pub mod hygiene {
    use std::os::unix::fs::PermissionsExt;
    use std::time::{Duration, SystemTime};

    /// Removes iceoryx2 objects (`iox2_*`) in /dev/shm that are empty, not
    /// yet readable (iceoryx2 grants read access once initialised) and older
    /// than `min_age`. Returns how many were removed; objects of other users
    /// that this user may not remove are skipped.
    pub fn purge_abandoned_shm(min_age: Duration) -> usize {
        let Ok(dir) = std::fs::read_dir("/dev/shm") else { return 0 };
        let now = SystemTime::now();
        let mut removed = 0;
        for entry in dir.flatten() {
            let name = entry.file_name();
            if !name.to_string_lossy().starts_with("iox2_") {
                continue;
            }
            let Ok(meta) = entry.metadata() else { continue };
            let abandoned = meta.is_file()
                && meta.len() == 0
                && meta.permissions().mode() & 0o444 == 0
                && meta.modified().ok().and_then(|m| now.duration_since(m).ok()).is_some_and(|age| age >= min_age);
            if abandoned && std::fs::remove_file(entry.path()).is_ok() {
                removed += 1;
            }
        }
        removed
    }
}

/// Errors of [`name_to_str`] / [`str_to_name`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum NameError {
    /// Longer than the field.
    TooLong { len: usize, max: usize },
    /// Not UTF-8 before the first NUL.
    NotUtf8,
    /// Non-NUL bytes after the first NUL.
    TrailingBytes,
}

impl core::fmt::Display for NameError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            NameError::TooLong { len, max } => write!(f, "{len} bytes, at most {max} fit"),
            NameError::NotUtf8 => f.write_str("not UTF-8"),
            NameError::TrailingBytes => f.write_str("bytes after the NUL terminator"),
        }
    }
}

impl std::error::Error for NameError {}

/// Reads a NUL-padded UTF-8 field strictly (garbage is an error).
pub fn name_to_str(bytes: &[u8]) -> Result<&str, NameError> {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    if bytes[end..].iter().any(|&b| b != 0) {
        return Err(NameError::TrailingBytes);
    }
    core::str::from_utf8(&bytes[..end]).map_err(|_| NameError::NotUtf8)
}

/// Reads a NUL-padded text field leniently (invalid UTF-8 replaced); for messages.
pub fn text_lossy(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

/// Writes `s` into a NUL-padded field; errors when it does not fit.
pub fn str_to_name<const N: usize>(s: &str) -> Result<[u8; N], NameError> {
    let mut out = [0u8; N];
    if s.len() > N {
        return Err(NameError::TooLong { len: s.len(), max: N });
    }
    out[..s.len()].copy_from_slice(s.as_bytes());
    Ok(out)
}

/// Writes `s` into a NUL-padded field, truncated at a character boundary to fit.
pub fn str_to_text<const N: usize>(s: &str) -> [u8; N] {
    let mut end = s.len().min(N);
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    let mut out = [0u8; N];
    out[..end].copy_from_slice(&s.as_bytes()[..end]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::mem::{align_of, offset_of, size_of};

    /// The layout README.md documents; a change here is a protocol change,
    /// and include/graspd.h changes with it (tests/c_header.rs).
    #[test]
    fn layouts_are_pinned() {
        assert_eq!((size_of::<RequestHeader>(), align_of::<RequestHeader>()), (160, 8));
        assert_eq!(offset_of!(RequestHeader, protocol_version), 32);
        assert_eq!(offset_of!(RequestHeader, category), 40);
        assert_eq!(offset_of!(RequestHeader, cloud_frame), 72);
        assert_eq!(offset_of!(RequestHeader, up_in_cloud), 104);
        assert_eq!(offset_of!(RequestHeader, table_mode), 116);
        assert_eq!(offset_of!(RequestHeader, viewpoint_in_cloud_m), 132);
        assert_eq!(offset_of!(RequestHeader, second_viewpoint_in_cloud_m), 144);
        assert_eq!(offset_of!(RequestHeader, reserved), 156);
        assert_eq!((size_of::<Point>(), align_of::<Point>()), (12, 4));
        assert_eq!(size_of::<NoPayload>(), 8);
        assert_eq!((size_of::<ResponseHeader>(), align_of::<ResponseHeader>()), (160, 8));
        assert_eq!(offset_of!(ResponseHeader, status), 24);
        assert_eq!(offset_of!(ResponseHeader, message), 32);
        assert_eq!(size_of::<HealthResponse>(), 120);
        assert_eq!(offset_of!(HealthResponse, hand_actuated_joints), 52);
        assert_eq!(offset_of!(HealthResponse, hand_name), 88);
        assert_eq!(size_of::<CategoryInfo>(), 32 + 8 + 256 + 384 + 8);
        assert_eq!(offset_of!(CategoryInfo, grasp_available), 680);
        assert_eq!(size_of::<CategoriesResponse>(), 8 + 8 * 688);
        assert_eq!(size_of::<Keypoint>(), 56);
        assert_eq!(offset_of!(Registration, rotation_cloud_from_canonical_xyzw), 128);
        assert_eq!(offset_of!(Registration, viewpoint_cloud_m), 224);
        assert_eq!(offset_of!(Registration, coverage), 248);
        assert_eq!(offset_of!(Registration, contradicted_fraction), 272);
        assert_eq!(offset_of!(Registration, latent_dim), 280);
        assert_eq!(offset_of!(Registration, viewpoint_source), 304);
        assert_eq!(offset_of!(Registration, table_points), 312);
        assert_eq!(offset_of!(Registration, keypoints), 320);
        assert_eq!(size_of::<Registration>(), 320 + 8 * 56);
        assert_eq!(size_of::<HandConfiguration>(), 312);
        assert_eq!(offset_of!(GraspResponse, grasp), 768);
        assert_eq!(offset_of!(GraspResponse, actuated_names), 768 + 624);
        assert_eq!(offset_of!(GraspResponse, task_space_distance_m), 768 + 624 + 1024);
        assert_eq!(size_of::<GraspResponse>(), 768 + 624 + 1024 + 48 + 24);
        assert_eq!(size_of::<MethodStats>(), 32 + 8 + 128 + 8 + 48 + 8);
        assert_eq!(size_of::<StatsResponse>(), 32 + 8 * 232);
    }

    #[test]
    fn names_round_trip_and_reject_garbage() {
        let n: Name = str_to_name("mug").unwrap();
        assert_eq!(name_to_str(&n).unwrap(), "mug");
        assert!(str_to_name::<4>("hammer").is_err());
        let full: [u8; 4] = str_to_name("abcd").unwrap();
        assert_eq!(name_to_str(&full).unwrap(), "abcd");
        let mut bad = n;
        bad[10] = b'x';
        assert_eq!(name_to_str(&bad), Err(NameError::TrailingBytes));
        let mut bad = [0u8; 32];
        bad[0] = 0xff;
        assert_eq!(name_to_str(&bad), Err(NameError::NotUtf8));
        let t: [u8; 5] = str_to_text("héllo");
        assert_eq!(text_lossy(&t), "héll");
    }

    #[test]
    fn abandoned_empty_write_only_iceoryx2_objects_are_purged() {
        use std::os::unix::fs::PermissionsExt;
        use std::time::{Duration, SystemTime};
        let dir = std::path::Path::new("/dev/shm");
        if !dir.is_dir() {
            return;
        }
        let make = |name: &str, mode: u32, len: u64, age_s: u64| {
            let p = dir.join(name);
            let f = std::fs::File::create(&p).unwrap();
            f.set_len(len).unwrap();
            f.set_modified(SystemTime::now() - Duration::from_secs(age_s)).unwrap();
            std::fs::set_permissions(&p, std::fs::Permissions::from_mode(mode)).unwrap();
            p
        };
        let pid = std::process::id();
        let abandoned = make(&format!("iox2_graspd_test_{pid}_abandoned"), 0o200, 0, 60);
        let young = make(&format!("iox2_graspd_test_{pid}_young"), 0o200, 0, 0);
        let live = make(&format!("iox2_graspd_test_{pid}_live"), 0o600, 0, 60);
        let sized = make(&format!("iox2_graspd_test_{pid}_sized"), 0o200, 64, 60);
        hygiene::purge_abandoned_shm(Duration::from_secs(1));
        assert!(!abandoned.exists());
        for p in [young, live, sized] {
            assert!(p.exists(), "{}", p.display());
            std::fs::remove_file(p).unwrap();
        }
    }

    #[test]
    fn status_codes_are_grpc_values() {
        assert_eq!(StatusCode::Unavailable as u32, 14);
        assert_eq!(StatusCode::from_u32(9), StatusCode::FailedPrecondition);
        assert_eq!(StatusCode::from_u32(12345), StatusCode::Internal);
        assert_eq!(Method::Register.service_name("graspd"), "graspd/v4/register");
        assert_eq!(reply_service_name("p", 255), "p/v4/reply/00000000000000ff");
    }
}

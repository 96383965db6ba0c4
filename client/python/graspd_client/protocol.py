"""The graspd.v4 wire types as ctypes structures, written from proto/README.md.

Each class mirrors one table of that file byte for byte (sizes and offsets
are checked by ``check_layouts``) and names itself to iceoryx2 with the
contract's type name, so that the services the daemon created open with
these types. Little-endian, native alignment, explicit ``reserved`` fields.
"""

import ctypes

PROTOCOL_VERSION = 4
DEFAULT_PREFIX = "graspd"
VERSION_SEGMENT = "v4"

MAX_KEYPOINTS = 8
MAX_LATENT = 16
MAX_CATEGORIES = 8
MAX_JOINTS = 16
MAX_METHODS = 8

Name = ctypes.c_uint8 * 32
Message = ctypes.c_uint8 * 128

FLAG_VIEWPOINT = 1
FLAG_SECOND_VIEWPOINT = 2

TABLE_AUTO = 0
TABLE_NONE = 1
TABLE_GIVEN = 2

VIEWPOINT_NONE = 0
VIEWPOINT_GIVEN = 1
VIEWPOINT_ESTIMATED = 2

WARNING_REGISTRATION_NOT_CONFIDENT = 1
WARNING_PREGRASP_IN_COLLISION = 2
WARNING_NO_TABLE_FRAME_NOT_Z_UP = 4

METHODS = ("health", "list_categories", "register", "grasp", "stats")


def _named(type_name):
    """Class decorator: the iceoryx2 type name of a wire type."""

    def wrap(cls):
        cls.type_name = staticmethod(lambda: type_name)
        return cls

    return wrap


@_named("graspd.v4.RequestHeader")
class RequestHeader(ctypes.Structure):
    _fields_ = [
        ("request_id", ctypes.c_uint64),
        ("deadline_unix_ns", ctypes.c_uint64),
        ("notify_token", ctypes.c_uint64),
        ("seed", ctypes.c_uint64),
        ("protocol_version", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
        ("category", Name),
        ("cloud_frame", Name),
        ("up_in_cloud", ctypes.c_float * 3),
        ("table_mode", ctypes.c_uint32),
        ("table_z_m", ctypes.c_float),
        ("pregrasp_backoff_m", ctypes.c_float),
        ("pregrasp_joint_fraction", ctypes.c_float),
        ("viewpoint_in_cloud_m", ctypes.c_float * 3),
        ("second_viewpoint_in_cloud_m", ctypes.c_float * 3),
        ("reserved", ctypes.c_uint32),
    ]


@_named("graspd.v4.Point")
class Point(ctypes.Structure):
    _fields_ = [("x", ctypes.c_float), ("y", ctypes.c_float), ("z", ctypes.c_float)]


@_named("graspd.v4.NoPayload")
class NoPayload(ctypes.Structure):
    _fields_ = [("reserved", ctypes.c_uint64)]


@_named("graspd.v4.ResponseHeader")
class ResponseHeader(ctypes.Structure):
    _fields_ = [
        ("request_id", ctypes.c_uint64),
        ("server_ns", ctypes.c_uint64),
        ("compute_ns", ctypes.c_uint64),
        ("status", ctypes.c_uint32),
        ("protocol_version", ctypes.c_uint32),
        ("message", Message),
    ]


@_named("graspd.v4.HealthResponse")
class HealthResponse(ctypes.Structure):
    _fields_ = [
        ("uptime_ns", ctypes.c_uint64),
        ("startup_ns", ctypes.c_uint64),
        ("pid", ctypes.c_uint32),
        ("protocol_version", ctypes.c_uint32),
        ("serving", ctypes.c_uint32),
        ("waiting", ctypes.c_uint32),
        ("categories", ctypes.c_uint32),
        ("max_points", ctypes.c_uint32),
        ("max_in_flight_per_client", ctypes.c_uint32),
        ("workers", ctypes.c_uint32),
        ("grasp_available", ctypes.c_uint32),
        ("hand_actuated_joints", ctypes.c_uint32),
        ("server_version", Name),
        ("hand_name", Name),
    ]


class CategoryInfo(ctypes.Structure):
    _fields_ = [
        ("name", Name),
        ("latent_dim", ctypes.c_uint32),
        ("keypoint_count", ctypes.c_uint32),
        ("keypoint_names", Name * MAX_KEYPOINTS),
        ("canonical_frame", ctypes.c_uint8 * 384),
        ("grasp_available", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
    ]


@_named("graspd.v4.CategoriesResponse")
class CategoriesResponse(ctypes.Structure):
    _fields_ = [
        ("count", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
        ("categories", CategoryInfo * MAX_CATEGORIES),
    ]


class Keypoint(ctypes.Structure):
    _fields_ = [("name", Name), ("position_cloud_m", ctypes.c_double * 3)]


@_named("graspd.v4.RegisterResponse")
class Registration(ctypes.Structure):
    _fields_ = [
        ("latent", ctypes.c_double * MAX_LATENT),
        ("rotation_cloud_from_canonical_xyzw", ctypes.c_double * 4),
        ("translation_cloud_from_canonical_m", ctypes.c_double * 3),
        ("scale", ctypes.c_double),
        ("sigma2_m2", ctypes.c_double),
        ("inlier_fraction", ctypes.c_double),
        ("residual_m", ctypes.c_double),
        ("inlier_threshold_m", ctypes.c_double),
        ("viewpoint_cloud_m", ctypes.c_double * 3),
        ("coverage", ctypes.c_double),
        ("view_width_m", ctypes.c_double),
        ("latent_mahalanobis", ctypes.c_double),
        ("contradicted_fraction", ctypes.c_double),
        ("latent_dim", ctypes.c_uint32),
        ("keypoint_count", ctypes.c_uint32),
        ("confident", ctypes.c_uint32),
        ("points", ctypes.c_uint32),
        ("ambiguous_pose", ctypes.c_uint32),
        ("stray_points", ctypes.c_uint32),
        ("viewpoint_source", ctypes.c_uint32),
        ("yaw_half_width_rad", ctypes.c_float),
        ("table_points", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
        ("keypoints", Keypoint * MAX_KEYPOINTS),
    ]


RegisterResponse = Registration


class HandConfiguration(ctypes.Structure):
    _fields_ = [
        ("rotation_cloud_from_wrist_xyzw", ctypes.c_double * 4),
        ("translation_cloud_from_wrist_m", ctypes.c_double * 3),
        ("actuated", ctypes.c_double * MAX_JOINTS),
        ("joints", ctypes.c_double * MAX_JOINTS),
    ]


@_named("graspd.v4.GraspResponse")
class GraspResponse(ctypes.Structure):
    _fields_ = [
        ("registration", Registration),
        ("grasp", HandConfiguration),
        ("pregrasp", HandConfiguration),
        ("actuated_names", Name * MAX_JOINTS),
        ("joint_names", Name * MAX_JOINTS),
        ("task_space_distance_m", ctypes.c_double),
        ("residual_mean_m", ctypes.c_double),
        ("residual_max_m", ctypes.c_double),
        ("penetration_m", ctypes.c_double),
        ("pregrasp_min_clearance_m", ctypes.c_double),
        ("table_z_m", ctypes.c_double),
        ("actuated_count", ctypes.c_uint32),
        ("joint_count", ctypes.c_uint32),
        ("table_used", ctypes.c_uint32),
        ("pregrasp_collision_free", ctypes.c_uint32),
        ("warnings", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
    ]


class MethodStats(ctypes.Structure):
    _fields_ = [
        ("name", Name),
        ("requests", ctypes.c_uint64),
        ("by_status", ctypes.c_uint64 * 16),
        ("slow", ctypes.c_uint64),
        ("latency_p50_us", ctypes.c_double),
        ("latency_p90_us", ctypes.c_double),
        ("latency_p99_us", ctypes.c_double),
        ("latency_max_us", ctypes.c_double),
        ("compute_p50_us", ctypes.c_double),
        ("compute_p99_us", ctypes.c_double),
        ("window", ctypes.c_uint32),
        ("in_flight", ctypes.c_uint32),
    ]


@_named("graspd.v4.StatsResponse")
class StatsResponse(ctypes.Structure):
    _fields_ = [
        ("uptime_ns", ctypes.c_uint64),
        ("rss_bytes", ctypes.c_uint64),
        ("clients_connected", ctypes.c_uint64),
        ("queued", ctypes.c_uint32),
        ("method_count", ctypes.c_uint32),
        ("methods", MethodStats * MAX_METHODS),
    ]


# (type, size, alignment) from proto/README.md, and field offsets where the
# tables give them: a mistake in a mirror above fails here, not on the wire.
LAYOUTS = [
    (RequestHeader, 160, 8, {"seed": 24, "category": 40, "cloud_frame": 72, "up_in_cloud": 104, "viewpoint_in_cloud_m": 132,
                             "second_viewpoint_in_cloud_m": 144, "reserved": 156}),
    (Point, 12, 4, {}),
    (NoPayload, 8, 8, {}),
    (ResponseHeader, 160, 8, {"status": 24, "message": 32}),
    (HealthResponse, 120, 8, {"grasp_available": 48, "hand_actuated_joints": 52, "server_version": 56,
                              "hand_name": 88}),
    (CategoryInfo, 688, 4, {"latent_dim": 32, "keypoint_names": 40, "canonical_frame": 296, "grasp_available": 680}),
    (CategoriesResponse, 5512, 4, {"categories": 8}),
    (Keypoint, 56, 8, {"position_cloud_m": 32}),
    (Registration, 768, 8, {"rotation_cloud_from_canonical_xyzw": 128, "scale": 184, "viewpoint_cloud_m": 224,
                            "coverage": 248, "contradicted_fraction": 272, "latent_dim": 280, "stray_points": 300,
                            "viewpoint_source": 304, "table_points": 312, "keypoints": 320}),
    (HandConfiguration, 312, 8, {"actuated": 56, "joints": 184}),
    (GraspResponse, 2488, 8, {"grasp": 768, "pregrasp": 1080, "actuated_names": 1392, "joint_names": 1904,
                              "task_space_distance_m": 2416, "table_z_m": 2456, "warnings": 2480}),
    (MethodStats, 232, 8, {"requests": 32, "slow": 168, "latency_p50_us": 176, "window": 224}),
    (StatsResponse, 1888, 8, {"methods": 32}),
]


def check_layouts():
    """Raises AssertionError naming the first type whose layout differs from the contract."""
    for cls, size, align, offsets in LAYOUTS:
        assert ctypes.sizeof(cls) == size, f"{cls.__name__}: {ctypes.sizeof(cls)} bytes, the contract says {size}"
        assert ctypes.alignment(cls) == align, f"{cls.__name__}: alignment {ctypes.alignment(cls)}, not {align}"
        for field, offset in offsets.items():
            got = getattr(cls, field).offset
            assert got == offset, f"{cls.__name__}.{field} at {got}, the contract says {offset}"


def text(field):
    """A NUL-padded UTF-8 field as str (invalid bytes replaced)."""
    raw = bytes(field)
    end = raw.find(b"\0")
    return (raw if end < 0 else raw[:end]).decode("utf-8", errors="replace")


def set_text(field, value):
    """Writes `value` into a NUL-padded field; ValueError when it does not fit."""
    data = value.encode("utf-8")
    if len(data) > len(field):
        raise ValueError(f"{value!r} is longer than {len(field)} bytes")
    ctypes.memset(ctypes.addressof(field), 0, len(field))
    ctypes.memmove(ctypes.addressof(field), data, len(data))


def service_name(prefix, method):
    return f"{prefix}/{VERSION_SEGMENT}/{method}"


def notify_name(prefix, method):
    return f"{service_name(prefix, method)}/notify"

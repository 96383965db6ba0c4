"""graspd's Python SDK: call a running ``graspd serve`` over iceoryx2 shared memory.

    import numpy as np
    from graspd_client import Client

    with Client() as c:                      # the daemon's default prefix, "graspd"
        print(c.health()["serving"])
        g = c.grasp("mug", points)           # (N, 3) float array, metres, z-up world frame
        wrist = g["grasp"]["wrist_pose"]     # {"translation": [...], "rotation_xyzw": [...]}

Written from ``proto/README.md`` alone (the contract's own claim, kept true
by the end-to-end test that compares this SDK's answers with the Rust
SDK's). Results are plain dicts in the JSON shapes of ``graspd register
--json`` and ``graspd grasp --json`` (``graspctl`` prints the same).
Failures raise :class:`GraspdError` with a gRPC-style :class:`StatusCode`.
The points are written straight into the shared-memory loan (one copy from
a NumPy array, none through Python objects).
"""

import ctypes
import enum
import itertools
import math
import os
import time

import iceoryx2 as iox2

from . import protocol as proto

__all__ = ["Client", "GraspdError", "StatusCode", "proto"]
__version__ = "0.1.0"


class StatusCode(enum.IntEnum):
    """The daemon's status codes (gRPC's values), also used for the SDK's own failures."""

    OK = 0
    INVALID_ARGUMENT = 3
    DEADLINE_EXCEEDED = 4
    NOT_FOUND = 5
    RESOURCE_EXHAUSTED = 8
    FAILED_PRECONDITION = 9
    INTERNAL = 13
    UNAVAILABLE = 14


class GraspdError(Exception):
    """A call that did not succeed: ``code`` (StatusCode) and ``message``."""

    def __init__(self, code, message):
        try:
            code = StatusCode(code)
        except ValueError:
            message = f"status {code}: {message}"
            code = StatusCode.INTERNAL
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message


_WARNINGS = [
    (proto.WARNING_REGISTRATION_NOT_CONFIDENT,
     "the registration is not confident: the cloud may not be a tool of this category"),
    (proto.WARNING_PREGRASP_IN_COLLISION, "the pre-grasp touches the scene; try a larger back-off"),
    (proto.WARNING_NO_TABLE_FRAME_NOT_Z_UP, "no table: the cloud's frame is not z up"),
]


def _config():
    """iceoryx2's defaults without the implicit dead-node cleanups (proto/README.md, calling sequence)."""
    config = iox2.config.default()
    # The nested getters hand out views into the config: set through them.
    config.global_cfg.node.cleanup_dead_nodes_on_creation = False
    config.global_cfg.node.cleanup_dead_nodes_on_destruction = False
    config.global_cfg.service.cleanup_dead_nodes_on_open = False
    return config


def _points_array(points):
    """(N, 3) float32, C-contiguous, from a NumPy array or a sequence of triples."""
    try:
        import numpy as np
    except ImportError:  # plain sequences still work
        np = None
    if np is not None:
        arr = np.ascontiguousarray(np.asarray(points, dtype=np.float32))
        if arr.size == 0:
            arr = arr.reshape(0, 3)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise GraspdError(StatusCode.INVALID_ARGUMENT, f"points of shape {arr.shape}: expected (N, 3)")
        return arr.shape[0], arr.ctypes.data, arr
    rows = list(points)
    buf = (proto.Point * len(rows))()
    for i, p in enumerate(rows):
        if len(p) != 3:
            raise GraspdError(StatusCode.INVALID_ARGUMENT, f"point {i} has {len(p)} coordinates: expected 3")
        buf[i].x, buf[i].y, buf[i].z = p
    return len(rows), ctypes.addressof(buf), buf


def _pose(rotation, translation, frame):
    return {"frame": frame, "translation": list(translation), "rotation_xyzw": list(rotation)}


def _registration(r, cloud_frame):
    keypoints = [
        {"name": proto.text(k.name), "position": list(k.position_cloud_m)}
        for k in r.keypoints[: min(r.keypoint_count, proto.MAX_KEYPOINTS)]
    ]
    return {
        "latent": list(r.latent[: min(r.latent_dim, proto.MAX_LATENT)]),
        "pose": _pose(r.rotation_cloud_from_canonical_xyzw, r.translation_cloud_from_canonical_m,
                      "cloud_from_canonical"),
        "scale": r.scale,
        "sigma2": r.sigma2_m2,
        "fit": {
            "inlier_fraction": r.inlier_fraction,
            "residual_mm": r.residual_m * 1e3,
            "inlier_mm": r.inlier_threshold_m * 1e3,
            "confident": bool(r.confident),
            "ambiguous_pose": bool(r.ambiguous_pose),
            "stray_fraction": r.stray_points / r.points if r.points else 0.0,
            "stray_points": r.stray_points,
            "table_points": r.table_points,
            "coverage": r.coverage,
            "view_width_mm": r.view_width_m * 1e3,
            "latent_mahalanobis": r.latent_mahalanobis,
            # Something in front of the tool raises it (None: not assessed); proto/README.md.
            "contradicted_fraction": r.contradicted_fraction if r.contradicted_fraction >= 0 else None,
            # The turns the view leaves open about the tool's upright axis, radians
            # (0: settled; None: not assessed); proto/README.md, `yaw_half_width_rad`.
            "yaw_half_width_rad": float(r.yaw_half_width_rad) if r.yaw_half_width_rad >= 0 else None,
        },
        "keypoints": keypoints,
        "cloud_frame": cloud_frame,
        "points": r.points,
        # As `graspd register`: the camera position assumed when none was given (None: none used).
        "estimated_viewpoint": (list(r.viewpoint_cloud_m)
                                if r.viewpoint_source == proto.VIEWPOINT_ESTIMATED else None),
    }


def _hand(h, actuated_names, joint_names):
    return {
        "wrist_pose": {"translation": list(h.translation_cloud_from_wrist_m),
                       "rotation_xyzw": list(h.rotation_cloud_from_wrist_xyzw)},
        "joints": dict(zip(joint_names, h.joints)),
        "actuated": dict(zip(actuated_names, h.actuated)),
    }


def yaw_arc(registration, up=(0.0, 0.0, 1.0)):
    """The arc of turns the view leaves open about the tool's upright axis,
    as ``graspd register --json`` reports it: ``axis_cloud``, ``half_width_rad``
    and each keypoint's ``keypoint_spread_m`` (how far it may lie from where it
    is reported: 2·r·sin(h/2), r its distance from the axis). ``up``: the
    request's up direction in the cloud's frame. None when not assessed.
    proto/README.md, ``yaw_half_width_rad``.
    """
    h = registration["fit"]["yaw_half_width_rad"]
    if h is None or up is None:
        return None
    dot = lambda a, b: sum(p * q for p, q in zip(a, b))
    n = math.sqrt(dot(up, up))
    if not (n > 0 and math.isfinite(n)):
        return None
    up = [u / n for u in up]
    x, y, z, w = registration["pose"]["rotation_xyzw"]
    columns = [
        [1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w)],
        [2 * (x * y - z * w), 1 - 2 * (x * x + z * z), 2 * (y * z + x * w)],
        [2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y)],
    ]
    columns = [[-c for c in col] if dot(col, up) < 0 else col for col in columns]
    nearest = max(columns, key=lambda col: dot(col, up))
    if dot(nearest, up) > math.cos(math.radians(10)):
        m = math.sqrt(dot(nearest, nearest))
        axis = [c / m for c in nearest]
    else:
        axis = up
    pivot = registration["pose"]["translation"]
    spread = []
    for k in registration["keypoints"]:
        d = [p - q for p, q in zip(k["position"], pivot)]
        along = dot(d, axis)
        r = math.sqrt(sum((di - along * a) ** 2 for di, a in zip(d, axis)))
        spread.append(2 * r * math.sin(min(h, math.pi) / 2))
    return {"axis_cloud": axis, "half_width_rad": h, "keypoint_spread_m": spread}


def _grasp(g, category, cloud_frame):
    actuated = [proto.text(n) for n in g.actuated_names[: min(g.actuated_count, proto.MAX_JOINTS)]]
    joints = [proto.text(n) for n in g.joint_names[: min(g.joint_count, proto.MAX_JOINTS)]]
    pregrasp = _hand(g.pregrasp, actuated, joints)
    pregrasp["collision_free"] = bool(g.pregrasp_collision_free)
    pregrasp["min_clearance_mm"] = g.pregrasp_min_clearance_m * 1e3
    registration = _registration(g.registration, cloud_frame)
    return {
        "category": category,
        "points": registration["points"],
        "registration": registration,
        "grasp": _hand(g.grasp, actuated, joints),
        "pregrasp": pregrasp,
        "task_space_distance_cm": g.task_space_distance_m * 1e2,
        "residual_mm": {"mean": g.residual_mean_m * 1e3, "max": g.residual_max_m * 1e3},
        "penetration_mm": g.penetration_m * 1e3,
        "table_z": g.table_z_m,
        "warnings": [w for bit, w in _WARNINGS if g.warnings & bit],
    }


class _Method:
    """One method's request-response client port and the notifier of its paired event service."""

    def __init__(self, node, prefix, method, request, response, slice_len):
        name = iox2.ServiceName.new(proto.service_name(prefix, method))
        builder = node.service_builder(name).request_response(request, response)
        try:
            service = builder.request_header(proto.RequestHeader).response_header(proto.ResponseHeader).open()
        except Exception as e:  # iceoryx2's open errors: absent, or other types
            text = str(e) or type(e).__name__
            if "DoesNotExist" in text:
                raise GraspdError(StatusCode.UNAVAILABLE, f"no daemon serves {proto.service_name(prefix, method)}") from e
            raise GraspdError(StatusCode.FAILED_PRECONDITION,
                              f"cannot open {proto.service_name(prefix, method)} ({text}): "
                              "the daemon speaks another protocol version?") from e
        ports = service.client_builder()
        if slice_len:
            ports = ports.initial_max_slice_len(slice_len).allocation_strategy(iox2.AllocationStrategy.PowerOfTwo)
        self.port = ports.create()
        event = node.service_builder(iox2.ServiceName.new(proto.notify_name(prefix, method))).event()
        try:
            self.notifier = event.open().notifier_builder().create()
        except Exception as e:
            raise GraspdError(StatusCode.UNAVAILABLE, f"no daemon serves {proto.notify_name(prefix, method)}") from e
        self.service = service

    def close(self):
        for obj in (self.port, self.notifier):
            try:
                obj.delete()
            except Exception:
                pass
        self.port = self.notifier = self.service = None


class Client:
    """A blocking client of one daemon (its ``service_prefix``).

    Not thread-safe: one Client per thread. ``timeout_s`` is the deadline of
    calls that take none; clouds up to ``initial_max_points`` fit the first
    shared-memory segment, larger ones grow it once; ``connect_timeout_s``:
    how long to wait for a daemon that does not serve the prefix yet.
    """

    def __init__(self, prefix=proto.DEFAULT_PREFIX, timeout_s=5.0, initial_max_points=32 * 1024, connect_timeout_s=0.0):
        proto.check_layouts()
        self.prefix = prefix
        self.timeout_s = timeout_s
        self.initial_max_points = initial_max_points
        self._node = iox2.NodeBuilder.new().config(_config()).create(iox2.ServiceType.Ipc)
        self._methods = {}
        self._ids = itertools.count(1)
        self._daemon_polls = None
        self._daemon_pid = 0
        self.last_call = {}
        # A daemon that is not serving yet (started in any order with its
        # clients) is waited for up to connect_timeout_s.
        give_up = time.monotonic() + connect_timeout_s
        while True:
            try:
                health = self.health()
                break
            except GraspdError as e:
                if e.code != StatusCode.UNAVAILABLE or time.monotonic() >= give_up:
                    self.close()
                    raise
                time.sleep(0.05)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        """Releases the ports and the node (their shared memory is removed at once,
        not left for the daemon to clean up as a dead peer's)."""
        self.close_ports()
        self._node = None

    # -- methods ------------------------------------------------------------

    def health(self):
        h = self._call("health", proto.NoPayload, proto.HealthResponse, self._header(), None, self.timeout_s)
        # The daemon's pid, for noticing its death mid-request; only where
        # this process sees it (not across PID namespaces).
        try:
            os.kill(h.pid, 0)
            self._daemon_pid = h.pid
        except PermissionError:
            self._daemon_pid = h.pid
        except (ProcessLookupError, OverflowError, ValueError):
            self._daemon_pid = 0
        self._daemon_polls = h.waiting == 1
        return {
            "serving": h.serving == 1,
            "draining": h.serving == 2,
            "waiting": "poll" if h.waiting == 1 else "event",
            "pid": h.pid,
            "protocol_version": h.protocol_version,
            "categories": h.categories,
            "max_points": h.max_points,
            "max_in_flight_per_client": h.max_in_flight_per_client,
            "workers": h.workers,
            "grasp_available": bool(h.grasp_available),
            "uptime_s": h.uptime_ns * 1e-9,
            "startup_ms": h.startup_ns * 1e-6,
            "server_version": proto.text(h.server_version),
            "hand_name": proto.text(h.hand_name) or None,
            "hand_actuated_joints": h.hand_actuated_joints,
        }

    def categories(self):
        r = self._call("list_categories", proto.NoPayload, proto.CategoriesResponse, self._header(), None,
                       self.timeout_s)
        out = []
        for c in r.categories[: min(r.count, proto.MAX_CATEGORIES)]:
            out.append({
                "name": proto.text(c.name),
                "latent_dim": c.latent_dim,
                "keypoints": [proto.text(n) for n in c.keypoint_names[: min(c.keypoint_count, proto.MAX_KEYPOINTS)]],
                "canonical_frame": proto.text(c.canonical_frame),
                "grasp_available": bool(c.grasp_available),
            })
        return out

    def stats(self):
        s = self._call("stats", proto.NoPayload, proto.StatsResponse, self._header(), None, self.timeout_s)
        methods = {}
        for m in s.methods[: min(s.method_count, proto.MAX_METHODS)]:
            methods[proto.text(m.name)] = {
                "requests": m.requests,
                "by_status": {c.name: m.by_status[c.value] for c in StatusCode if m.by_status[c.value]},
                "slow": m.slow,
                "latency_us": {"p50": m.latency_p50_us, "p90": m.latency_p90_us, "p99": m.latency_p99_us,
                               "max": m.latency_max_us},
                "compute_us": {"p50": m.compute_p50_us, "p99": m.compute_p99_us},
                "window": m.window,
                "in_flight": m.in_flight,
            }
        return {"uptime_s": s.uptime_ns * 1e-9, "rss_bytes": s.rss_bytes, "clients_connected": s.clients_connected,
                "queued": s.queued, "methods": methods}

    def register(self, category, points, *, timeout_s=30.0, table=None, **cloud):
        """Registers one segmented partial view of a tool: latent shape, pose, fit, keypoints.

        ``table``: the z of the table top the tool rests on, in the cloud's
        frame (metres; z-up clouds), when known: the registration then holds
        the tool's lowest point on it. None: not known.
        ``cloud`` options: ``cloud_frame`` (default "world"), ``up`` (world up in
        the cloud's frame, default (0, 0, 1); None = unknown), ``viewpoint`` (the
        camera's origin in the cloud's frame, None = unknown),
        ``second_viewpoint`` (with ``viewpoint``: a second camera's origin,
        when the points merge two cameras' views), ``seed`` (0).
        """
        header = self._cloud_header(category, **cloud)
        if table is not None:
            header.table_mode = proto.TABLE_GIVEN
            header.table_z_m = float(table)
        r = self._call("register", proto.Point, proto.RegisterResponse, header, points, timeout_s)
        out = _registration(r, proto.text(header.cloud_frame))
        out["category"] = category
        return out

    def grasp(self, category, points, *, timeout_s=30.0, table="auto", pregrasp_backoff_m=0.0,
              pregrasp_joint_fraction=0.0, **cloud):
        """Registration, the transferred grasp and the pre-grasp in one round trip.

        ``table``: "auto" (at the lowest point, z-up clouds), None (no table) or
        the table top's z in the cloud's frame (metres; the registration then
        also holds the tool's lowest point on it). Pre-grasp options 0 =
        the daemon's defaults. ``cloud`` options as :meth:`register`.
        """
        header = self._cloud_header(category, **cloud)
        if table == "auto":
            header.table_mode = proto.TABLE_AUTO
        elif table is None:
            header.table_mode = proto.TABLE_NONE
        else:
            header.table_mode = proto.TABLE_GIVEN
            header.table_z_m = float(table)
        header.pregrasp_backoff_m = pregrasp_backoff_m
        header.pregrasp_joint_fraction = pregrasp_joint_fraction
        g = self._call("grasp", proto.Point, proto.GraspResponse, header, points, timeout_s)
        return _grasp(g, category, proto.text(header.cloud_frame))

    # -- the calling sequence (proto/README.md) -------------------------------

    def _header(self):
        h = proto.RequestHeader()
        h.protocol_version = proto.PROTOCOL_VERSION
        return h

    def _cloud_header(self, category, cloud_frame="world", up=(0.0, 0.0, 1.0), viewpoint=None,
                      second_viewpoint=None, seed=0):
        h = self._header()
        try:
            proto.set_text(h.category, category)
            proto.set_text(h.cloud_frame, cloud_frame)
        except ValueError as e:
            raise GraspdError(StatusCode.INVALID_ARGUMENT, str(e)) from e
        h.seed = seed
        if up is not None:
            h.up_in_cloud[:] = [float(v) for v in up]
        if viewpoint is not None:
            h.flags |= proto.FLAG_VIEWPOINT
            h.viewpoint_in_cloud_m[:] = [float(v) for v in viewpoint]
        if second_viewpoint is not None:
            h.flags |= proto.FLAG_SECOND_VIEWPOINT
            h.second_viewpoint_in_cloud_m[:] = [float(v) for v in second_viewpoint]
        return h

    def _method(self, method, request, response):
        if self._node is None:
            raise GraspdError(StatusCode.FAILED_PRECONDITION, "the client is closed")
        m = self._methods.get(method)
        if m is None:
            slice_len = self.initial_max_points if request is proto.Point else 0
            payload = iox2.Slice[request] if request is proto.Point else request
            m = _Method(self._node, self.prefix, method, payload, response, slice_len)
            self._methods[method] = m
        return m

    def _call(self, method, request, response, header, points, timeout_s):
        t0 = time.perf_counter()
        deadline = t0 + timeout_s
        header.request_id = next(self._ids)
        header.deadline_unix_ns = time.time_ns() + int(timeout_s * 1e9)
        cloud = None if points is None else _points_array(points)
        while True:
            r, t_sent = self._send_and_wait(method, request, response, header, cloud, deadline, timeout_s)
            if r is not None:
                break
            # The daemon died with the request: every method is idempotent,
            # so wait for the next daemon (within the deadline) and resend.
            self._reconnect(deadline, method)
        rtt = time.perf_counter() - t_sent
        rh = ctypes.cast(r.user_header_ptr, ctypes.POINTER(proto.ResponseHeader)).contents
        if rh.request_id != header.request_id:
            raise GraspdError(StatusCode.INTERNAL, f"{method}: answer to request {rh.request_id}, "
                                                   f"expected {header.request_id}")
        self.last_call = {"rtt_us": rtt * 1e6, "server_us": rh.server_ns * 1e-3, "compute_us": rh.compute_ns * 1e-3,
                          "fill_us": (t_sent - t0) * 1e6}
        if rh.status != StatusCode.OK:
            raise GraspdError(rh.status, proto.text(rh.message))
        body = response()
        ctypes.memmove(ctypes.addressof(body), r.payload_ptr, ctypes.sizeof(response))
        r.delete()
        return body

    def _send_and_wait(self, method, request, response, header, cloud, deadline, timeout_s):
        """One send and its wait: (response, send time), or (None, _) when the daemon died meanwhile."""
        m = self._method(method, request, response)
        try:
            if cloud is None:
                req = m.port.loan_uninit()
            else:
                n, address, _keep = cloud
                try:
                    req = m.port.loan_slice_uninit(n)
                except Exception as e:
                    raise GraspdError(StatusCode.RESOURCE_EXHAUSTED,
                                      f"cannot loan {n} points of shared memory: {e}") from e
                if n:
                    ctypes.memmove(req.payload_ptr, address, n * ctypes.sizeof(proto.Point))
            ctypes.memmove(req.user_header_ptr, ctypes.addressof(header), ctypes.sizeof(header))
            req = req.assume_init()
            t_sent = time.perf_counter()
            pending = req.send()
        except GraspdError:
            raise
        except Exception as e:
            self._drop(method)
            raise GraspdError(StatusCode.UNAVAILABLE, f"{method}: send failed ({e})") from e
        if not self._daemon_polls:
            m.notifier.notify()
        spins, next_check = 0, t_sent + 0.2
        while True:
            r = pending.receive()
            if r is not None:
                return r, t_sent
            now = time.perf_counter()
            if now > deadline:
                raise GraspdError(StatusCode.DEADLINE_EXCEEDED, f"{method}: no answer within {timeout_s} s")
            spins += 1
            if spins > 2000:
                time.sleep(50e-6)
            # A daemon killed mid-request leaves the request pending for ever
            # (iceoryx2 still reports it connected): look at its process.
            if now > next_check:
                next_check = now + 0.2
                if not self._daemon_alive():
                    self.close_ports()
                    return None, t_sent

    def _daemon_alive(self):
        """False only when the daemon's process (pid from Health) is known to be gone."""
        if not self._daemon_pid:
            return True
        try:
            os.kill(self._daemon_pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            pass
        # A killed daemon its parent has not reaped yet still answers kill(0):
        # a zombie (Linux's /proc says so) is as dead as a gone one.
        try:
            with open(f"/proc/{self._daemon_pid}/stat", "rb") as f:
                state = f.read().rsplit(b")", 1)[1].split()[0]
            return state not in (b"Z", b"X")
        except (OSError, IndexError):
            return True

    def _reconnect(self, deadline, method):
        """Waits for a daemon to serve the prefix again (Health), until `deadline`."""
        while True:
            try:
                self.health()
                return
            except GraspdError as e:
                if e.code != StatusCode.UNAVAILABLE:
                    raise
            if time.perf_counter() > deadline:
                raise GraspdError(StatusCode.UNAVAILABLE, f"{method}: the daemon went away and no other came in time")
            time.sleep(0.05)

    def close_ports(self):
        """Drops every method's ports (they are reopened on the next call)."""
        for m in self._methods.values():
            m.close()
        self._methods.clear()

    def _drop(self, method):
        m = self._methods.pop(method, None)
        if m is not None:
            m.close()


def connect(prefix=os.environ.get("GRASPD_PREFIX", proto.DEFAULT_PREFIX), **kwargs):
    """A :class:`Client` of the daemon serving ``prefix`` ($GRASPD_PREFIX, else "graspd")."""
    return Client(prefix, **kwargs)

"""The Python SDK against a running daemon.

Run by the end-to-end test tests/daemon.rs (the_python_sdk_answers_as_the_rust_sdk),
which starts a daemon and writes the fixture named by $GRASPD_SDK_FIXTURE:
its service prefix, a rendered mug view (points) and what `graspd register
--json` and `graspd grasp --json` answer for that view. Without it these
tests are skipped, saying so.
"""

import json
import math
import os
import time

import numpy as np
import pytest

import graspd_client as gc
from graspd_client import protocol as proto

FIXTURE = os.environ.get("GRASPD_SDK_FIXTURE")
needs_daemon = pytest.mark.skipif(not FIXTURE, reason="no daemon fixture ($GRASPD_SDK_FIXTURE unset): run by tests/daemon.rs")


@pytest.fixture(scope="module")
def fixture():
    with open(FIXTURE) as f:
        return json.load(f)


@pytest.fixture(scope="module")
def client(fixture):
    with gc.Client(fixture["prefix"], timeout_s=30.0) as c:
        yield c


def test_the_wire_types_have_the_contracts_layout():
    proto.check_layouts()


@needs_daemon
def test_health_and_categories(client, fixture):
    h = client.health()
    assert h["serving"] and h["protocol_version"] == proto.PROTOCOL_VERSION == 4 and h["max_points"] > 0
    # The bundled hand: its URDF name and actuated joints, as `graspd hand info --json` says.
    assert h["hand_name"] == fixture["hand"]["name"] and h["hand_actuated_joints"] == len(fixture["hand"]["actuated"])
    cats = client.categories()
    assert [c["name"] for c in cats] == ["mug"]
    assert cats[0]["keypoints"] == [k["name"] for k in fixture["register"]["keypoints"]]
    assert cats[0]["latent_dim"] == len(fixture["register"]["latent"])
    assert cats[0]["grasp_available"] == h["grasp_available"] is True


@needs_daemon
def test_two_cameras_answer_as_the_cli(client, fixture):
    """A cloud merging two cameras' views, both positions given (protocol 4)."""
    points = np.array(fixture["points"], dtype=np.float32)
    first, second = fixture["cameras"]
    r = client.register("mug", points, viewpoint=first, second_viewpoint=second)
    expected = fixture["two_cameras"]
    assert r["latent"] == expected["latent"]
    assert r["keypoints"] == expected["keypoints"]
    with pytest.raises(gc.GraspdError) as e:
        client.register("mug", points, second_viewpoint=second)
    assert e.value.code == gc.StatusCode.INVALID_ARGUMENT and "needs VIEWPOINT" in str(e.value)


@needs_daemon
def test_register_answers_as_the_cli(client, fixture):
    points = np.array(fixture["points"], dtype=np.float32)
    r = client.register("mug", points)
    expected = fixture["register"]
    # The same daemon engine, cloud and seed: the same numbers, bit for bit.
    assert r["latent"] == expected["latent"]
    assert r["pose"]["rotation_xyzw"] == expected["pose"]["rotation_xyzw"]
    assert r["pose"]["translation"] == expected["pose"]["translation"]
    assert r["keypoints"] == expected["keypoints"]
    assert r["scale"] == expected["scale"]
    assert r["fit"]["confident"] == expected["fit"]["confident"]
    for key in ("stray_points", "table_points", "coverage", "latent_mahalanobis", "contradicted_fraction"):
        assert r["fit"][key] == expected["fit"][key], key
    assert math.isclose(r["fit"]["view_width_mm"], expected["fit"]["view_width_mm"], rel_tol=1e-12)
    assert r["estimated_viewpoint"] == expected["estimated_viewpoint"]
    assert abs(r["fit"]["yaw_half_width_rad"] - expected["yaw_arc"]["half_width_rad"]) < 1e-6
    arc = gc.yaw_arc(r)
    for key in ("axis_cloud", "keypoint_spread_m"):
        assert np.allclose(arc[key], expected["yaw_arc"][key], atol=1e-6), key
    assert r["points"] == len(points)
    # Plain lists of triples go the same way as an array.
    assert client.register("mug", points.tolist())["latent"] == expected["latent"]
    t = client.last_call
    assert t["rtt_us"] >= t["compute_us"] > 0


@needs_daemon
def test_register_on_a_known_table_answers_as_the_cli(client, fixture):
    # `graspd register --table-z 0`: the mug held on the table it stands on.
    r = client.register("mug", np.array(fixture["points"], dtype=np.float32), table=0.0)
    expected = fixture["on_table"]
    assert r["latent"] == expected["latent"]
    assert r["keypoints"] == expected["keypoints"]
    assert r["pose"]["translation"] == expected["pose"]["translation"]
    assert r["keypoints"] != fixture["register"]["keypoints"]


@needs_daemon
def test_grasp_answers_as_the_cli(client, fixture):
    g = client.grasp("mug", np.array(fixture["points"]))
    expected = fixture["grasp"]
    for hand in ("grasp", "pregrasp"):
        assert g[hand]["wrist_pose"] == expected[hand]["wrist_pose"], hand
        assert g[hand]["actuated"] == expected[hand]["actuated"], hand
        assert g[hand]["joints"] == expected[hand]["joints"], hand
    assert g["pregrasp"]["collision_free"] == expected["pregrasp"]["collision_free"]
    assert math.isclose(g["task_space_distance_cm"], expected["task_space_distance_cm"], rel_tol=1e-12)
    assert g["registration"]["latent"] == expected["registration"]["latent"]
    assert g["warnings"] == expected["warnings"]


@needs_daemon
def test_bad_inputs_get_their_status_and_the_daemon_keeps_serving(client, fixture):
    points = np.array(fixture["points"], dtype=np.float32)
    cases = [
        (lambda: client.register("mug", np.zeros((0, 3))), gc.StatusCode.INVALID_ARGUMENT, "empty"),
        (lambda: client.register("mug", np.full((500, 3), np.nan)), gc.StatusCode.INVALID_ARGUMENT, "finite"),
        (lambda: client.register("spoon", points), gc.StatusCode.NOT_FOUND, "spoon"),
        (lambda: client.grasp("mug", points[:, :2]), gc.StatusCode.INVALID_ARGUMENT, "(N, 3)"),
        (lambda: client.register("a" * 40, points), gc.StatusCode.INVALID_ARGUMENT, "longer than 32 bytes"),
        (lambda: client.register("mug", points, timeout_s=1e-6), gc.StatusCode.DEADLINE_EXCEEDED, ""),
    ]
    for call, code, words in cases:
        with pytest.raises(gc.GraspdError) as e:
            call()
        assert e.value.code == code, (e.value, code)
        assert words in str(e.value), (e.value, words)
    assert client.health()["serving"]
    assert client.register("mug", points)["latent"] == fixture["register"]["latent"]
    stats = client.stats()["methods"]["register"]
    assert stats["by_status"].get("NOT_FOUND", 0) >= 1 and stats["by_status"].get("INVALID_ARGUMENT", 0) >= 2


def test_a_prefix_nobody_serves_is_unavailable():
    with pytest.raises(gc.GraspdError) as e:
        gc.Client("graspd_nobody_serves_this_prefix", timeout_s=1.0)
    assert e.value.code == gc.StatusCode.UNAVAILABLE
    # Waiting for a daemon that never comes ends with the same, after the wait.
    t0 = time.monotonic()
    with pytest.raises(gc.GraspdError) as e:
        gc.Client("graspd_nobody_serves_this_prefix", connect_timeout_s=0.3)
    assert e.value.code == gc.StatusCode.UNAVAILABLE and time.monotonic() - t0 >= 0.3

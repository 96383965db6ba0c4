#!/usr/bin/env python3
"""dex-retargeting 0.5.0's position optimiser (free wrist) beside `graspd retarget`.

Same hand (our URDF, with one fixed link added per task-space keypoint so that
dex-retargeting, which targets link origins, sees our 12 keypoints), same
targets (FK of random reachable configurations from `graspd hand sample`),
one thread each. Prints per-solve times, keypoint residuals and the ratios.

Run through bench/retarget_peer.sh, which makes the venv and the inputs.
"""

import argparse
import json
import os
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")


def augmented_urdf(urdf_path, hand_info, out_dir):
    """Our URDF plus a link `kp_<name>` on a fixed joint at each keypoint."""
    tree = ET.parse(urdf_path)
    robot = tree.getroot()
    for k in hand_info["keypoints"]:
        name = f"kp_{k['name']}"
        ET.SubElement(robot, "link", {"name": name})
        j = ET.SubElement(robot, "joint", {"name": f"{name}_joint", "type": "fixed"})
        ET.SubElement(j, "origin", {"xyz": " ".join(repr(float(v)) for v in k["offset"]), "rpy": "0 0 0"})
        ET.SubElement(j, "parent", {"link": k["link"]})
        ET.SubElement(j, "child", {"link": name})
    path = os.path.join(out_dir, "sih_right_keypoints.urdf")
    tree.write(path)
    return path


def kabsch(src, dst):
    """Rigid (R, t) minimising sum |R src + t - dst|^2."""
    cs, cd = src.mean(0), dst.mean(0)
    h = (src - cs).T @ (dst - cd)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


def quat_wxyz(r):
    from pytransform3d import rotations

    return rotations.quaternion_from_matrix(r)


def stats(v):
    v = np.asarray(v, dtype=float)
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)), "mean": float(v.mean()), "max": float(v.max())}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", required=True, help="graspd hand sample --json output")
    ap.add_argument("--hand", required=True, help="graspd hand info --json output")
    ap.add_argument("--urdf", required=True)
    ap.add_argument("--ours", required=True, help="graspd retarget --json output on the same samples")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from dex_retargeting.retargeting_config import RetargetingConfig

    samples = json.load(open(a.samples))
    hand = json.load(open(a.hand))
    ours = json.load(open(a.ours))
    names = [k["name"] for k in hand["keypoints"]]
    actuated = [j["name"] for j in hand["actuated"]]
    links = [f"kp_{n}" for n in names]

    tmp = tempfile.mkdtemp(prefix="graspd-peer-")
    urdf = augmented_urdf(a.urdf, hand, tmp)
    cfg = RetargetingConfig(
        type="position",
        urdf_path=urdf,
        add_dummy_free_joint=True,
        target_joint_names=list(actuated),
        target_link_names=links,
        target_link_human_indices=np.arange(len(links)),
        low_pass_alpha=-1,  # no temporal filter: one-shot solves
    )
    retargeting = cfg.build()
    opt = retargeting.optimizer
    robot = opt.robot
    link_ids = [robot.get_link_index(n) for n in links]
    palm_id = robot.get_link_index(hand["root_link"])

    def keypoints_of(robot_qpos):
        robot.compute_forward_kinematics(robot_qpos)
        return np.stack([robot.get_link_pose(i)[:3, 3] for i in link_ids])

    # The open hand's keypoints in the palm frame (for the same rigid-fit
    # initial wrist graspd uses).
    retargeting.reset()
    q_open = np.zeros(robot.dof)
    open_vals = {j["name"]: j["open"] for j in hand["actuated"]}
    for name in robot.dof_joint_names:
        if name in open_vals:
            q_open[robot.get_joint_index(name)] = open_vals[name]
    if opt.adaptor is not None:
        q_open = opt.adaptor.forward_qpos(q_open)
    kp_open_world = keypoints_of(q_open)
    robot.compute_forward_kinematics(q_open)
    palm = robot.get_link_pose(palm_id)
    kp_open_palm = (kp_open_world - palm[:3, 3]) @ palm[:3, :3]

    results = {}
    for mode in ["reset", "rigid_fit_init"]:
        times, means, maxes = [], [], []
        for s in samples["sets"]:
            target = np.asarray(s["keypoints"], dtype=float)
            retargeting.reset()
            if mode == "rigid_fit_init":
                r, t = kabsch(kp_open_palm, target)
                retargeting.warm_start(t, quat_wxyz(r))
            t0 = time.perf_counter()
            qpos = retargeting.retarget(target.astype(np.float32))
            times.append(1e3 * (time.perf_counter() - t0))
            err = np.linalg.norm(keypoints_of(qpos) - target, axis=1) * 1e3
            means.append(err.mean())
            maxes.append(err.max())
        results[mode] = {"solve_ms": stats(times), "residual_mm": {"mean": float(np.mean(means)), "p50_of_means": float(np.median(means)), "max": float(np.max(maxes))}}

    o = ours["summary"]
    out = {
        "sets": len(samples["sets"]),
        "graspd": {"solve_ms": o["elapsed_ms"], "residual_mm": o["residual_mm"]},
        "dex_retargeting": results,
        "ratios": {
            mode: {
                "time_p50": results[mode]["solve_ms"]["p50"] / o["elapsed_ms"]["p50"],
                "residual_mean": results[mode]["residual_mm"]["mean"] / max(o["residual_mm"]["mean"], 1e-12),
            }
            for mode in results
        },
    }
    if a.json:
        print(json.dumps(out, indent=2))
        return
    print(f"{out['sets']} reachable target sets (FK of random configurations), single thread, cold solves")
    print(f"{'solver':<34} {'p50 ms':>8} {'p99 ms':>8} {'residual mean mm':>17} {'max mm':>9}")
    g = out["graspd"]
    print(f"{'graspd retarget':<34} {g['solve_ms']['p50']:>8.3f} {g['solve_ms']['p99']:>8.3f} {g['residual_mm']['mean']:>17.2e} {g['residual_mm']['max']:>9.2e}")
    for mode, r in results.items():
        label = f"dex-retargeting 0.5.0 ({mode})"
        print(f"{label:<34} {r['solve_ms']['p50']:>8.3f} {r['solve_ms']['p99']:>8.3f} {r['residual_mm']['mean']:>17.2f} {r['residual_mm']['max']:>9.2f}")
    for mode, r in out["ratios"].items():
        res = (
            f"mean residual {r['residual_mean']:.3g}x"
            if g["residual_mm"]["mean"] >= 1e-3
            else f"mean residual {results[mode]['residual_mm']['mean']:.2f} mm vs graspd's below 1 um"
        )
        print(f"ratio dex/graspd ({mode}): time p50 {r['time_p50']:.1f}x, {res}")


if __name__ == "__main__":
    sys.exit(main())

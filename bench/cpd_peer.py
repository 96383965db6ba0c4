#!/usr/bin/env python3
"""Peer benchmark for graspd's non-rigid CPD (issue 3).

Runs ONE non-rigid CPD problem through
  - pycpd 2.0.0   DeformableRegistration (pure NumPy, full rank),
  - rustcpd 4.0.0 register_deformable, full rank (low_rank=None),
  - rustcpd 4.0.0 register_deformable, low rank (rank-300 eigen factor),
  - graspd cpd    (the shipped CLI with its defaults: the kernel factor keeps
                  eigenvalues above 1e-8 of the largest, at most 1,024),
  - graspd cpd    with --max-rank R (R = --max-rank, rustcpd low-rank's rank;
                  a diagnostic row),
and prints time, speed ratio to graspd, iterations and the largest
point-wise difference of the moved source against rustcpd full rank and
against pycpd, in mm and in % of the object's size.

One convention for the parameters: graspd's. graspd maps both clouds by the
SOURCE's centroid c and RMS radius r (p -> (p - c) / r), its --beta is in
units of r and lambda/w act in those normalised coordinates. The peers take
an absolute beta on raw coordinates and do no normalisation of their own
(rustcpd's normalize= is left False), so they get the clouds already mapped
by (c, r), beta = graspd's relative beta, alpha = lambda, w = w, and their
moved clouds are mapped back to metres. Every method runs exactly --iters EM
iterations (tolerance 0).

Each peer runs in a child process capped at --timeout seconds; a run over
the cap is skipped with a note saying how many iterations it finished in
that time (from a per-iteration progress callback, which all peer runs
carry; its cost is microseconds per iteration) and a linear projection of
its full time. Timings: the peers' registration call only
(pycpd: constructor, which builds the kernel, plus register(); rustcpd: the
register_deformable call), without interpreter start and imports; graspd:
the whole `graspd cpd` process (start, reading the .npy files, kernel factor,
EM, writing the result) and, separately, graspd's own elapsed_ms, which
covers the EM loop only (not the kernel factorisation). CPU time (all threads)
is printed beside wall time: on a shared 2-core machine it is the figure that
other load inflates least. --repeats R keeps the fastest of R runs, for every
method alike.

Usage: bench/cpd_peer.sh [--sizes 1024,4096] [--json] ...  (see --help)
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MUG = os.path.join(ROOT, "assets", "tools", "mug")


# ------------------------------------------------------------------ inputs

def read_obj(path):
    """Vertices and triangles (fan-triangulated) of a Wavefront OBJ."""
    verts, tris = [], []
    with open(path) as f:
        for line in f:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                idx = []
                for tok in parts[1:]:
                    i = int(tok.split("/")[0])
                    idx.append(i - 1 if i > 0 else len(verts) + i)
                for k in range(1, len(idx) - 1):
                    tris.append([idx[0], idx[k], idx[k + 1]])
    return np.asarray(verts, float), np.asarray(tris, int)


def sample_surface(path, n, seed, oversample=12):
    """n points spread evenly over a mesh surface, deterministic in `seed`:
    area-weighted uniform samples (n * oversample), thinned to n by farthest
    point sampling (CPD follows sampling density, so even spacing matters)."""
    v, t = read_obj(path)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    k = n * oversample
    tri = rng.choice(len(t), size=k, p=area / area.sum())
    u, w = rng.random(k), rng.random(k)
    flip = u + w > 1.0
    u[flip], w[flip] = 1.0 - u[flip], 1.0 - w[flip]
    pts = a[tri] + u[:, None] * (b[tri] - a[tri]) + w[:, None] * (c[tri] - a[tri])
    chosen = np.empty(n, int)
    chosen[0] = 0
    d2 = np.sum((pts - pts[0]) ** 2, axis=1)
    for i in range(1, n):
        j = int(np.argmax(d2))
        chosen[i] = j
        d2 = np.minimum(d2, np.sum((pts - pts[j]) ** 2, axis=1))
    return pts[chosen]


def graspd_normalisation(src):
    """graspd's Normalization::of(source): centroid and RMS radius."""
    c = src.mean(axis=0)
    r = float(np.sqrt(np.mean(np.sum((src - c) ** 2, axis=1))))
    return c, r


def write_ply(path, pts):
    with open(path, "w") as f:
        f.write("ply\nformat ascii 1.0\nelement vertex %d\n" % len(pts))
        f.write("property double x\nproperty double y\nproperty double z\nend_header\n")
        for p in pts:
            f.write("%.17g %.17g %.17g\n" % tuple(p))


# ------------------------------------------------------------------ workers
# Run in a child process: `cpd_peer.py --worker NAME --src A --tgt B --out C
# --params JSON`. A and B are already in graspd's normalised coordinates; C
# gets the moved source in the same coordinates; stdout gets one JSON line.

def worker(args):
    p = json.loads(args.params)
    y = np.load(args.src)
    x = np.load(args.tgt)
    t0 = time.perf_counter()
    c0 = time.process_time()

    def progress(iteration):
        # One line per EM iteration on stderr: tells how far a run got if the cap kills it.
        sys.stderr.write("PROGRESS %d %.6f\n" % (iteration, time.perf_counter() - t0))
        sys.stderr.flush()

    if args.worker == "pycpd":
        from pycpd import DeformableRegistration
        t0, c0 = time.perf_counter(), time.process_time()
        reg = DeformableRegistration(X=x, Y=y, alpha=p["lambda"], beta=p["beta"], w=p["w"],
                                     max_iterations=p["iters"], tolerance=0.0)
        moved, _ = reg.register(callback=lambda **kw: progress(kw["iteration"]))
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        info = {"iterations": int(reg.iteration), "sigma2": float(reg.sigma2)}
    elif args.worker in ("rustcpd-full", "rustcpd-lowrank"):
        import rustcpd
        low_rank = None if args.worker == "rustcpd-full" else int(p.get("rank", p["max_rank"]))
        t0, c0 = time.perf_counter(), time.process_time()
        res = rustcpd.register_deformable(x, y, alpha=p["lambda"], beta=p["beta"], low_rank=low_rank,
                                          normalize=False, max_iterations=p["iters"], tolerance=0.0,
                                          outlier_weight=p["w"],
                                          callback=lambda st: progress(st["iteration"]))
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        moved = np.asarray(res.points)
        info = {"iterations": int(res.iterations), "sigma2": float(res.sigma2)}
    else:
        raise SystemExit("unknown worker " + args.worker)
    np.save(args.out, np.ascontiguousarray(moved, dtype=np.float64))
    info["time_s"] = dt
    info["cpu_s"] = cpu
    info["rank"] = "full" if args.worker in ("pycpd", "rustcpd-full") else low_rank
    print(json.dumps(info))


def run_peer(name, src_n, tgt_n, workdir, params, timeout):
    out = os.path.join(workdir, name + ".npy")
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", name, "--src", src_n, "--tgt", tgt_n,
           "--out", out, "--params", json.dumps(params)]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        note = "over the %.0f s cap (killed)" % timeout
        err = e.stderr.decode() if isinstance(e.stderr, bytes) else (e.stderr or "")
        done = [ln.split() for ln in err.splitlines() if ln.startswith("PROGRESS ")]
        if not done:
            return {"skipped": note + " before its first iteration ended"}
        it, t = int(done[-1][1]), float(done[-1][2])
        t1 = float(done[0][2])
        per_iter = (t - t1) / max(it - 1, 1)
        est = t + (params["iters"] - it) * per_iter
        note += ("; %d of %d iterations in %.1f s (first ended at %.1f s); about %.0f s at that pace, a rough "
                 "guide only (per-iteration cost changes with sigma; raise --timeout to measure)") % (
            it, params["iters"], t, t1, est)
        return {"skipped": note, "iterations_done": it, "estimated_time_s": est}
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["exit %d" % r.returncode]
        return {"skipped": "failed: " + tail[0][:160]}
    info = json.loads(r.stdout.strip().splitlines()[-1])
    info["moved_n"] = np.load(out)
    return info


def run_graspd(binary, src, tgt, workdir, params, max_rank, tag):
    out = os.path.join(workdir, "graspd-%s.npy" % tag)
    cmd = [binary, "cpd", "--source", src, "--target", tgt, "--beta", repr(params["beta"]),
           "--lambda", repr(params["lambda"]), "--w", repr(params["w"]), "--iters", str(params["iters"]),
           "--tol", "0", "--out", out, "--json"] + ([] if max_rank is None else ["--max-rank", str(max_rank)])
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    if r.returncode != 0:
        return {"skipped": "failed: " + (r.stderr.strip().splitlines() or ["exit %d" % r.returncode])[-1][:160]}
    rep = json.loads(r.stdout)
    return {"time_s": dt, "cpu_s": cpu, "em_s": rep["elapsed_ms"] / 1e3, "iterations": rep["iterations"],
            "sigma2": rep["sigma2"], "kernel_rank": rep.get("kernel_rank"), "rank": rep.get("kernel_rank"),
            "moved": np.load(out)}


# ------------------------------------------------------------------ bench

def max_diff(a, b):
    return float(np.max(np.linalg.norm(a - b, axis=1)))


def mean_nearest(a, b, chunk=512):
    """Mean distance from each point of a to its nearest point of b."""
    d = []
    for i in range(0, len(a), chunk):
        d2 = np.sum((a[i:i + chunk, None, :] - b[None, :, :]) ** 2, axis=2)
        d.append(np.sqrt(d2.min(axis=1)))
    return float(np.mean(np.concatenate(d)))


def bench_size(n, a, log):
    params = {"beta": a.beta, "lambda": a.lam, "w": a.w, "iters": a.iters, "max_rank": a.max_rank}
    workdir = tempfile.mkdtemp(prefix="cpd_peer_%d_" % n)
    src = sample_surface(os.path.join(MUG, a.source_obj), n, a.seed)
    tgt = sample_surface(os.path.join(MUG, a.target_obj), n, a.seed + 1)
    c, r = graspd_normalisation(src)
    size = float(np.linalg.norm(src.max(axis=0) - src.min(axis=0)))
    paths = {k: os.path.join(workdir, k) for k in ("source.npy", "target.npy", "source_n.npy", "target_n.npy")}
    np.save(paths["source.npy"], src)
    np.save(paths["target.npy"], tgt)
    np.save(paths["source_n.npy"], (src - c) / r)
    np.save(paths["target_n.npy"], (tgt - c) / r)
    write_ply(os.path.join(workdir, "source.ply"), src)
    write_ply(os.path.join(workdir, "target.ply"), tgt)
    log("[%d] inputs in %s: source %s, target %s; size (source bbox diagonal) %.1f mm; "
        "normalisation centre %s m, RMS radius %.2f mm"
        % (n, workdir, a.source_obj, a.target_obj, size * 1e3, np.round(c, 5).tolist(), r * 1e3))

    rows = []

    def best(run):
        """Best of --repeats runs (the fastest; results are deterministic)."""
        out = run()
        for _ in range(a.repeats - 1):
            if "time_s" not in out:
                break
            again = run()
            if "time_s" in again and again["time_s"] < out["time_s"]:
                out = again
        return out

    def add(name, res):
        if "moved_n" in res:
            res["moved"] = res.pop("moved_n") * r + c
        res["method"] = name
        rows.append(res)
        if "skipped" in res:
            log("[%d] %-22s skipped: %s" % (n, name, res["skipped"]))
        else:
            log("[%d] %-22s %.3f s, %d iterations" % (n, name, res["time_s"], res["iterations"]))

    add("graspd", best(lambda: run_graspd(a.graspd, paths["source.npy"], paths["target.npy"], workdir, params,
                                          None, "default")))
    # Diagnostic: graspd's kernel cut to rustcpd low-rank's rank.
    add("graspd --max-rank %d" % a.max_rank,
        best(lambda: run_graspd(a.graspd, paths["source.npy"], paths["target.npy"], workdir, params, a.max_rank,
                                "lr")))
    peers = [("rustcpd full-rank", "rustcpd-full"), ("rustcpd low-rank %d" % a.max_rank, "rustcpd-lowrank"),
             ("pycpd", "pycpd")]
    for label, name in peers:
        if name in a.skip:
            add(label, {"skipped": "not run (--skip)"})
            continue
        if name.startswith("rustcpd") and not a.have_rustcpd:
            add(label, {"skipped": "rustcpd not installed"})
            continue
        if name == "pycpd" and not a.have_pycpd:
            add(label, {"skipped": "pycpd not installed"})
            continue
        add(label, best(lambda: run_peer(name, paths["source_n.npy"], paths["target_n.npy"], workdir, params,
                                         a.timeout)))
    # Diagnostic: rustcpd with the rank graspd's kernel actually kept (its
    # eigenvalue cut-off, rank_tol 1e-6 of the largest, usually ends below
    # --max-rank): shows how much of graspd's difference is that truncation.
    k = rows[0].get("kernel_rank")
    if a.have_rustcpd and "rustcpd-lowrank" not in a.skip and k and k != a.max_rank and k < n:
        res = best(lambda: run_peer("rustcpd-lowrank", paths["source_n.npy"], paths["target_n.npy"], workdir,
                                    dict(params, rank=k), a.timeout))
        add("rustcpd low-rank %d" % k, res)

    byname = {row["method"]: row for row in rows}
    g = byname["graspd"]
    ref_rust = byname.get("rustcpd full-rank", {}).get("moved")
    ref_py = byname.get("pycpd", {}).get("moved")
    for row in rows:
        if "moved" not in row:
            continue
        row["ratio_to_graspd"] = row["time_s"] / g["time_s"] if "time_s" in g else None
        row["fit_mean_mm"] = mean_nearest(row["moved"], tgt) * 1e3
        for key, ref in (("vs_rustcpd_full", ref_rust), ("vs_pycpd", ref_py)):
            if ref is not None:
                d = max_diff(row["moved"], ref)
                row[key + "_mm"] = d * 1e3
                row[key + "_pct"] = 100.0 * d / size
    return {"points": n, "size_mm": size * 1e3, "rms_radius_mm": r * 1e3, "workdir": workdir,
            "displacement_max_mm": max_diff(src, g["moved"]) * 1e3 if "moved" in g else None, "rows": rows}


def fmt_table(res, a):
    n = res["points"]
    lines = ["", "%d x %d points, object size (source bbox diagonal) %.1f mm, source RMS radius %.1f mm, "
             "graspd moved points up to %.1f mm" % (n, n, res["size_mm"], res["rms_radius_mm"],
                                                    res["displacement_max_mm"] or float("nan"))]
    hdr = "%-22s %9s %8s %9s %7s %6s %5s %19s %19s %9s" % ("method", "time (s)", "CPU (s)", "EM (s)", "ratio", "iters",
                                                         "rank",
                                                  "diff vs rustcpd-full", "diff vs pycpd", "fit (mm)")
    lines += [hdr, "-" * len(hdr)]

    def d(row, key):
        if key + "_mm" not in row:
            return "-"
        return "%.3f mm %.3f%%" % (row[key + "_mm"], row[key + "_pct"])

    for row in res["rows"]:
        if "skipped" in row:
            lines.append("%-22s skipped: %s" % (row["method"], row["skipped"]))
            continue
        ratio = row.get("ratio_to_graspd")
        lines.append("%-22s %9.3f %8.3f %9s %6.1fx %6d %5s %19s %19s %9.3f" % (
            row["method"], row["time_s"], row["cpu_s"], ("%.3f" % row["em_s"]) if "em_s" in row else "",
            ratio if ratio is not None else float("nan"), row["iterations"], row.get("rank", ""),
            d(row, "vs_rustcpd_full"), d(row, "vs_pycpd"), row["fit_mean_mm"]))
    byname = {row["method"]: row for row in res["rows"]}
    g, rf = byname["graspd"], byname.get("rustcpd full-rank", {})
    rt = rf.get("time_s", rf.get("estimated_time_s"))
    if "time_s" in g and rt is not None:
        speed = rt / g["time_s"]
        diffs = [g[k] for k in ("vs_rustcpd_full_pct", "vs_pycpd_pct") if k in g]
        agree = "max diff %.3f%% -> result %s" % (max(diffs), "MET" if max(diffs) <= 1.0 else "NOT MET") \
            if diffs else "no peer result to compare"
        lines.append("target (graspd >= 10x faster than rustcpd full-rank, same result within 1%% of size): "
                     "%.1fx%s -> speed %s; %s" % (
                         speed, "" if "time_s" in rf else " against rustcpd's PROJECTED time",
                         ("MET" if speed >= 10 else "NOT MET") + ("" if "time_s" in rf else " (not measured)"), agree))
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1024,4096", help="points per cloud, comma-separated")
    ap.add_argument("--beta", type=float, default=0.5, help="kernel width, in units of the source's RMS radius")
    ap.add_argument("--lambda", dest="lam", type=float, default=2.0, help="smoothness weight (normalised coords)")
    ap.add_argument("--w", type=float, default=0.1, help="outlier weight")
    ap.add_argument("--iters", type=int, default=100)
    ap.add_argument("--max-rank", type=int, default=300,
                    help="rank of rustcpd low-rank and of graspd's diagnostic row (the graspd row keeps its default)")
    ap.add_argument("--timeout", type=float, default=60.0, help="cap on each peer run, seconds")
    ap.add_argument("--repeats", type=int, default=1, help="runs per method, the fastest kept (all methods alike)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--source-obj", default="mug_canonical.obj")
    ap.add_argument("--target-obj", default="mug_train_00.obj")
    ap.add_argument("--graspd", default=os.environ.get("GRASPD_BIN", os.path.join(ROOT, "target", "release", "graspd")))
    ap.add_argument("--skip", default="", help="peers not to run: pycpd,rustcpd-full,rustcpd-lowrank")
    ap.add_argument("--json", action="store_true", help="JSON summary on stdout (progress on stderr)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--src", help=argparse.SUPPRESS)
    ap.add_argument("--tgt", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--params", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        return worker(a)

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    a.skip = set(filter(None, a.skip.split(",")))
    a.have_pycpd, a.have_rustcpd = True, True
    versions = {}
    for mod in ("pycpd", "rustcpd"):
        try:
            m = __import__(mod)
            versions[mod] = getattr(m, "__version__", None)
        except Exception as e:  # noqa: BLE001 - report and go on
            log("NOTE: %s is not importable (%s); its rows are skipped" % (mod, e))
            setattr(a, "have_" + mod, False)
    if versions.get("pycpd") is None and a.have_pycpd:
        try:
            from importlib.metadata import version
            versions["pycpd"] = version("pycpd")
        except Exception:  # noqa: BLE001
            pass
    if not os.path.exists(a.graspd):
        sys.exit("graspd binary not found at %s (build it: cargo build --release -p graspd)" % a.graspd)

    machine = "%d cores (os.cpu_count), %s, load average %.2f at start" % (
        os.cpu_count() or 0, os.uname().machine, os.getloadavg()[0])
    if os.getloadavg()[0] > 0.5:
        log("WARNING: load average %.2f: other work shares the CPU, timings will be inflated" % os.getloadavg()[0])
    log("machine: " + machine + "; parameters: beta %.3g (x source RMS radius), lambda %.3g, w %.3g, %d iterations, "
        "tolerance 0, max rank %d, peer cap %.0f s, best of %d" % (a.beta, a.lam, a.w, a.iters, a.max_rank, a.timeout,
                                                                  a.repeats))
    results = [bench_size(int(s), a, log) for s in a.sizes.split(",") if s.strip()]
    machine += ", %.2f at end" % os.getloadavg()[0]

    if a.json:
        for res in results:
            for row in res["rows"]:
                row.pop("moved", None)
        print(json.dumps({"machine": machine, "versions": versions, "numpy": np.__version__,
                          "params": {"beta_relative": a.beta, "lambda": a.lam, "w": a.w, "iters": a.iters,
                                     "max_rank": a.max_rank, "timeout_s": a.timeout, "seed": a.seed, "repeats": a.repeats,
                                     "source_obj": a.source_obj, "target_obj": a.target_obj},
                          "results": results}, indent=2))
    else:
        print("CPD peer benchmark: machine %s; pycpd %s, rustcpd %s, numpy %s" % (
            machine, versions.get("pycpd") or "not installed", versions.get("rustcpd") or "not installed",
            np.__version__))
        print("non-rigid, beta %.3g x source RMS radius, lambda %.3g, w %.3g, %d iterations (tolerance 0); "
              "peers get the clouds in graspd's normalised frame" % (a.beta, a.lam, a.w, a.iters))
        print("time: wall clock of the registration call (peers) / of the whole `graspd cpd` process (graspd); "
              "CPU: CPU time of the same, all threads; EM: graspd's elapsed_ms (EM loop only); ratio: time / graspd's time; diff: largest point distance between moved sources; "
              "fit: mean distance moved source -> nearest target point")
        for res in results:
            print(fmt_table(res, a))


if __name__ == "__main__":
    main()

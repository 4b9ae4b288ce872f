#!/usr/bin/env python3
"""Reference run for depthmill's statistical outlier removal: Open3D's
PointCloud.remove_statistical_outlier(nb_neighbors=k, std_ratio=n_sigma) on the same cloud,
checked to remove exactly the same points, with both times.

Needs numpy and open3d (`python3 -m pip install open3d numpy`; open3d is a large wheel). When they
are missing the script says so and exits with status 3.

Two ways to run it:

1. From the Rust bench (what `cargo bench -p depthmill-reconstruction --bench sor` does): the bench
   writes its cloud and keep mask and calls
       python3 services/reconstruction/scripts/compare_open3d.py --cloud CLOUD.npy --keep KEEP.npy \
           --k 20 --n-sigma 2 --repeat 3
   CLOUD.npy is float64, shape (n, 3), C order; KEEP.npy is bool, shape (n,). Prints
   `open3d_ms=<best ms>`, `open3d_cpu_ms=<mean CPU ms per run, all threads>`, `open3d_kept=`, `depthmill_kept=`, `mismatches=` (points kept by one and
   removed by the other; exit status 1 when not 0).

2. On its own, from the workspace root:
       python3 services/reconstruction/scripts/compare_open3d.py [--points 1000000] [--k 20] \
           [--n-sigma 2] [--repeat 3] [--seed 7] [--manifest Cargo.toml]
   builds a scanned-like cloud with numpy (a wavy height field on a jittered 0.1 mm grid with
   10 um noise, plus 1 % outliers), runs the Rust bench binary on it in its file mode
   (`cargo bench --manifest-path M -p depthmill-reconstruction --bench sor -- --cloud IN.npy
   --keep-out OUT.npy --k K --n-sigma S --repeat R`, which prints `sor_ms=` and `sor_cpu_ms=`),
   then Open3D, and prints both wall times, the speed-up, both CPU times per run (all threads;
   the fairer figure on a busy machine) and the mismatches. From a scratch crate, pass its
   manifest with --manifest and set CARGO_TARGET_DIR as usual.

Before timing, both modes check on a small random cloud that the installed Open3D follows the rule
depthmill implements (brute force in numpy): the mean distance to the k nearest points counts the
point itself (distance 0) among the k; sigma is the sample standard deviation (ddof = 1); a point
is kept iff its mean is strictly below mean + std_ratio * sigma. Prints `semantics=ok` or exits 2.
(depthmill differs from Open3D only for points with k - 1 exact duplicates, whose mean distance is
0: Open3D drops them, depthmill keeps them; the clouds here have none.)
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time

try:
    import numpy as np
    import open3d as o3d
except ImportError as e:  # pragma: no cover - depends on the machine
    print(f"missing python module: {e.name}; install with: {sys.executable} -m pip install open3d numpy")
    sys.exit(3)

HERE = os.path.dirname(os.path.abspath(__file__))
CRATE = os.path.dirname(HERE)
WORKSPACE = os.path.dirname(os.path.dirname(CRATE))


def scan_like_cloud(n, seed):
    """A wavy height field on a jittered 0.1 mm grid plus 1 % outliers in its box widened by 5 mm."""
    rng = np.random.default_rng(seed)
    outliers = n // 100
    surface = n - outliers
    side = int(np.ceil(np.sqrt(surface)))
    r, c = np.divmod(np.arange(surface), side)
    x = (c + 0.5) * 0.1 + rng.uniform(-0.03, 0.03, surface)
    y = (r + 0.5) * 0.1 + rng.uniform(-0.03, 0.03, surface)
    z = 2.0 * np.sin(x * 0.1) * np.cos(y * 0.13) + 0.4 * np.sin(x * 0.9 + y * 0.4) + rng.normal(0.0, 0.01, surface)
    extent = side * 0.1
    o = np.column_stack([
        rng.uniform(-5.0, extent + 5.0, outliers),
        rng.uniform(-5.0, extent + 5.0, outliers),
        rng.uniform(-7.5, 7.5, outliers),
    ])
    return np.ascontiguousarray(np.vstack([np.column_stack([x, y, z]), o]), dtype=np.float64)


def open3d_keep(points, k, n_sigma):
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    _, idx = pc.remove_statistical_outlier(nb_neighbors=k, std_ratio=n_sigma)
    keep = np.zeros(len(points), dtype=bool)
    keep[np.asarray(idx, dtype=np.int64)] = True
    return keep


def check_semantics():
    """Open3D's rule against a numpy brute force on small random clouds."""
    rng = np.random.default_rng(1)
    distinguishing = 0
    for _ in range(200):
        n = int(rng.integers(5, 40))
        pts = rng.normal(0.0, 1.0, (n, 3))
        k = int(rng.integers(1, 8))
        ratio = float(rng.uniform(0.3, 2.0))
        d = np.sqrt(((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1))
        d.sort(axis=1)
        kk = min(k, n)
        mean_incl = d[:, :kk].mean(axis=1)  # the point itself included
        expected = mean_incl < mean_incl.mean() + ratio * mean_incl.std(ddof=1)
        population = mean_incl < mean_incl.mean() + ratio * mean_incl.std(ddof=0)
        excl = d[:, 1:kk + 1].mean(axis=1) if n > kk else mean_incl
        excluded = excl < excl.mean() + ratio * excl.std(ddof=1)
        got = open3d_keep(pts, k, ratio)
        if not np.array_equal(got, expected):
            print(f"semantics=mismatch (n={n}, k={k}, std_ratio={ratio:.3f}): open3d keeps {np.flatnonzero(got)}, "
                  f"the documented rule keeps {np.flatnonzero(expected)}")
            sys.exit(2)
        distinguishing += (not np.array_equal(expected, population)) or (not np.array_equal(expected, excluded))
    print(f"semantics=ok (200 clouds, {distinguishing} of them tell the rule from population sigma or self excluded)")


def time_open3d(points, k, n_sigma, repeat):
    """Best wall time (ms), mean process CPU time per run (ms, all threads) and the keep mask."""
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    best, cpu, idx = float("inf"), 0.0, None
    for _ in range(repeat):
        c, t = time.process_time(), time.perf_counter()
        _, idx = pc.remove_statistical_outlier(nb_neighbors=k, std_ratio=n_sigma)
        best = min(best, (time.perf_counter() - t) * 1e3)
        cpu += time.process_time() - c
    keep = np.zeros(len(points), dtype=bool)
    keep[np.asarray(idx, dtype=np.int64)] = True
    return best, cpu * 1e3 / repeat, keep


def compare(points, ours, k, n_sigma, repeat):
    ms, cpu_ms, theirs = time_open3d(points, k, n_sigma, repeat)
    diff = np.flatnonzero(theirs != ours)
    print(f"open3d_version={o3d.__version__}")
    print(f"open3d_ms={ms:.3f}")
    print(f"open3d_cpu_ms={cpu_ms:.0f}")
    print(f"open3d_kept={int(theirs.sum())}")
    print(f"depthmill_kept={int(ours.sum())}")
    print(f"mismatches={len(diff)}")
    if len(diff):
        print(f"first mismatched indices: {diff[:20].tolist()}")
    return ms, cpu_ms, len(diff)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cloud", help="float64 (n, 3) .npy cloud (bench mode)")
    ap.add_argument("--keep", help="bool (n,) .npy keep mask from depthmill (bench mode)")
    ap.add_argument("--k", type=int, default=20)
    ap.add_argument("--n-sigma", type=float, default=2.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--manifest", default=os.path.join(WORKSPACE, "Cargo.toml"))
    ap.add_argument("--package", default="depthmill-reconstruction")
    a = ap.parse_args()

    check_semantics()

    if a.cloud:
        points = np.load(a.cloud)
        if a.keep:
            ours = np.load(a.keep).astype(bool)
        else:
            ours = np.zeros(len(points), dtype=bool)
        _, _, mismatches = compare(points, ours, a.k, a.n_sigma, a.repeat)
        sys.exit(1 if a.keep and mismatches else 0)

    points = scan_like_cloud(a.points, a.seed)
    with tempfile.TemporaryDirectory() as tmp:
        cloud_path = os.path.join(tmp, "cloud.npy")
        keep_path = os.path.join(tmp, "keep.npy")
        np.save(cloud_path, points)
        cmd = ["cargo", "bench", "--manifest-path", a.manifest, "-p", a.package, "--bench", "sor", "--",
               "--cloud", cloud_path, "--keep-out", keep_path,
               "--k", str(a.k), "--n-sigma", str(a.n_sigma), "--repeat", str(a.repeat)]
        print("running:", " ".join(cmd), flush=True)
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        m = re.search(r"^sor_ms=([0-9.]+)", out, re.M)
        if not m:
            print(out)
            sys.exit("no sor_ms= in the bench output")
        rust_ms = float(m.group(1))
        c = re.search(r"^sor_cpu_ms=([0-9.]+)", out, re.M)
        rust_cpu = float(c.group(1)) if c else float("nan")
        ours = np.load(keep_path).astype(bool)
    print(f"depthmill_ms={rust_ms:.3f}")
    print(f"depthmill_cpu_ms={rust_cpu:.0f}")
    o3d_ms, o3d_cpu, mismatches = compare(points, ours, a.k, a.n_sigma, a.repeat)
    print(f"{len(points)} points, k={a.k}, n_sigma={a.n_sigma}: depthmill {rust_ms:.1f} ms, "
          f"open3d {o3d_ms:.1f} ms, speed-up {o3d_ms / rust_ms:.2f}x (target >= 8x); CPU per run "
          f"{rust_cpu:.0f} vs {o3d_cpu:.0f} ms ({o3d_cpu / rust_cpu:.2f}x); mismatches {mismatches}")
    sys.exit(1 if mismatches else 0)


if __name__ == "__main__":
    main()

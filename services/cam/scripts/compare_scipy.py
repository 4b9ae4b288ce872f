#!/usr/bin/env python3
"""Compare depthmill's `compensate` with scipy.ndimage.grey_dilation on the same map.

Needs numpy and scipy; installs them with `pip install numpy scipy` when missing.

Writes a seeded smooth random relief (2000 x 2000 cells at 0.1 mm, Gaussian bumps over a wave),
runs the Rust bench binary in --map mode (`cargo bench -p depthmill-cam --bench compensate --
--map IN.npy --out OUT.npy --tool ball-6 --model point --floor Z`; cargo bench builds in release),
then scipy's grey_dilation with the identical structuring element, and checks that the results agree
to 1e-4 mm. Prints both times (the Rust time excludes I/O and is the one the binary reports) and the
ratio.

Structuring element (point model, ball of radius r = 3 mm at p = 0.1 mm, cell offsets i, j):
    d(i, j)         = p sqrt(i^2 + j^2)           (f64, as depthmill's kernel() computes it)
    footprint(i, j) = d <= r
    B(i, j)         = r - sqrt(r^2 - d^2)          (rounded to f32 like the kernel)
    C = grey_dilation(A, footprint=footprint, structure=-B, mode='constant', cval=floor)
grey_dilation reflects the structuring element (it computes max A(x - i) + s(i)); B is symmetric
under (i, j) -> (-i, -j), so the reflection does not change the result here.

Usage: python3 scripts/compare_scipy.py [--size 2000] [--seed 7] [--manifest PATH] [--package NAME]
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time


def ensure(modules):
    try:
        for m in modules:
            __import__(m)
    except ImportError:
        print("installing numpy and scipy (pip install numpy scipy)", flush=True)
        subprocess.check_call([sys.executable, "-m", "pip", "install", "--quiet", "numpy", "scipy"])


ensure(["numpy", "scipy"])
import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
CAM = os.path.dirname(HERE)


def relief(n, seed):
    rng = np.random.default_rng(seed)
    x = (np.arange(n) + 0.5) / n
    X, Y = np.meshgrid(x, x)
    z = 2.0 + 1.5 * np.sin(9.0 * X) * np.cos(7.0 * Y)
    for _ in range(24):
        bx, by, s, a = rng.random(), rng.random(), 0.03 + 0.15 * rng.random(), 2.0 + 10.0 * rng.random()
        z += a * np.exp(-((X - bx) ** 2 + (Y - by) ** 2) / (s * s))
    return z.astype(np.float32)


def ball_element(radius_mm, pixel_mm):
    half = int(np.floor(radius_mm / pixel_mm))
    i = np.arange(-half, half + 1)
    I, J = np.meshgrid(i, i, indexing="ij")
    # The same f64 arithmetic as depthmill's kernel(): d = p * sqrt(i^2 + j^2), in the footprint when d <= r.
    d = pixel_mm * np.sqrt((I ** 2 + J ** 2).astype(np.float64))
    footprint = d <= radius_mm
    b = (radius_mm - np.sqrt(np.maximum(radius_mm * radius_mm - d * d, 0.0))).astype(np.float32)
    return footprint, np.where(footprint, b, 0.0)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--manifest", default=os.path.join(CAM, "Cargo.toml"))
    ap.add_argument("--package", default="depthmill-cam")
    args = ap.parse_args()

    pixel, radius, floor = 0.1, 3.0, 0.0
    a = relief(args.size, args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = os.path.join(tmp, "a.npy"), os.path.join(tmp, "c.npy")
        np.save(src, a)
        cmd = ["cargo", "bench", "--manifest-path", args.manifest, "-p", args.package, "--bench", "compensate",
               "--", "--map", src, "--out", dst, "--tool", "ball-6", "--model", "point", "--floor", str(floor)]
        print("$ " + " ".join(cmd), flush=True)
        run = subprocess.run(cmd, capture_output=True, text=True)
        if run.returncode != 0:
            sys.exit(f"cargo bench failed:\n{run.stderr[-4000:]}")
        m = re.search(r"^compensate_ms=([0-9.]+)$", run.stdout, re.M)
        if not m:
            sys.exit(f"no compensate_ms line in:\n{run.stdout}")
        rust_ms = float(m.group(1))
        c_rust = np.load(dst).astype(np.float64)

    footprint, b = ball_element(radius, pixel)
    t = time.perf_counter()
    c_scipy = ndimage.grey_dilation(a, footprint=footprint, structure=-b, mode="constant",
                                    cval=floor)
    scipy_ms = (time.perf_counter() - t) * 1e3

    diff = float(np.max(np.abs(c_rust - c_scipy.astype(np.float64))))
    print(f"map {args.size}x{args.size} at {pixel} mm, ball-6 (footprint {footprint.shape[0]}x{footprint.shape[1]}, "
          f"{int(footprint.sum())} cells), point model, floor {floor}")
    print(f"rust compensate: {rust_ms:.1f} ms")
    print(f"scipy grey_dilation: {scipy_ms:.1f} ms")
    print(f"speed-up: x{scipy_ms / rust_ms:.1f}")
    print(f"max |difference|: {diff:.3e} mm")
    if diff > 1e-4:
        sys.exit("FAIL: results differ by more than 1e-4 mm")
    print("OK: results agree within 1e-4 mm")


if __name__ == "__main__":
    main()

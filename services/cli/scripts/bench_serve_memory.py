#!/usr/bin/env python3
"""Peak resident memory of `depthmill serve` while a large point-cloud job runs.

Writes a binary little-endian PLY of N points (float32 x y z; default 10^7: a 100 x 80 mm relief
sampled like a line scanner's output, 0.02 mm noise), starts `depthmill serve` (release build) on a
fresh data directory, submits the cloud (`depthmill submit`, so the job runs reconstruct, plan,
execute and report), waits for it, and reads the server's peak resident set (`VmHWM` in
/proc/PID/status) before the submission (the idle stack) and after the job. Prints the cloud's size
on disk, both peaks and their ratios to it (target: peak <= 2x the cloud's size).

Usage: python3 services/cli/scripts/bench_serve_memory.py [--points N] [--keep] [--bin PATH]
Needs numpy (`pip install numpy`). Builds `target/release/depthmill` first, unless `--bin` names
the binary to measure (another build, to compare two on the same cloud).
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request

import numpy as np

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
BIN = os.path.join(ROOT, "target", "release", "depthmill")


def write_cloud(path, n):
    # 100 x 80 mm (within the EMCO F1's 200 x 100 mm travel), rows along X.
    cols = int(np.ceil(np.sqrt(n * 100.0 / 80.0)))
    pitch = 100.0 / cols
    rng = np.random.default_rng(7)
    with open(path, "wb") as f:
        header = (
            "ply\nformat binary_little_endian 1.0\ncomment depthmill serve-memory benchmark\n"
            f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        )
        f.write(header.encode())
        chunk = 1 << 20
        for start in range(0, n, chunk):
            i = np.arange(start, min(n, start + chunk))
            x = (i % cols) * pitch
            y = (i // cols) * pitch
            z = (
                10.0
                + 4.0 * np.sin(x / 17.0) * np.cos(y / 23.0)
                + 1.5 * np.sin((x + y) / 7.0)
                + rng.normal(0.0, 0.02, i.size)
            )
            xyz = np.stack([x, y, z], axis=1).astype("<f4")
            f.write(xyz.tobytes())


def vm(pid, key):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    return 0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=10_000_000)
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    ap.add_argument("--bin", help="the depthmill binary to measure (default: build target/release/depthmill)")
    a = ap.parse_args()
    global BIN
    if a.bin:
        BIN = os.path.abspath(a.bin)
    else:
        subprocess.run(["cargo", "build", "--release", "--bin", "depthmill"], cwd=ROOT, check=True)
    tmp = tempfile.mkdtemp(prefix="depthmill-serve-memory-")
    try:
        cloud = os.path.join(tmp, "cloud.ply")
        t = time.time()
        write_cloud(cloud, a.points)
        size = os.path.getsize(cloud)
        print(f"cloud: {a.points} points, {size / 2**20:.1f} MiB on disk (written in {time.time() - t:.1f} s)")
        data = os.path.join(tmp, "data")
        server = subprocess.Popen(
            [BIN, "serve", "--rest-addr", "127.0.0.1:0", "--data-dir", data],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        url = None
        for line in server.stdout:
            m = re.search(r"REST listening on (http://\S+)", line)
            if m:
                url = m.group(1)
                break
        if url is None:
            sys.exit("serve did not print its address")
        env = dict(os.environ, DEPTHMILL_URL=url)
        time.sleep(1.0)
        idle = vm(server.pid, "VmHWM")
        t = time.time()
        out = subprocess.run([BIN, "submit", cloud], capture_output=True, text=True, env=env)
        if out.returncode != 0:
            sys.exit(f"submit failed: {out.stderr.strip()}")
        job = out.stdout.strip().split()[-1]
        # Resident set every 50 ms, by the stage the job is in (GET /v1/jobs/{id}).
        per_stage = {}
        stage, ok, polled = "submitted", False, 0.0
        while True:
            now = time.time()
            if now - polled > 0.2:
                polled = now
                with urllib.request.urlopen(f"{url}/v1/jobs/{job}") as r:
                    j = json.load(r)
                stage = j.get("stage") or j.get("status")
                if j.get("status") in ("succeeded", "failed", "cancelled"):
                    ok = j.get("status") == "succeeded"
                    break
            rss = vm(server.pid, "VmRSS")
            per_stage[stage] = max(per_stage.get(stage, 0), rss)
            time.sleep(0.05)
        wall = time.time() - t
        peak = vm(server.pid, "VmHWM")
        status = subprocess.run([BIN, "status", job], capture_output=True, text=True, env=env).stdout
        server.terminate()
        server.wait(timeout=30)
        print(f"job {job}: {'succeeded' if ok else 'FAILED'} in {wall:.1f} s")
        print(status.strip())
        print("largest resident set seen (50 ms samples) while the job was in each stage:")
        for k, v in per_stage.items():
            print(f"  {k:12} {v / 2**20:8.1f} MiB ({v / size:.2f}x the cloud)")
        print(f"serve peak RSS idle (before the job): {idle / 2**20:.1f} MiB ({idle / size:.2f}x the cloud)")
        print(
            f"serve peak RSS with the job:          {peak / 2**20:.1f} MiB ({peak / size:.2f}x the cloud); "
            f"target <= 2x: {'MET' if peak <= 2 * size else 'NOT MET'}"
        )
    finally:
        if a.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()

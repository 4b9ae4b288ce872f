#!/usr/bin/env python3
"""Slicing against trimesh's `section_multiplane` on the same 10^6-triangle STL and heights.

Runs `cargo bench -p depthmill-cam --bench slice -- --out DIR` (our figure, best of 3, and our
contours), then in this process loads DIR/mesh.stl with trimesh, times `section_multiplane` over
the same 200 heights (best of 3, the load not counted), and compares the contours: per layer the
number of closed loops, and every vertex of ours within 1e-6 mm of a vertex of trimesh's and back
(nearest neighbours, scipy's cKDTree). Prints both times and the ratio (target >= 10x).

Usage: python3 services/cam/scripts/compare_trimesh.py
Needs `pip install trimesh numpy scipy networkx shapely`.
"""

import json
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np
import trimesh
from scipy.spatial import cKDTree

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))


def worst_distance(mine, theirs):
    """Largest nearest-neighbour distance either way between two point sets (inf if one is empty)."""
    a = np.concatenate([np.asarray(c) for c in mine]) if mine else np.zeros((0, 2))
    b = np.concatenate(theirs) if theirs else np.zeros((0, 2))
    if len(a) and len(b):
        return max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max())
    return 0.0 if len(a) == len(b) else float("inf")


def main():
    tmp = tempfile.mkdtemp(prefix="depthmill-slice-")
    out = subprocess.run(
        ["cargo", "bench", "-p", "depthmill-cam", "--bench", "slice", "--", "--out", tmp, "--no-reference"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    if out.returncode != 0:
        sys.exit(out.stderr[-2000:])
    print(out.stdout.strip())
    ours_s = float(re.search(r"slice: ([0-9.]+) s", out.stdout).group(1))
    levels = np.loadtxt(os.path.join(tmp, "levels.txt"))
    with open(os.path.join(tmp, "ours.json")) as f:
        ours = json.load(f)
    mesh = trimesh.load(os.path.join(tmp, "mesh.stl"))
    print(f"trimesh {trimesh.__version__}: {len(mesh.faces)} faces, {len(mesh.vertices)} vertices")
    best = float("inf")
    sections = None
    for _ in range(3):
        t = time.time()
        sections = mesh.section_multiplane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], levels)
        best = min(best, time.time() - t)
    print(f"trimesh section_multiplane: {best:.3f} s (best of 3)")
    print(f"ratio: {best / ours_s:.1f}x trimesh (target >= 10x)")

    worst = 0.0
    loops_differ = 0
    for path, mine in zip(sections, ours):
        theirs = []
        if path is not None:
            to3d = path.metadata["to_3D"]
            for d in path.discrete:
                h = np.column_stack([d, np.zeros(len(d)), np.ones(len(d))])
                theirs.append((h @ to3d.T)[:, :2])
        if len(theirs) != len(mine):
            loops_differ += 1
        worst = max(worst, worst_distance(mine, theirs))
    print(
        f"contours: {sum(len(m) for m in ours)} closed loops ours; layers whose loop count differs: {loops_differ}; "
        f"largest vertex distance either way to section_multiplane's paths: {worst:.2e} mm"
    )
    # section_multiplane's paths merge vertices closer than trimesh's merge tolerance; its raw
    # segments (mesh_multiplane, the same intersection without the path building) are compared
    # exactly as well.
    t = time.time()
    lines, _, _ = trimesh.intersections.mesh_multiplane(mesh, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], levels)
    raw_s = time.time() - t
    worst_raw = 0.0
    for seg, mine in zip(lines, ours):
        worst_raw = max(worst_raw, worst_distance(mine, [np.asarray(seg).reshape(-1, 2)]))
    print(
        f"raw segments (mesh_multiplane, {raw_s:.3f} s, {raw_s / ours_s:.1f}x ours): largest vertex distance either way "
        f"{worst_raw:.2e} mm (target <= 1e-6): {'SAME' if worst_raw <= 1e-6 and loops_differ == 0 else 'DIFFERENT'}"
    )


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Reference runs for depthmill's radius outlier removal and voxel decimation: Open3D's
PointCloud.remove_radius_outlier(nb_points, radius) and PointCloud.voxel_down_sample(voxel_size)
on the cloud the bench wrote, with times and checks. Called by
`cargo bench -p depthmill-reconstruction --bench filters`:

    python3 services/reconstruction/scripts/compare_open3d_filters.py --cloud CLOUD.npy \
        --ror-keep KEEP.npy --radius-mm 0.25 --min-neighbours 8 --voxel-mm 0.5 \
        --depthmill-voxels N --repeat 3

CLOUD.npy is float64 (n, 3); KEEP.npy is depthmill's radius keep mask, bool (n,). Prints
`open3d_ror_ms=`, `open3d_ror_cpu_ms=`, `ror_mismatches=` (points kept by one tool and removed
by the other; depthmill keeps a point with at least min_neighbours other points strictly within
the radius, and so does Open3D with nb_points = min_neighbours: it keeps a point whose radius
search, which finds the point itself, returns more than nb_points),
`open3d_voxel_ms=`, `open3d_voxel_cpu_ms=`, `open3d_voxels=`, and each tool's voxel count against
numpy's count under that tool's rule (`depthmill_voxels_expected=`, `open3d_voxels_expected=`).
Exit status 1 when the radius masks differ or a voxel count is not its rule's; 3 when numpy or
open3d is missing (`python3 -m pip install open3d numpy`).
"""

import argparse
import sys
import time

try:
    import numpy as np
    import open3d as o3d
except ImportError as e:  # pragma: no cover - depends on the machine
    print(f"missing python module: {e.name}; install with: {sys.executable} -m pip install open3d numpy")
    sys.exit(3)


def timed(repeat, run):
    """Best wall time (ms), mean process CPU time per run (ms, all threads), last result."""
    best, cpu, out = float("inf"), 0.0, None
    for _ in range(repeat):
        c, t = time.process_time(), time.perf_counter()
        out = run()
        best = min(best, (time.perf_counter() - t) * 1e3)
        cpu += time.process_time() - c
    return best, cpu * 1e3 / repeat, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cloud", required=True)
    ap.add_argument("--ror-keep", required=True)
    ap.add_argument("--radius-mm", type=float, required=True)
    ap.add_argument("--min-neighbours", type=int, required=True)
    ap.add_argument("--voxel-mm", type=float, required=True)
    ap.add_argument("--depthmill-voxels", type=int, required=True)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    points = np.load(a.cloud)
    ours = np.load(a.ror_keep)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    print(f"open3d_version={o3d.__version__}")
    status = 0

    ms, cpu, (_, idx) = timed(a.repeat, lambda: pc.remove_radius_outlier(nb_points=a.min_neighbours,
                                                                         radius=a.radius_mm))
    theirs = np.zeros(len(points), dtype=bool)
    theirs[np.asarray(idx, dtype=np.int64)] = True
    mismatches = int(np.count_nonzero(theirs != ours))
    print(f"open3d_ror_ms={ms:.3f}")
    print(f"open3d_ror_cpu_ms={cpu:.0f}")
    print(f"open3d_ror_kept={int(theirs.sum())}")
    print(f"depthmill_ror_kept={int(ours.sum())}")
    print(f"ror_mismatches={mismatches}")
    status |= mismatches != 0

    ms, cpu, down = timed(a.repeat, lambda: pc.voxel_down_sample(a.voxel_mm))
    v = a.voxel_mm
    ours_expected = len(np.unique(np.floor(points / v).astype(np.int64), axis=0))
    lo = points.min(axis=0) - 0.5 * v
    theirs_expected = len(np.unique(np.floor((points - lo) / v).astype(np.int64), axis=0))
    print(f"open3d_voxel_ms={ms:.3f}")
    print(f"open3d_voxel_cpu_ms={cpu:.0f}")
    print(f"open3d_voxels={len(down.points)}")
    print(f"open3d_voxels_expected={theirs_expected}")
    print(f"depthmill_voxels={a.depthmill_voxels}")
    print(f"depthmill_voxels_expected={ours_expected}")
    status |= len(down.points) != theirs_expected or a.depthmill_voxels != ours_expected
    sys.exit(1 if status else 0)


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Reference run for depthmill's point-to-plane ICP: Open3D's registration_icp on the same clouds.

Called by `cargo bench -p depthmill-geometry --bench icp` with
    python3 services/geometry/scripts/compare_open3d_icp.py --source S.npy --target T.npy \
        --max-corr 2.0 --tukey 0.1 --normal-k 20 --max-iter 30 --repeat 3
S.npy and T.npy are float64, shape (n, 3). Estimates the target's normals (KNN, k = normal-k),
then runs registration_icp from the identity with TransformationEstimationPointToPlane(TukeyLoss(k))
and ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration). Prints
`normals_ms=` and `icp_ms=` (best of --repeat), `fitness=`, `inlier_rmse=` and `transform=` (16
numbers, row major). Needs numpy and open3d (`python3 -m pip install open3d numpy`); exits with
status 3 when they are missing.
"""

import argparse
import sys
import time


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--source", required=True)
    ap.add_argument("--target", required=True)
    ap.add_argument("--max-corr", type=float, default=2.0)
    ap.add_argument("--tukey", type=float, default=0.1)
    ap.add_argument("--normal-k", type=int, default=20)
    ap.add_argument("--max-iter", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    try:
        import numpy as np
        import open3d as o3d
    except ImportError as e:
        print(f"missing: {e}; python3 -m pip install open3d numpy", file=sys.stderr)
        sys.exit(3)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.load(a.source)))
    tgt_pts = np.load(a.target)
    best_n = best_i = float("inf")
    result = None
    for _ in range(a.repeat):
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt_pts))
        t0 = time.perf_counter()
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=a.normal_k))
        t1 = time.perf_counter()
        est = o3d.pipelines.registration.TransformationEstimationPointToPlane(
            o3d.pipelines.registration.TukeyLoss(k=a.tukey))
        crit = o3d.pipelines.registration.ICPConvergenceCriteria(
            relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=a.max_iter)
        t2 = time.perf_counter()
        result = o3d.pipelines.registration.registration_icp(src, tgt, a.max_corr, np.identity(4), est, crit)
        t3 = time.perf_counter()
        best_n = min(best_n, (t1 - t0) * 1e3)
        best_i = min(best_i, (t3 - t2) * 1e3)
    print(f"normals_ms={best_n:.3f}")
    print(f"icp_ms={best_i:.3f}")
    print(f"fitness={result.fitness:.9f}")
    print(f"inlier_rmse={result.inlier_rmse:.9f}")
    print("transform=" + ",".join(f"{v:.15e}" for v in np.asarray(result.transformation).ravel()))


if __name__ == "__main__":
    main()

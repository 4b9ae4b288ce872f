//! The table a scanned part stood on, found in the cloud and made the XY plane
//! (`reconstruct.filters.table`): a range scan taken in the sensor's own frame, of a part on a
//! table among whatever else the sensor saw, comes out standing on `z = 0` with the table and
//! everything under it gone and, by default, only the largest group of points above it kept (the
//! part; a cable, a clamp or a far wall are smaller or apart from it).
//!
//! 1. **The plane**: RANSAC (planes through three random points, scored by the points within
//!    `tolerance_mm` among up to [`SCORE_SAMPLES`] of the cloud, [`ITERATIONS`] tries from a fixed
//!    seed, so a cloud always gives the same plane), then refined twice by a least-squares fit to
//!    its points within the tolerance (the covariance's smallest eigenvector).
//! 2. **Up**: the side of the plane more of the other points lie on (a scan from above sees the
//!    part on the table, not the table's underside).
//! 3. **The turn**: the shortest rotation taking that side's normal to `+Z`, and the plane to
//!    `z = 0`; points at or under `tolerance_mm` go (the table, and what lies under it).
//! 4. **Groups**: the points left, on a grid of `gap_mm` cells, joined when their cells touch (26
//!    neighbours): points less than `gap_mm` apart always share a group, points more than twice
//!    that apart never touch directly.

use std::collections::HashMap;

use depthmill_geometry::{CloudPoint, PointCloud};
use nalgebra::{Isometry3, Matrix3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::Serialize;

use crate::domain::error::{ReconError, Result};

/// Planes tried.
pub const ITERATIONS: usize = 400;
/// Most points a candidate plane is scored on.
pub const SCORE_SAMPLES: usize = 20_000;
/// Default distance from the plane within which a point is the table's, mm.
pub const DEFAULT_TOLERANCE_MM: f64 = 1.0;
/// Default gap that separates groups of points above the table, mm.
pub const DEFAULT_GAP_MM: f64 = 3.0;

/// [`crate::domain::pipeline::TableOptions`] after defaults and checks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TableSettings {
    pub tolerance_mm: f64,
    pub largest_only: bool,
    pub gap_mm: f64,
}

impl Default for TableSettings {
    fn default() -> Self {
        TableSettings { tolerance_mm: DEFAULT_TOLERANCE_MM, largest_only: true, gap_mm: DEFAULT_GAP_MM }
    }
}

/// What the table filter found and did (the reconstruct report's `table`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TableReport {
    /// The table's plane in the input's frame (after `filters.transform`): its unit normal,
    /// towards the part, and `offset_mm` with `normal · p = offset_mm` on it.
    pub normal: [f64; 3],
    pub offset_mm: f64,
    /// Its angle to the input's XY plane, degrees.
    pub tilt_deg: f64,
    /// Points on the table (within the tolerance) and under it: removed.
    pub on_table: usize,
    pub under_table: usize,
    /// Groups of points above the table, and the points of all but the largest (removed when
    /// only the largest is kept).
    pub groups: usize,
    pub in_other_groups: usize,
    pub kept: usize,
    /// The rigid motion applied, input frame to the table's, row-major 4x4 ([`Self::motion`]).
    pub transform: [[f64; 4]; 4],
    /// The same motion, for what must follow the cloud (a scan's free space).
    #[serde(skip)]
    pub motion: Isometry3<f64>,
}

/// Finds the table in `cloud`, turns the cloud to stand on it at `z = 0` and keeps what stands
/// above it (the largest group only, when asked). Errors when no plane can be found (fewer than
/// three points, all on one line) or nothing is left above it.
pub fn level_on_table(cloud: PointCloud, s: &TableSettings) -> Result<(PointCloud, TableReport)> {
    let pts: Vec<Point3<f64>> = cloud.points.iter().map(|p| p.at()).collect();
    let (normal, offset) = find_plane(&pts, s.tolerance_mm)?;
    let dist: Vec<f64> = pts.iter().map(|p| normal.dot(&p.coords) - offset).collect();
    let above = dist.iter().filter(|d| **d > s.tolerance_mm).count();
    let below = dist.iter().filter(|d| **d < -s.tolerance_mm).count();
    let (normal, offset, dist) = if below > above {
        (-normal, -offset, dist.iter().map(|d| -d).collect())
    } else {
        (normal, offset, dist)
    };
    let rotation = UnitQuaternion::rotation_between(&normal, &Vector3::z())
        .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
    // p ↦ R·p − offset·ẑ: the plane goes to z = 0 (R·n = ẑ).
    let iso = Isometry3::from_parts(Translation3::new(0.0, 0.0, -offset), rotation);
    let on_table = dist.iter().filter(|d| d.abs() <= s.tolerance_mm).count();
    let under_table = dist.iter().filter(|d| **d < -s.tolerance_mm).count();
    let up: Vec<usize> = (0..pts.len()).filter(|&i| dist[i] > s.tolerance_mm).collect();
    if up.is_empty() {
        return Err(ReconError::Empty(format!(
            "reconstruct.filters.table: nothing stands more than {} mm above the table found ({} points on it, {} under it)",
            s.tolerance_mm, on_table, under_table
        )));
    }
    let turned: Vec<Point3<f64>> = up.iter().map(|&i| iso * pts[i]).collect();
    let group = groups(&turned, s.gap_mm);
    let n_groups = group.iter().copied().max().map_or(0, |g| g + 1);
    let mut sizes = vec![0usize; n_groups];
    for &g in &group {
        sizes[g] += 1;
    }
    let largest = (0..n_groups).max_by_key(|&g| (sizes[g], std::cmp::Reverse(g))).unwrap_or(0);
    let in_other_groups = up.len() - sizes.get(largest).copied().unwrap_or(0);
    let mut keep = vec![false; pts.len()];
    for (k, &i) in up.iter().enumerate() {
        keep[i] = !s.largest_only || group[k] == largest;
    }
    let mut cloud = cloud;
    cloud.transform(&iso);
    let cloud = crate::domain::filters::retain(cloud, &keep);
    let m = iso.to_homogeneous();
    let transform = std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]));
    let report = TableReport {
        normal: [normal.x, normal.y, normal.z],
        offset_mm: offset,
        tilt_deg: normal.z.abs().clamp(0.0, 1.0).acos().to_degrees(),
        on_table,
        under_table,
        groups: n_groups,
        in_other_groups,
        kept: cloud.len(),
        transform,
        motion: iso,
    };
    tracing::info!(
        tilt_deg = report.tilt_deg,
        on_table,
        groups = n_groups,
        kept = report.kept,
        "table found"
    );
    Ok((cloud, report))
}

/// The plane most points lie within `tol` of: unit normal and offset (`n · p = offset`).
pub fn find_plane(pts: &[Point3<f64>], tol: f64) -> Result<(Vector3<f64>, f64)> {
    let no_plane = |why: &str| ReconError::Empty(format!("reconstruct.filters.table: no table found: {why}"));
    if pts.len() < 3 {
        return Err(no_plane(&format!("{} points, a plane needs 3", pts.len())));
    }
    let mut rng = StdRng::seed_from_u64(0x7AB1E);
    let score: Vec<Point3<f64>> = if pts.len() <= SCORE_SAMPLES {
        pts.to_vec()
    } else {
        (0..SCORE_SAMPLES).map(|_| pts[rng.random_range(0..pts.len())]).collect()
    };
    let count = |n: &Vector3<f64>, d: f64, set: &[Point3<f64>]| {
        set.iter().filter(|p| (n.dot(&p.coords) - d).abs() <= tol).count()
    };
    let mut best: Option<(usize, Vector3<f64>, f64)> = None;
    for _ in 0..ITERATIONS {
        let [a, b, c] = [0; 3].map(|_| pts[rng.random_range(0..pts.len())]);
        let Some(n) = (b - a).cross(&(c - a)).try_normalize(1e-12) else { continue };
        let d = n.dot(&a.coords);
        let k = count(&n, d, &score);
        if best.is_none_or(|(bk, _, _)| k > bk) {
            best = Some((k, n, d));
        }
    }
    let Some((_, mut n, mut d)) = best else {
        return Err(no_plane("every three points tried lie on one line"));
    };
    // Least squares on the plane's own points, twice (the band moves as the plane settles).
    for _ in 0..2 {
        let inliers: Vec<&Point3<f64>> = pts.iter().filter(|p| (n.dot(&p.coords) - d).abs() <= tol).collect();
        if inliers.len() < 3 {
            break;
        }
        let c = inliers.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / inliers.len() as f64;
        let cov = inliers.iter().fold(Matrix3::zeros(), |s, p| {
            let v = p.coords - c;
            s + v * v.transpose()
        });
        let eig = cov.symmetric_eigen();
        let (i, _) = eig
            .eigenvalues
            .iter()
            .enumerate()
            .fold((0, f64::INFINITY), |m, (i, v)| if *v < m.1 { (i, *v) } else { m });
        let Some(fit) = eig.eigenvectors.column(i).into_owned().try_normalize(1e-12) else { break };
        // Keep the side the RANSAC plane had.
        let fit = if fit.dot(&n) < 0.0 { -fit } else { fit };
        n = fit;
        d = n.dot(&c);
    }
    Ok((n, d))
}

/// Group index of each point: points whose `gap`-cells touch (26 neighbours) share a group;
/// groups are numbered in the order their first point comes.
pub fn groups(pts: &[Point3<f64>], gap: f64) -> Vec<usize> {
    let key = |p: &Point3<f64>| -> (i64, i64, i64) {
        ((p.x / gap).floor() as i64, (p.y / gap).floor() as i64, (p.z / gap).floor() as i64)
    };
    let mut cells: HashMap<(i64, i64, i64), usize> = HashMap::new();
    let cell_of: Vec<usize> = pts
        .iter()
        .map(|p| {
            let n = cells.len();
            *cells.entry(key(p)).or_insert(n)
        })
        .collect();
    // Union-find over the occupied cells.
    let mut parent: Vec<usize> = (0..cells.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for (&(x, y, z), &i) in &cells {
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(&j) = cells.get(&(x + dx, y + dy, z + dz)) {
                        let (a, b) = (root(&mut parent, i), root(&mut parent, j));
                        if a != b {
                            parent[a.max(b)] = a.min(b);
                        }
                    }
                }
            }
        }
    }
    let mut label: HashMap<usize, usize> = HashMap::new();
    cell_of
        .iter()
        .map(|&c| {
            let r = root(&mut parent, c);
            let n = label.len();
            *label.entry(r).or_insert(n)
        })
        .collect()
}

#[cfg(test)]
mod tests;

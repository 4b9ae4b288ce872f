//! Clean-up filters for point clouds, sphere fitting for spherical reference beacons, the frame
//! three beacons define, and rigid user transforms.
//!
//! Every filter takes the cloud by value and returns the filtered cloud (intensity and normals
//! follow their points, see [`retain`]) with a [`FilterReport`] of points kept and removed. The
//! surviving points keep their original order, except after [`statistical_outlier_removal`],
//! which works in place and leaves them grouped by grid cell. An empty cloud is fine (report 0/0).
//! Points are the cloud's single-precision ones; every distance is computed in `f64` from them
//! (exactly what Open3D computes from a float PLY it reads into doubles).
//!
//! # Conventions
//!
//! - A point is *usable* when its three coordinates are finite. The outlier filters and the voxel
//!   decimation remove points that are not usable (they count as removed) and ignore them as
//!   neighbours; [`intensity_window`] looks at the intensity only.
//! - Parameter errors are [`ReconError::InvalidParameter`] with the job JSON's field name
//!   (`reconstruct.filters.statistical.k`, `reconstruct.filters.radius.radius_mm`,
//!   `reconstruct.filters.voxel_mm`, `reconstruct.filters.intensity.min`, ...).
//!
//! # Statistical outlier removal: the same rule as Open3D
//!
//! [`statistical_outlier_mask`] follows Open3D's `remove_statistical_outlier(nb_neighbors = k,
//! std_ratio = n_sigma)` (checked against Open3D 0.20's `PointCloud::RemoveStatisticalOutliers`
//! and by experiment, see `scripts/compare_open3d.py`):
//!
//! - `d_i` = mean Euclidean distance from point `i` to its `k` nearest usable points, **the point
//!   itself included** (its distance 0 is the first of the `k`), summed in ascending order and
//!   divided by `k`. With fewer than `k` usable points, all of them are used.
//! - `μ` = mean of the `d_i` and `σ` = their **sample** standard deviation (Bessel, divide by
//!   `m − 1`), both accumulated in point order like Open3D, so thresholds agree to the last bit.
//! - A point is kept iff `d_i < μ + n_sigma·σ` (strict).
//!
//! Two deliberate differences, both outside what a real scan produces: Open3D drops every point
//! whose `d_i` is exactly 0 (a point with `k − 1` exact duplicates) and leaves those points out of
//! `μ`'s sum but not its count; here such points are ordinary inliers. And when `σ = 0` (every
//! `d_i` equal) or fewer than 2 points are usable, Open3D keeps nothing; here every usable point is
//! kept (no point stands out). On a cloud without `k` coincident points the kept sets are equal.
//!
//! # Radius outlier removal
//!
//! [`radius_outlier_mask`] keeps a point iff at least `min_neighbours` *other* usable points lie at
//! a distance strictly below `radius_mm` (Open3D's `remove_radius_outlier(nb_points, radius)`
//! counts the point itself and keeps it iff the count exceeds `nb_points`: the same rule).
//!
//! # The neighbour search
//!
//! Both outlier filters use a uniform grid: usable points are sorted by cell (radix sort on a key
//! made of the 2-D Morton code of the cell's (x, y) column followed by its z layer), so that each
//! cell is a contiguous run and each column a contiguous run of cells. A cell is processed as a
//! batch against its 3 × 3 × 3 block, which lies in at most 9 contiguous runs (one per column).
//!
//! - Radius search: the cell edge is at least the radius, so the block holds the whole ball and
//!   the count is exact (it stops as soon as `min_neighbours + 1` points are found).
//! - k nearest neighbours: the cell edge is chosen on a random sample so that a typical point's
//!   cell holds about `0.4·k` points on a surface (`0.55·k` on a curve, `0.33·k` in a volume;
//!   the local dimension is estimated on the sample, and exact duplicates are left out of the
//!   estimate). For each query the block's squared distances are filtered (branch-free, two
//!   queries per pass) to those below the previous query's k-th distance² · 1.25 and below the
//!   block margin² (the distance from the query to the block's boundary: every point outside the
//!   block is at least that far), then sorted. When at least `k` survive they are provably the
//!   `k` nearest of the whole cloud. Queries that fail get a second chance on the 5 × 5 × 5
//!   block; the rest (isolated points) and the queries of overfull blocks (heaps of duplicates)
//!   go to a bounding-volume hierarchy over the grid's own point order (a node is a run of cells
//!   with a common key prefix, a box; leaves of at most 24 points, nearest-child-first search
//!   with box pruning; no copy of the points), built only when needed. The isolated cells'
//!   points (at most an eighth of the cloud) are left out of it and copied into a small
//!   hierarchy of their own, searched first (small, it sets a bound for the big one): a stray
//!   point in a run of surface cells would stretch the boxes above the run to its height.
//!   These queries go in grid order, each starting with a bound from the one before (its k-th
//!   distance plus the step between them, the triangle inequality), so pruning starts at the
//!   first node.
//!
//! [`statistical_outlier_mask`] sorts a copy of the usable points (with their indices) and returns
//! the mask in point order, for Open3D's bit-for-bit rule. [`statistical_outlier_removal`] sorts
//! the cloud itself instead (an in-place MSD radix sort of the points and their attributes by cell
//! key), stores the means in 16 bits and measures a point again exactly when its stored mean
//! cannot tell which side of the threshold it lies on: beside the cloud it holds the grid's
//! cells (12 bytes each, about one per three points) and 4 bytes a point while sorting, 2 after.
//!
//! Only distances are kept, never neighbour identities, so ties need no tie-break: the multiset of
//! the `k` smallest distances is unique and the result is deterministic, bit for bit the same as
//! the O(n²) reference of the tests. Work is split over cells with rayon; per-point results do
//! not depend on the split.
//!
//! # Voxel decimation
//!
//! [`voxel_decimate`] uses voxels of edge `voxel_mm` anchored at the origin (voxel
//! `floor(p / voxel_mm)`), so a point's voxel does not depend on the rest of the cloud. Per
//! occupied voxel it keeps the original point nearest the centroid of the voxel's points (ties: the
//! lowest index), with its attributes; points stay in their original order.
//!
//! # Spheres and beacons
//!
//! [`fit_sphere`] solves the algebraic least-squares problem (`|p|² = 2 c·p + d`, on centred and
//! scaled coordinates) and refines centre and radius by Levenberg–Marquardt on the geometric
//! residuals `|p − c| − r`. [`fit_beacon`] selects the points near an approximate centre, finds a
//! robust start by least median of squares over random 4-point spheres (so points of the table or
//! the part around the beacon do not bias it, as long as at least half of the selected points lie
//! on the sphere), then refits on the points whose residual is within 3·rms until the set is
//! stable. [`beacon_frame`] builds the frame of three beacon centres.

use std::cmp::Ordering;
use std::ops::Range;

use depthmill_geometry::pose::rotation_from_ypr_deg;
use depthmill_geometry::{CloudPoint, PointCloud};
use nalgebra::{
    Isometry3, Matrix3, Matrix4, Point3, Rotation3, Translation3, UnitQuaternion, Vector3, Vector4,
};
use rayon::prelude::*;
use serde::Serialize;

use crate::domain::error::{ReconError, Result};

/// What one filter did: its name (`intensity`, `voxel`, `statistical`, `radius`, the keys of the
/// job's `filters` object) and how many points it kept and removed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct FilterReport {
    pub filter: &'static str,
    pub kept: usize,
    pub removed: usize,
}

impl FilterReport {
    fn from_mask(filter: &'static str, keep: &[bool]) -> Self {
        let kept = keep.iter().filter(|&&k| k).count();
        FilterReport { filter, kept, removed: keep.len() - kept }
    }
}

/// Keeps the points whose `keep` entry is true, with their intensity/normals.
///
/// Order is preserved. A point without a `keep` entry (when `keep` is shorter than the cloud) is
/// dropped; extra entries are ignored.
pub fn retain(cloud: PointCloud, keep: &[bool]) -> PointCloud {
    retain_where(cloud, |i| keep.get(i).copied().unwrap_or(false))
}

/// Keeps point `i` (with its intensity/normals) where `keep(i)`, in order, in place.
fn retain_where(mut cloud: PointCloud, keep: impl Fn(usize) -> bool) -> PointCloud {
    fn retain_vec<T>(v: &mut Vec<T>, keep: &impl Fn(usize) -> bool) {
        let mut i = 0usize;
        // Vec::retain visits every element exactly once, in order.
        v.retain(|_| {
            i += 1;
            keep(i - 1)
        });
    }
    retain_vec(&mut cloud.points, &keep);
    if let Some(v) = &mut cloud.intensity {
        retain_vec(v, &keep);
    }
    if let Some(v) = &mut cloud.normals {
        retain_vec(v, &keep);
    }
    cloud
}

/// Keeps the points whose intensity lies in `[min, max]` (inclusive; a NaN intensity is outside).
///
/// Errors: [`ReconError::MissingAttribute`] when the cloud has no intensity;
/// [`ReconError::InvalidParameter`] (`reconstruct.filters.intensity.min`/`max`) when a bound is
/// not finite or `min > max`; a geometry error when the cloud's arrays differ in length.
pub fn intensity_window(cloud: PointCloud, min: f32, max: f32) -> Result<(PointCloud, FilterReport)> {
    if !min.is_finite() {
        return Err(ReconError::param("reconstruct.filters.intensity.min", min, "must be finite"));
    }
    if !max.is_finite() {
        return Err(ReconError::param("reconstruct.filters.intensity.max", max, "must be finite"));
    }
    if min > max {
        return Err(ReconError::param(
            "reconstruct.filters.intensity.max",
            max,
            format!("must be at least min = {min}"),
        ));
    }
    cloud.validate()?;
    let Some(intensity) = &cloud.intensity else {
        return Err(ReconError::MissingAttribute { operation: "the intensity window", what: "intensity" });
    };
    let keep: Vec<bool> = intensity.iter().map(|&i| i >= min && i <= max).collect();
    let report = FilterReport::from_mask("intensity", &keep);
    Ok((retain(cloud, &keep), report))
}

fn check_k(k: usize) -> Result<()> {
    if k == 0 {
        return Err(ReconError::param("reconstruct.filters.statistical.k", k, "must be at least 1"));
    }
    Ok(())
}

/// Most points the neighbour search takes (its cell starts are 32-bit).
const MAX_GRID_POINTS: usize = u32::MAX as usize;

fn check_size(points: usize, field: &str) -> Result<()> {
    if points > MAX_GRID_POINTS {
        return Err(ReconError::param(field, points, format!("at most {MAX_GRID_POINTS} points")));
    }
    Ok(())
}

fn check_sor(k: usize, n_sigma: f64) -> Result<()> {
    check_k(k)?;
    if !(n_sigma.is_finite() && n_sigma > 0.0) {
        return Err(ReconError::param(
            "reconstruct.filters.statistical.n_sigma",
            n_sigma,
            "must be finite and positive",
        ));
    }
    Ok(())
}

/// Mean distance from each point to its `k` nearest usable points, the point itself included
/// (distance 0), summed in ascending order; `NaN` for points that are not usable. With fewer than
/// `k` usable points, the mean is over all of them. This is the `d_i` of
/// [`statistical_outlier_mask`] (see the module docs).
///
/// Errors: `reconstruct.filters.statistical.k` when `k = 0`.
pub fn knn_mean_distances(points: &[Point3<f32>], k: usize) -> Result<Vec<f64>> {
    check_k(k)?;
    check_size(points.len(), "reconstruct.filters.statistical")?;
    Ok(knn_means(points, k))
}

/// Which points statistical outlier removal keeps (Open3D's rule, see the module docs): `true`
/// iff the point is usable and its mean distance to its `k` nearest neighbours (itself included)
/// is below `μ + n_sigma·σ` over the cloud (`σ` the sample standard deviation).
///
/// Errors: `reconstruct.filters.statistical.k` when `k = 0`; `reconstruct.filters.statistical.n_sigma`
/// when `n_sigma` is not finite and positive.
pub fn statistical_outlier_mask(points: &[Point3<f32>], k: usize, n_sigma: f64) -> Result<Vec<bool>> {
    check_sor(k, n_sigma)?;
    check_size(points.len(), "reconstruct.filters.statistical")?;
    let means = knn_means(points, k);
    Ok(sor_mask_from_means(&means, n_sigma))
}

/// The keep rule on per-point mean distances (`NaN` = unusable point), in point order like Open3D.
fn sor_mask_from_means(means: &[f64], n_sigma: f64) -> Vec<bool> {
    let mut count = 0usize;
    let mut sum = 0.0f64;
    for &d in means.iter().filter(|d| !d.is_nan()) {
        count += 1;
        sum += d;
    }
    if count < 2 {
        return means.iter().map(|d| !d.is_nan()).collect();
    }
    let mean = sum / count as f64;
    let mut sq_sum = 0.0f64;
    for &d in means.iter().filter(|d| !d.is_nan()) {
        sq_sum += (d - mean) * (d - mean);
    }
    let std_dev = (sq_sum / (count - 1) as f64).sqrt();
    let threshold = mean + n_sigma * std_dev;
    // `d <= mean` only matters when σ = 0 (then everything is kept); otherwise it implies
    // `d < threshold`.
    means.iter().map(|&d| !d.is_nan() && (d < threshold || d <= mean)).collect()
}

/// Statistical outlier removal (report name `statistical`): the rule of
/// [`statistical_outlier_mask`], done in place.
///
/// Beside the cloud it needs 4 bytes a point while sorting (the keys), then 2 (the means), and
/// the grid's cells (12 bytes each, about one per three points), where the mask needs a sorted
/// copy with indices: the cloud is sorted by grid cell (its attributes with it), the mean
/// distances are kept in 16 bits (a point whose mean lies within their rounding of the threshold
/// is measured again exactly), and the survivors are compacted. So the survivors come
/// out grouped by grid cell, not in their original order, and `μ` and `σ` are summed in that
/// order (merged per chunk of cells, Chan et al.): the kept set is the mask's unless a mean lies
/// within the last bit of the threshold.
pub fn statistical_outlier_removal(
    cloud: PointCloud,
    k: usize,
    n_sigma: f64,
) -> Result<(PointCloud, FilterReport)> {
    sor_in_place(cloud, k, n_sigma, STORED_SLACK, false)
}

/// [`statistical_outlier_removal`], then the points it flagged that lie on the surface their `k`
/// nearest neighbours sample are kept after all (report name `statistical`).
///
/// Why: the rule compares every point's mean neighbour distance with the whole cloud's, so where
/// the scanner samples a surface sparsely (a steep wall seen at a glancing angle, a pass from
/// afar, the edge of a line's reach) it removes true points by the thousand; a depth map then
/// fills those cells from around them, below the surface they showed. A flagged point is kept
/// when its neighbours lie close together (the farthest at most four times as far as the
/// median) and flat (their RMS distance from their plane at most a quarter of their
/// spread along its shorter axis: a surface, not a scatter of strays nor a single line), it lies
/// on their plane within four times that RMS, and among them (within twice their RMS spread
/// along the plane of their centroid). A stray point above a densely sampled surface stands far
/// off its neighbours' plane and stays removed. [`statistical_outlier_mask_keeping_surface`] is
/// the same on a mask.
pub fn statistical_outlier_removal_keeping_surface(
    cloud: PointCloud,
    k: usize,
    n_sigma: f64,
) -> Result<(PointCloud, FilterReport)> {
    sor_in_place(cloud, k, n_sigma, STORED_SLACK, true)
}

/// [`statistical_outlier_mask`] with the points it flags on a sparsely sampled surface kept (see
/// [`statistical_outlier_removal_keeping_surface`]).
pub fn statistical_outlier_mask_keeping_surface(
    points: &[Point3<f32>],
    k: usize,
    n_sigma: f64,
) -> Result<Vec<bool>> {
    let mut keep = statistical_outlier_mask(points, k, n_sigma)?;
    let Some(bbox) = UsableBox::of(points) else { return Ok(keep) };
    if !keep.iter().zip(points).any(|(&kp, p)| !kp && usable(p)) {
        return Ok(keep);
    }
    let k = k.min(bbox.count);
    let grid = Grid::build(points, &bbox, knn_cell_size(points, &bbox, k), false);
    let dropped: Vec<usize> =
        (0..grid.order.len().min(bbox.count)).filter(|&s| !keep[grid.order[s]]).collect();
    for s in kept_back(&grid, k, dropped) {
        keep[grid.order[s]] = true;
    }
    Ok(keep)
}

/// A mean distance as stored by the in-place removal: the upper 16 bits of its `f32` (bfloat16:
/// 8 bits of precision, `f32`'s range).
fn store_mean(d: f64) -> u16 {
    ((d as f32).to_bits() >> 16) as u16
}

/// [`store_mean`]'s value, within [`STORED_SLACK`] of the mean.
fn stored_mean(b: u16) -> f64 {
    f64::from(f32::from_bits(u32::from(b) << 16))
}

/// Relative half-width of the interval a stored mean may have come from (the truncation loses
/// less than 2^-7 of the value, the rounding to `f32` 2^-24; 2^-6 for margin). The points whose
/// stored mean lies that close to the threshold are measured again exactly.
const STORED_SLACK: f64 = 1.0 / 64.0;

/// Leaf size of the hierarchy the in-place removal builds for its fallback queries (fewer,
/// larger leaves: a smaller tree).
const LEAF_MAX_IN_PLACE: usize = 256;

/// [`statistical_outlier_removal`] with the relative slack within which a stored mean is
/// measured again exactly (tests force every point through the exact path with a large one).
fn sor_in_place(
    mut cloud: PointCloud,
    k: usize,
    n_sigma: f64,
    slack: f64,
    keep_surface: bool,
) -> Result<(PointCloud, FilterReport)> {
    cloud.validate()?;
    check_sor(k, n_sigma)?;
    check_size(cloud.len(), "reconstruct.filters.statistical")?;
    let n = cloud.len();
    let Some(bbox) = UsableBox::of(&cloud.points) else {
        let report = FilterReport { filter: "statistical", kept: 0, removed: n };
        return Ok((retain(cloud, &[]), report));
    };
    let k = k.min(bbox.count);
    let h = knn_cell_size(&cloud.points, &bbox, k);
    let mut grid = Grid::build_in_place(&mut cloud, &bbox, h, true);
    if grid.probe_failures(k) > PROBE_FAIL {
        // Cells too small for much of the cloud (a density that varies): once more, larger.
        let Grid { xyz, .. } = grid;
        cloud.points = xyz;
        grid = Grid::build_in_place(&mut cloud, &bbox, h * GROW, true);
    }
    let mut means = vec![0u16; grid.xyz.len()];
    let (_, moments) = grid_knn(&grid, k, LEAF_MAX_IN_PLACE, SumOrder::Any, &mut means, store_mean);
    // The decisions overwrite the means (1 keep, 0 drop): no second array.
    if moments.n < 2 {
        means.fill(1);
    } else {
        let mean = moments.mean;
        let threshold = mean + n_sigma * (moments.m2 / (moments.n - 1) as f64).sqrt();
        let rule = |d: f64| d < threshold || d <= mean;
        // Some(decision) when the stored mean settles it, None when it must be measured again.
        let sure = |m: u16| {
            let m = stored_mean(m);
            let e = m.abs() * slack;
            if rule(m + e) {
                Some(true)
            } else if !rule(m - e) {
                Some(false)
            } else {
                None
            }
        };
        let unsure: Vec<usize> = (0..means.len()).filter(|&s| sure(means[s]).is_none()).collect();
        means.par_iter_mut().for_each(|m| *m = u16::from(sure(*m) == Some(true)));
        if !unsure.is_empty() {
            // The points near the threshold: their blocks, grown until they hold the k nearest
            // for sure.
            let exact: Vec<bool> = unsure.par_iter().map(|&s| rule(ring_knn(&grid, s, k))).collect();
            for (&s, e) in unsure.iter().zip(exact) {
                means[s] = u16::from(e);
            }
        }
        if keep_surface {
            // The usable points are the first `bbox.count` of the sorted cloud.
            let dropped: Vec<usize> = (0..bbox.count.min(means.len())).filter(|&s| means[s] == 0).collect();
            for s in kept_back(&grid, k, dropped) {
                means[s] = 1;
            }
        }
    }
    let Grid { xyz, .. } = grid;
    cloud.points = xyz;
    let kept = means.iter().filter(|&&m| m == 1).count();
    let report = FilterReport { filter: "statistical", kept, removed: n - kept };
    Ok((retain_where(cloud, |i| means[i] == 1), report))
}

/// Which points radius outlier removal keeps: `true` iff the point is usable and at least
/// `min_neighbours` other usable points lie at a distance strictly below `radius_mm`.
///
/// Errors: `reconstruct.filters.radius.radius_mm` when the radius is not finite and positive;
/// `reconstruct.filters.radius.min_neighbours` when it is 0 (that would keep every point).
pub fn radius_outlier_mask(
    points: &[Point3<f32>],
    radius_mm: f64,
    min_neighbours: usize,
) -> Result<Vec<bool>> {
    if !(radius_mm.is_finite() && radius_mm > 0.0) {
        return Err(ReconError::param(
            "reconstruct.filters.radius.radius_mm",
            radius_mm,
            "must be finite and positive",
        ));
    }
    if min_neighbours == 0 {
        return Err(ReconError::param(
            "reconstruct.filters.radius.min_neighbours",
            min_neighbours,
            "must be at least 1 (0 keeps every point)",
        ));
    }
    check_size(points.len(), "reconstruct.filters.radius")?;
    let Some(bbox) = UsableBox::of(points) else {
        return Ok(vec![false; points.len()]);
    };
    // Cells at least as large as the radius (plus rounding slack): the block holds the whole ball.
    let h = (radius_mm * (1.0 + 1e-6) + bbox.tol).max(bbox.min_cell());
    let grid = Grid::build(points, &bbox, h, false);
    let r2 = radius_mm * radius_mm;
    let need = min_neighbours.saturating_add(1); // the point itself is among the hits
    let mut keep_sorted = vec![false; grid.xyz.len()];
    let chunks = grid.chunks();
    let slices = split_by_chunks(&mut keep_sorted, &grid, &chunks);
    let columns = Columns::build(&grid);
    chunks.into_par_iter().zip(slices).for_each(|(cells, out)| {
        let base = grid.start(cells.start);
        let mut ranges = Vec::with_capacity(9);
        for c in cells {
            grid.block_ranges_with(columns.as_ref(), c, 1, &mut ranges);
            for s in grid.start(c)..grid.start(c + 1) {
                let q = &grid.xyz[s];
                let mut count = 0usize;
                'search: for r in &ranges {
                    for p in &grid.xyz[r.clone()] {
                        if dist2(q, p) < r2 {
                            count += 1;
                            if count >= need {
                                break 'search;
                            }
                        }
                    }
                }
                out[s - base] = count >= need;
            }
        }
    });
    let mut keep = vec![false; points.len()];
    for (s, &k) in keep_sorted.iter().enumerate() {
        keep[grid.order[s]] = k;
    }
    Ok(keep)
}

/// Radius outlier removal (report name `radius`): [`radius_outlier_mask`] applied with [`retain`].
pub fn radius_outlier_removal(
    cloud: PointCloud,
    radius_mm: f64,
    min_neighbours: usize,
) -> Result<(PointCloud, FilterReport)> {
    cloud.validate()?;
    let keep = radius_outlier_mask(&cloud.points, radius_mm, min_neighbours)?;
    let report = FilterReport::from_mask("radius", &keep);
    Ok((retain(cloud, &keep), report))
}

/// Largest voxel index magnitude accepted (integers up to 2^53 are exact in f64).
const MAX_VOXEL_INDEX: f64 = 9_007_199_254_740_992.0;

/// The voxel of `p` (edge `voxel`, anchored at the origin), `None` when beyond ±2^53 voxels.
fn voxel_of(p: &Point3<f64>, voxel: f64) -> Option<[i64; 3]> {
    let mut out = [0i64; 3];
    for (o, c) in out.iter_mut().zip(p.coords.iter()) {
        let v = c / voxel;
        // Beyond 2^53 every `f64` is an integer, so `v` within the bound iff its floor is.
        if v.is_nan() || v.abs() > MAX_VOXEL_INDEX {
            return None;
        }
        // The floor without a call into libm: truncate (exact here), one less for a negative
        // fraction.
        let t = v as i64;
        *o = if (t as f64) > v { t - 1 } else { t };
    }
    Some(out)
}

/// The point of `members` (indices into `points`, ascending) nearest the members' centroid; the
/// first one on ties. The centroid is `p₀ + Σ(pᵢ − p₀)/m`, summed in index order.
fn nearest_to_centroid<P: CloudPoint>(
    points: &[P],
    members: impl Iterator<Item = usize> + Clone,
) -> Option<usize> {
    let mut it = members.clone();
    let first = it.next()?;
    let p0 = points[first].at();
    let mut sum = Vector3::zeros();
    let mut m = 0usize;
    for i in members.clone() {
        sum += points[i].at() - p0;
        m += 1;
    }
    let centroid = p0 + sum / m as f64;
    let mut best = (first, f64::INFINITY);
    for i in members {
        let d = (points[i].at() - centroid).norm_squared();
        if d < best.1 {
            best = (i, d);
        }
    }
    Some(best.0)
}

/// Points per task of the voxel decimation's passes.
const VOXEL_CHUNK: usize = 1 << 14;

/// [`voxel_keep_mask`] when the cloud's voxel indices, taken from their minimum, pack into 32
/// bits (and the points are fewer than 2^32): one `u64` per point (packed voxel, point index)
/// radix-sorted on the voxel bits, which keeps each voxel's points in index order as the general
/// path's sort does, so the same point is kept. `None` otherwise (also when a point's voxel is
/// out of range: the general path reports it).
fn voxel_keep_packed<P: CloudPoint>(points: &[P], voxel: f64) -> Option<Vec<bool>> {
    if points.len() >= u32::MAX as usize {
        return None;
    }
    // The usable points' coordinate bounds: `floor(c / voxel)` never decreases as `c` grows
    // (a correctly rounded division is monotonic), so their voxels bound every point's.
    type Bounds = ([f64; 3], [f64; 3], usize);
    let empty: Bounds = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3], 0);
    let (lo_c, hi_c, usable_n) = points
        .par_chunks(VOXEL_CHUNK)
        .map(|part| {
            let mut b = empty;
            for p in part.iter().filter(|p| usable(*p)) {
                let q = p.at();
                for a in 0..3 {
                    b.0[a] = b.0[a].min(q[a]);
                    b.1[a] = b.1[a].max(q[a]);
                }
                b.2 += 1;
            }
            b
        })
        .reduce(
            || empty,
            |a, b| {
                let mut r = a;
                for i in 0..3 {
                    r.0[i] = a.0[i].min(b.0[i]);
                    r.1[i] = a.1[i].max(b.1[i]);
                }
                r.2 = a.2 + b.2;
                r
            },
        );
    if usable_n == 0 {
        return Some(vec![false; points.len()]);
    }
    let lo = voxel_of(&Point3::from(lo_c), voxel)?;
    let hi = voxel_of(&Point3::from(hi_c), voxel)?;
    let bits = [0, 1, 2].map(|a| 64 - (hi[a].abs_diff(lo[a])).leading_zeros());
    let total = bits.iter().sum::<u32>();
    if total > 32 {
        return None;
    }
    // (packed voxel << 32) | index per usable point, in index order, written chunk by chunk.
    let counts: Vec<usize> = if usable_n == points.len() {
        points.chunks(VOXEL_CHUNK).map(<[P]>::len).collect()
    } else {
        points.par_chunks(VOXEL_CHUNK).map(|part| part.iter().filter(|p| usable(*p)).count()).collect()
    };
    let ranges: Vec<Range<usize>> = counts
        .iter()
        .scan(0usize, |at, &c| {
            *at += c;
            Some(*at - c..*at)
        })
        .collect();
    let mut items = vec![0u64; usable_n];
    split_ranges_mut(&mut items, &ranges)
        .into_par_iter()
        .zip(points.par_chunks(VOXEL_CHUNK))
        .enumerate()
        .for_each(|(j, (out, part))| {
            let base = j * VOXEL_CHUNK;
            let mut o = out.iter_mut();
            for (i, p) in part.iter().enumerate() {
                if !usable(p) {
                    continue;
                }
                // Within the bounds (monotonic), so never `None`.
                let v = voxel_of(&p.at(), voxel).unwrap_or(lo);
                let d = [0, 1, 2].map(|a| v[a].abs_diff(lo[a]));
                let key = (d[0] << (bits[1] + bits[2])) | (d[1] << bits[2]) | d[2];
                if let Some(slot) = o.next() {
                    *slot = (key << 32) | (base + i) as u64;
                }
            }
        });
    radix_sort_bits(&mut items, 32, total.max(1));
    // Spans of whole voxels (each cut moved on to the next voxel's start), their voxels' runs
    // found and reduced in parallel.
    let m = items.len();
    let mut cuts: Vec<usize> = (0..m.div_ceil(VOXEL_CHUNK)).map(|c| c * VOXEL_CHUNK).collect();
    for c in cuts.iter_mut().skip(1) {
        let key = items[*c] >> 32;
        *c += items[*c..].partition_point(|&it| it >> 32 == key);
    }
    cuts.push(m);
    cuts.dedup();
    let kept: Vec<usize> = cuts
        .par_windows(2)
        .flat_map_iter(|w| {
            let span = &items[w[0]..w[1]];
            let mut out = Vec::new();
            let mut start = 0usize;
            for j in 1..=span.len() {
                if j == span.len() || span[j] >> 32 != span[start] >> 32 {
                    let members = span[start..j].iter().map(|&it| (it & 0xFFFF_FFFF) as usize);
                    out.extend(nearest_to_centroid(points, members));
                    start = j;
                }
            }
            out
        })
        .collect();
    let mut keep = vec![false; points.len()];
    for i in kept {
        keep[i] = true;
    }
    Some(keep)
}

/// Which points voxel decimation keeps: per occupied voxel the point nearest its centroid (see
/// the module docs).
///
/// Errors: `reconstruct.filters.voxel_mm` when the voxel is not finite and positive, or so small
/// that a point lies more than 2^53 voxels from the origin.
pub fn voxel_keep_mask<P: CloudPoint>(points: &[P], voxel_mm: f64) -> Result<Vec<bool>> {
    if !(voxel_mm.is_finite() && voxel_mm > 0.0) {
        return Err(ReconError::param(
            "reconstruct.filters.voxel_mm",
            voxel_mm,
            "must be finite and positive",
        ));
    }
    if let Some(keep) = voxel_keep_packed(points, voxel_mm) {
        return Ok(keep);
    }
    voxel_keep_general(points, voxel_mm)
}

/// [`voxel_keep_mask`] for any cloud: (voxel, index) pairs sorted.
fn voxel_keep_general<P: CloudPoint>(points: &[P], voxel_mm: f64) -> Result<Vec<bool>> {
    let mut pairs: Vec<([i64; 3], usize)> = points
        .par_iter()
        .enumerate()
        .filter(|(_, p)| usable(*p))
        .map(|(i, p)| voxel_of(&p.at(), voxel_mm).map(|v| (v, i)).ok_or(i))
        .collect::<std::result::Result<_, usize>>()
        .map_err(|i| {
            let p = points[i].at();
            ReconError::param(
                "reconstruct.filters.voxel_mm",
                voxel_mm,
                format!(
                    "too small: point {i} at ({}, {}, {}) mm lies more than 2^53 voxels from the origin",
                    p.x, p.y, p.z
                ),
            )
        })?;
    pairs.par_sort_unstable();
    let mut runs = Vec::new();
    let mut start = 0usize;
    for j in 1..=pairs.len() {
        if j == pairs.len() || pairs[j].0 != pairs[start].0 {
            runs.push(start..j);
            start = j;
        }
    }
    let kept: Vec<usize> = runs
        .into_par_iter()
        .filter_map(|r| nearest_to_centroid(points, pairs[r].iter().map(|&(_, i)| i)))
        .collect();
    let mut keep = vec![false; points.len()];
    for i in kept {
        keep[i] = true;
    }
    Ok(keep)
}

/// Voxel-grid decimation that keeps shape (report name `voxel`): per occupied voxel of edge
/// `voxel_mm`, the original point nearest the voxel's centroid, with its attributes; original
/// order. Unusable points are removed. Errors as [`voxel_keep_mask`].
pub fn voxel_decimate(cloud: PointCloud, voxel_mm: f64) -> Result<(PointCloud, FilterReport)> {
    cloud.validate()?;
    let keep = voxel_keep_mask(&cloud.points, voxel_mm)?;
    let report = FilterReport::from_mask("voxel", &keep);
    Ok((retain(cloud, &keep), report))
}

// ---------------------------------------------------------------------------------------------
// Neighbour search: usable box, grid, k-best buffers, bounding-volume hierarchy.
// ---------------------------------------------------------------------------------------------

fn usable<P: CloudPoint>(p: &P) -> bool {
    let p = p.at();
    p.x.is_finite() && p.y.is_finite() && p.z.is_finite()
}

/// A cloud's point, as the neighbour search stores it.
type Xyz = Point3<f32>;

/// Squared distance in `f64` (the cloud's `f32` coordinates widened exactly, as Open3D reads a
/// float PLY into doubles), accumulated x, y, z in that order (as Open3D's nanoflann adaptor
/// does).
#[inline(always)]
fn dist2(a: &Xyz, b: &Xyz) -> f64 {
    let dx = f64::from(a.x) - f64::from(b.x);
    let dy = f64::from(a.y) - f64::from(b.y);
    let dz = f64::from(a.z) - f64::from(b.z);
    dx * dx + dy * dy + dz * dz
}

/// `p` widened to `f64`.
#[inline(always)]
fn wide(p: &Xyz) -> [f64; 3] {
    [f64::from(p.x), f64::from(p.y), f64::from(p.z)]
}

/// Most cells along one axis (so the mixed-radix cell key stays below 2^60).
const MAX_CELLS_PER_AXIS: u64 = 1 << 20;
/// Points per rayon work item (cells are never split).
const CHUNK_POINTS: usize = 2048;
/// Points per rayon work item when finding where the cells start in sorted points.
const RUN_CHUNK: usize = 1 << 15;
/// Points per leaf of the bounding-volume hierarchy.
const LEAF: usize = 16;

/// Bounding box and count of the usable points.
#[derive(Debug, Clone, Copy)]
struct UsableBox {
    lo: [f64; 3],
    hi: [f64; 3],
    count: usize,
    /// Absolute slack for rounding of coordinates of this magnitude.
    tol: f64,
}

impl UsableBox {
    fn of(points: &[Point3<f32>]) -> Option<Self> {
        let empty = || ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3], 0usize);
        let (lo, hi, count) = points
            .par_iter()
            .filter(|p| usable(*p))
            .fold(empty, |(mut lo, mut hi, n), p| {
                let p = p.at();
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
                (lo, hi, n + 1)
            })
            .reduce(empty, |(l1, h1, n1), (l2, h2, n2)| {
                (
                    [l1[0].min(l2[0]), l1[1].min(l2[1]), l1[2].min(l2[2])],
                    [h1[0].max(h2[0]), h1[1].max(h2[1]), h1[2].max(h2[2])],
                    n1 + n2,
                )
            });
        if count == 0 {
            return None;
        }
        let scale = (0..3).map(|a| lo[a].abs().max(hi[a].abs())).fold(0.0, f64::max);
        Some(UsableBox { lo, hi, count, tol: 1e-14 * scale })
    }

    fn max_extent(&self) -> f64 {
        (0..3).map(|a| self.hi[a] - self.lo[a]).fold(0.0, f64::max)
    }

    /// Smallest cell edge for which every axis has at most [`MAX_CELLS_PER_AXIS`] cells.
    fn min_cell(&self) -> f64 {
        self.max_extent() / (MAX_CELLS_PER_AXIS - 2) as f64
    }
}

/// Cell coordinates of `p` on a grid at `origin` with `1/h = inv_h` and `dims` cells per axis.
#[inline]
fn cell_of(p: &[f64; 3], origin: &[f64; 3], inv_h: f64, dims: &[u64; 3]) -> [u64; 3] {
    // `as u64` truncates towards zero, which is the floor for every non-negative value, and
    // saturates (negative values and NaN give 0, as their floor would): the floor without a
    // call into libm, and no input can wrap.
    let c = |a: usize| (((p[a] - origin[a]) * inv_h) as u64).min(dims[a] - 1);
    [c(0), c(1), c(2)]
}

/// Spreads the low 20 bits of `v` to the even bits.
fn spread2(v: u64) -> u64 {
    let mut x = v & 0xF_FFFF;
    x = (x | (x << 16)) & 0x0000_FFFF_0000_FFFF;
    x = (x | (x << 8)) & 0x00FF_00FF_00FF_00FF;
    x = (x | (x << 4)) & 0x0F0F_0F0F_0F0F_0F0F;
    x = (x | (x << 2)) & 0x3333_3333_3333_3333;
    x = (x | (x << 1)) & 0x5555_5555_5555_5555;
    x
}

/// Inverse of [`spread2`]: the even bits of `v`, packed.
fn compact2(v: u64) -> u64 {
    let mut x = v & 0x5555_5555_5555_5555;
    x = (x | (x >> 1)) & 0x3333_3333_3333_3333;
    x = (x | (x >> 2)) & 0x0F0F_0F0F_0F0F_0F0F;
    x = (x | (x >> 4)) & 0x00FF_00FF_00FF_00FF;
    x = (x | (x >> 8)) & 0x0000_FFFF_0000_FFFF;
    (x | (x >> 16)) & 0xF_FFFF
}

/// Bits for the z coordinate of a cell key on a grid with `dims_z` layers.
fn z_bits(dims_z: u64) -> u32 {
    64 - (dims_z.max(2) - 1).leading_zeros()
}

/// Cell key: the 2-D Morton code of the (x, y) column, then z (`zbits` bits). The cells of one
/// column are consecutive (z fastest), and a common key prefix is a box of columns and layers.
#[inline]
fn cell_key(c: [u64; 3], zbits: u32) -> u64 {
    ((spread2(c[0]) | (spread2(c[1]) << 1)) << zbits) | c[2]
}

fn grid_dims(bbox: &UsableBox, inv_h: f64) -> [u64; 3] {
    let d = |a: usize| (((bbox.hi[a] - bbox.lo[a]) * inv_h).floor() as u64).saturating_add(1);
    [d(0), d(1), d(2)].map(|d| d.clamp(1, MAX_CELLS_PER_AXIS))
}

/// Stable LSD radix sort of `items` by bits `shift0..shift0 + bits` (11 bits per pass).
fn radix_sort_bits(items: &mut Vec<u64>, shift0: u32, bits: u32) {
    const DIGIT: u32 = 11;
    let mut tmp = vec![0u64; items.len()];
    let mut counts = vec![0usize; 1 << DIGIT];
    let end = shift0 + bits;
    let mut shift = shift0;
    while shift < end {
        let width = DIGIT.min(end - shift);
        let mask = (1u64 << width) - 1;
        let counts = &mut counts[..1 << width];
        counts.fill(0);
        for &v in items.iter() {
            counts[((v >> shift) & mask) as usize] += 1;
        }
        if !counts.contains(&items.len()) {
            let mut sum = 0usize;
            for c in counts.iter_mut() {
                let here = *c;
                *c = sum;
                sum += here;
            }
            for &v in items.iter() {
                let b = ((v >> shift) & mask) as usize;
                tmp[counts[b]] = v;
                counts[b] += 1;
            }
            std::mem::swap(items, &mut tmp);
        }
        shift += width;
    }
}

/// Reorders `pts` by recursive median splits along the widest axis, splitting at multiples of
/// [`LEAF`] from the start, so that every run of [`LEAF`] points is a compact kd-tree leaf.
fn kd_order(pts: &mut [(Xyz, usize)]) {
    if pts.len() <= LEAF {
        return;
    }
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for (p, _) in pts.iter() {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let axis = (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0);
    let mid = LEAF * pts.len().div_ceil(2 * LEAF);
    pts.select_nth_unstable_by(mid, |p, q| p.0[axis].total_cmp(&q.0[axis]).then(p.1.cmp(&q.1)));
    let (l, r) = pts.split_at_mut(mid);
    kd_order(l);
    kd_order(r);
}

/// Usable points sorted by grid cell, cells as contiguous runs.
struct Grid {
    origin: [f64; 3],
    h: f64,
    dims: [u64; 3],
    /// Bits of z in a cell key ([`cell_key`]).
    zbits: u32,
    tol: f64,
    /// Key ([`cell_key`]) of every occupied cell, ascending.
    keys: Vec<u64>,
    /// `xyz[starts[c]..starts[c + 1]]` are cell `c`'s points; `starts.len() == keys.len() + 1`
    /// (32 bits: a grid holds at most [`MAX_GRID_POINTS`]).
    starts: Vec<u32>,
    /// Usable points grouped by cell.
    xyz: Vec<Xyz>,
    /// Original index of `xyz[s]`.
    order: Vec<usize>,
}

/// A radix-sortable key.
trait RadixKey: Copy + Ord + Send + Sync + Default {
    fn bits(self) -> u64;
    /// The key from a value that fits (the caller has checked the width).
    fn narrow(k: u64) -> Self;
}

impl RadixKey for u32 {
    #[inline(always)]
    fn bits(self) -> u64 {
        u64::from(self)
    }
    #[inline(always)]
    fn narrow(k: u64) -> Self {
        k as u32
    }
}

impl RadixKey for u64 {
    #[inline(always)]
    fn bits(self) -> u64 {
        self
    }
    #[inline(always)]
    fn narrow(k: u64) -> Self {
        k
    }
}

/// How a point gets its cell key on a grid ([`cell_of`], [`cell_key`]); points that are not
/// usable get `limit`, above every cell's key.
#[derive(Debug, Clone, Copy)]
struct Keying {
    origin: [f64; 3],
    inv_h: f64,
    dims: [u64; 3],
    zbits: u32,
    limit: u64,
}

/// Points per batch of keys computed at once.
const KEY_BATCH: usize = 256;

impl Keying {
    #[inline(always)]
    fn key(&self, p: &Xyz) -> u64 {
        if usable(p) {
            cell_key(cell_of(&wide(p), &self.origin, self.inv_h, &self.dims), self.zbits)
        } else {
            self.limit
        }
    }

    /// The keys of every point, in parallel.
    fn all_keys<K: RadixKey>(&self, pts: &[Xyz]) -> Vec<K> {
        let mut out = vec![K::default(); pts.len()];
        out.par_chunks_mut(RUN_CHUNK).zip(pts.par_chunks(RUN_CHUNK)).for_each(|(o, p)| self.keys_into(p, o));
        out
    }

    /// The keys of `pts` into `out` (of the same length), a batch at a time through the vector
    /// kernel where the CPU has it.
    fn keys_into<K: RadixKey>(&self, pts: &[Xyz], out: &mut [K]) {
        let mut batch = [0u64; KEY_BATCH];
        for (p, o) in pts.chunks(KEY_BATCH).zip(out.chunks_mut(KEY_BATCH)) {
            simd::keys(self, p, &mut batch[..p.len()]);
            for (o, &k) in o.iter_mut().zip(&batch) {
                *o = K::narrow(k);
            }
        }
    }
}

/// A cloud's parallel arrays with a key per point, sorted together by [`flag_sort`].
struct Lanes<'a, K> {
    keys: &'a mut [K],
    pts: &'a mut [Xyz],
    intensity: Option<&'a mut [f32]>,
    normals: Option<&'a mut [Vector3<f32>]>,
}

/// `v` split at `mid`, each half optional like `v`.
fn split_opt<T>(v: Option<&mut [T]>, mid: usize) -> (Option<&mut [T]>, Option<&mut [T]>) {
    match v {
        Some(v) => {
            let (a, b) = v.split_at_mut(mid);
            (Some(a), Some(b))
        }
        None => (None, None),
    }
}

impl<'a, K: RadixKey> Lanes<'a, K> {
    #[inline(always)]
    fn swap(&mut self, i: usize, j: usize) {
        self.keys.swap(i, j);
        self.pts.swap(i, j);
        if let Some(v) = self.intensity.as_deref_mut() {
            v.swap(i, j);
        }
        if let Some(v) = self.normals.as_deref_mut() {
            v.swap(i, j);
        }
    }

    fn split_at(self, mid: usize) -> (Self, Self) {
        let (ka, kb) = self.keys.split_at_mut(mid);
        let (pa, pb) = self.pts.split_at_mut(mid);
        let (ia, ib) = split_opt(self.intensity, mid);
        let (na, nb) = split_opt(self.normals, mid);
        (
            Lanes { keys: ka, pts: pa, intensity: ia, normals: na },
            Lanes { keys: kb, pts: pb, intensity: ib, normals: nb },
        )
    }
}

/// Buckets of at most this many points are finished by insertion sort.
const FLAG_SMALL: usize = 48;
/// Buckets of at least this many points have their sub-buckets sorted in parallel.
const FLAG_PARALLEL: usize = 1 << 15;

/// In-place MSD radix sort (American flag sort, 8-bit digits) of `lanes` by key, from the digit
/// at bit `shift` (a multiple of 8) down; every swap moves all lanes. Not stable.
fn flag_sort<K: RadixKey>(mut lanes: Lanes<'_, K>, shift: u32) {
    let n = lanes.keys.len();
    if n <= FLAG_SMALL {
        for i in 1..n {
            let mut j = i;
            while j > 0 && lanes.keys[j - 1] > lanes.keys[j] {
                lanes.swap(j - 1, j);
                j -= 1;
            }
        }
        return;
    }
    let digit = |k: K| ((k.bits() >> shift) & 0xFF) as usize;
    let mut count = [0usize; 256];
    for &k in lanes.keys.iter() {
        count[digit(k)] += 1;
    }
    let mut start = [0usize; 257];
    for b in 0..256 {
        start[b + 1] = start[b] + count[b];
    }
    if !count.contains(&n) {
        // Sweeps over what each unfinished bucket has not yet settled: every point swept is
        // swapped to the next free place of its own bucket (for good) and what comes back is
        // looked at in the next sweep, so the swaps of one sweep do not wait on each other's
        // loads (the point at a place is not read again at once, as one swap after another
        // into the same place would). Places below `next[b]` hold bucket `b`'s points.
        let mut next = start;
        let mut open: Vec<usize> = (0..256).filter(|&b| count[b] > 0).collect();
        while !open.is_empty() {
            for &b in &open {
                for i in next[b]..start[b + 1] {
                    let d = digit(lanes.keys[i]);
                    lanes.swap(i, next[d]);
                    next[d] += 1;
                }
            }
            open.retain(|&b| next[b] < start[b + 1]);
        }
    }
    if shift == 0 {
        return;
    }
    let mut buckets = Vec::new();
    let mut rest = lanes;
    for &c in &count {
        let (mine, tail) = rest.split_at(c);
        rest = tail;
        if c > 1 {
            buckets.push(mine);
        }
    }
    if n >= FLAG_PARALLEL {
        buckets.into_par_iter().for_each(|b| flag_sort(b, shift - 8));
    } else {
        for b in buckets {
            flag_sort(b, shift - 8);
        }
    }
}

/// The bit of the highest 8-bit digit of keys below `limit`.
fn top_shift(limit: u64) -> u32 {
    let bits = 64 - limit.leading_zeros();
    (bits.max(1) - 1) / 8 * 8
}

impl Grid {
    /// [`Grid::build`] on the cloud's own arrays: the points (and their attributes) are sorted in
    /// place and moved into the grid, unusable points dropped; no copy and no index (`order` is
    /// empty). The cloud's `points` are left empty: put `xyz` back.
    fn build_in_place(cloud: &mut PointCloud, bbox: &UsableBox, h: f64, kd_cells: bool) -> Grid {
        let h = if h.is_finite() && h > 0.0 { h } else { 1.0 };
        let inv_h = 1.0 / h;
        let dims = grid_dims(bbox, inv_h);
        let origin = bbox.lo;
        let zbits = z_bits(dims[2]);
        let key_limit =
            cell_key([dims[0].next_power_of_two() - 1, dims[1].next_power_of_two() - 1, 0], zbits)
                + (1 << zbits);
        let keying = Keying { origin, inv_h, dims, zbits, limit: key_limit };
        let mut pts = std::mem::take(&mut cloud.points);
        let count = bbox.count;
        // The sort's keys go before the cells are built (from the sorted points' keys again), so
        // the two never take memory at once.
        fn sort<K: RadixKey>(mut keys: Vec<K>, pts: &mut [Xyz], cloud: &mut PointCloud, shift: u32) {
            let (intensity, normals) = (cloud.intensity.as_deref_mut(), cloud.normals.as_deref_mut());
            flag_sort(Lanes { keys: &mut keys, pts, intensity, normals }, shift);
        }
        let shift = top_shift(key_limit);
        if key_limit < 1 << 32 {
            sort(keying.all_keys::<u32>(&pts), &mut pts, cloud, shift);
        } else {
            sort(keying.all_keys::<u64>(&pts), &mut pts, cloud, shift);
        }
        // Cell runs, counted first so the arrays take no more than they hold; both passes in
        // parallel over runs of points, each point's key computed once per pass.
        let sorted = &pts[..count];
        let parts: Vec<Range<usize>> =
            (0..count.div_ceil(RUN_CHUNK)).map(|i| i * RUN_CHUNK..((i + 1) * RUN_CHUNK).min(count)).collect();
        // Calls `f(s, key)` for every point `s` of `r` that starts a cell.
        let cell_starts = |r: &Range<usize>, f: &mut dyn FnMut(usize, u64)| {
            let mut prev = r.start.checked_sub(1).map(|s| keying.key(&sorted[s]));
            let mut batch = [0u64; KEY_BATCH];
            let mut at = r.start;
            for part in sorted[r.clone()].chunks(KEY_BATCH) {
                let keys = &mut batch[..part.len()];
                simd::keys(&keying, part, keys);
                for (s, &k) in (at..).zip(keys.iter()) {
                    if prev != Some(k) {
                        f(s, k);
                    }
                    prev = Some(k);
                }
                at += part.len();
            }
        };
        let counts: Vec<usize> = parts
            .par_iter()
            .map(|r| {
                let mut n = 0usize;
                cell_starts(r, &mut |_, _| n += 1);
                n
            })
            .collect();
        let cells_n: usize = counts.iter().sum();
        let (mut keys, mut starts) = (vec![0u64; cells_n], vec![0u32; cells_n + 1]);
        let part_cells: Vec<Range<usize>> = counts
            .iter()
            .scan(0usize, |at, &c| {
                *at += c;
                Some(*at - c..*at)
            })
            .collect();
        split_ranges_mut(&mut keys, &part_cells)
            .into_par_iter()
            .zip(split_ranges_mut(&mut starts[..cells_n], &part_cells))
            .zip(&parts)
            .for_each(|((ks, ss), r)| {
                let mut i = 0usize;
                cell_starts(r, &mut |s, k| {
                    ks[i] = k;
                    ss[i] = s as u32;
                    i += 1;
                });
            });
        starts[cells_n] = count as u32;
        pts.truncate(count);
        if let Some(v) = &mut cloud.intensity {
            v.truncate(count);
        }
        if let Some(v) = &mut cloud.normals {
            v.truncate(count);
        }
        if kd_cells {
            let big: Vec<Range<usize>> = (0..keys.len())
                .map(|c| starts[c] as usize..starts[c + 1] as usize)
                .filter(|r| r.len() > LEAF)
                .collect();
            let intensity = split_ranges_opt(cloud.intensity.as_deref_mut(), &big);
            let normals = split_ranges_opt(cloud.normals.as_deref_mut(), &big);
            split_ranges_mut(&mut pts, &big).into_par_iter().zip(intensity).zip(normals).for_each(
                |((xyz, intensity), normals)| {
                    let mut order: Vec<(Xyz, usize)> = xyz.iter().copied().zip(0..).collect();
                    kd_order(&mut order);
                    for (x, (p, _)) in xyz.iter_mut().zip(&order) {
                        *x = *p;
                    }
                    if let Some(v) = intensity {
                        let was = v.to_vec();
                        for (x, &(_, i)) in v.iter_mut().zip(&order) {
                            *x = was[i];
                        }
                    }
                    if let Some(v) = normals {
                        let was = v.to_vec();
                        for (x, &(_, i)) in v.iter_mut().zip(&order) {
                            *x = was[i];
                        }
                    }
                },
            );
        }
        Grid { origin, h, dims, zbits, tol: bbox.tol, keys, starts, xyz: pts, order: Vec::new() }
    }

    /// The grid of edge `h`; with `kd_cells`, cells of more than [`LEAF`] points are put in
    /// [`kd_order`] (for [`Bvh`] leaves).
    fn build(points: &[Point3<f32>], bbox: &UsableBox, h: f64, kd_cells: bool) -> Grid {
        let h = if h.is_finite() && h > 0.0 { h } else { 1.0 };
        let inv_h = 1.0 / h;
        let dims = grid_dims(bbox, inv_h);
        let origin = bbox.lo;
        let zbits = z_bits(dims[2]);
        let key_of = |p: &Point3<f32>| cell_key(cell_of(&wide(p), &origin, inv_h, &dims), zbits);
        // Every key is below this (all-ones x and y bits, then z).
        let key_limit =
            cell_key([dims[0].next_power_of_two() - 1, dims[1].next_power_of_two() - 1, 0], zbits)
                + (1 << zbits);
        let mut keys = Vec::new();
        let mut starts = Vec::new();
        let mut add_cell = |s: usize, key: u64| {
            if keys.last() != Some(&key) {
                keys.push(key);
                starts.push(s as u32);
            }
        };
        // Original indices sorted by (cell key, index).
        let mut order: Vec<usize> = if key_limit < 1 << 32 && points.len() <= 1 << 32 {
            // (key << 32) | index, radix-sorted on the key bits; unusable points get the key
            // `key_limit`, which sorts after every real key, and are cut off.
            let mut items: Vec<u64> = points
                .par_iter()
                .enumerate()
                .map(|(i, p)| (if usable(p) { key_of(p) } else { key_limit } << 32) | i as u64)
                .collect();
            let key_bits = 64 - key_limit.leading_zeros();
            radix_sort_bits(&mut items, 32, key_bits);
            items.truncate(bbox.count);
            items.iter().enumerate().for_each(|(s, &v)| add_cell(s, v >> 32));
            items.into_par_iter().map(|v| (v & 0xFFFF_FFFF) as usize).collect()
        } else {
            let mut pairs: Vec<(u64, usize)> = points
                .par_iter()
                .enumerate()
                .filter(|(_, p)| usable(*p))
                .map(|(i, p)| (key_of(p), i))
                .collect();
            pairs.par_sort_unstable();
            pairs.iter().enumerate().for_each(|(s, &(key, _))| add_cell(s, key));
            pairs.into_par_iter().map(|(_, i)| i).collect()
        };
        starts.push(order.len() as u32);
        let mut xyz: Vec<Xyz> = order.par_iter().map(|&i| points[i]).collect();
        if kd_cells {
            let big: Vec<Range<usize>> = (0..keys.len())
                .map(|c| starts[c] as usize..starts[c + 1] as usize)
                .filter(|r| r.len() > LEAF)
                .collect();
            split_ranges_mut(&mut xyz, &big)
                .into_par_iter()
                .zip(split_ranges_mut(&mut order, &big))
                .for_each(|(xyz, order)| {
                    let mut pts: Vec<(Xyz, usize)> = xyz.iter().copied().zip(order.iter().copied()).collect();
                    kd_order(&mut pts);
                    for ((x, o), (p, i)) in xyz.iter_mut().zip(order.iter_mut()).zip(pts) {
                        *x = p;
                        *o = i;
                    }
                });
        }
        Grid { origin, h, dims, zbits, tol: bbox.tol, keys, starts, xyz, order }
    }

    /// Where cell `c`'s points start in `xyz` (`c` up to the number of cells).
    #[inline(always)]
    fn start(&self, c: usize) -> usize {
        self.starts[c] as usize
    }

    fn coords(&self, key: u64) -> [u64; 3] {
        let column = key >> self.zbits;
        [compact2(column), compact2(column >> 1), key & ((1 << self.zbits) - 1)]
    }

    /// The first cell whose key is at least `target`, searched outwards from cell `from`
    /// (galloping: cost logarithmic in the distance).
    fn seek(&self, from: usize, target: u64) -> usize {
        let keys = &self.keys;
        let from = from.min(keys.len());
        if from < keys.len() && keys[from] < target {
            let mut lo = from; // keys[lo] < target
            let mut step = 1;
            while lo + step < keys.len() && keys[lo + step] < target {
                lo += step;
                step *= 2;
            }
            let hi = (lo + step).min(keys.len());
            lo + 1 + keys[lo + 1..hi].partition_point(|&k| k < target)
        } else {
            // keys[from] >= target (or from == len): go back.
            let mut hi = from;
            let mut step = 1;
            while hi >= step && keys[hi - step] >= target {
                hi -= step;
                step *= 2;
            }
            let lo = hi.saturating_sub(step);
            lo + keys[lo..hi].partition_point(|&k| k < target)
        }
    }

    /// Ranges of cells holding about [`CHUNK_POINTS`] points each.
    fn chunks(&self) -> Vec<Range<usize>> {
        let mut out = Vec::new();
        let mut first = 0usize;
        for c in 0..self.keys.len() {
            if self.start(c + 1) - self.start(first) >= CHUNK_POINTS {
                out.push(first..c + 1);
                first = c + 1;
            }
        }
        if first < self.keys.len() {
            out.push(first..self.keys.len());
        }
        out
    }

    /// The point ranges of the block of cells within `ring` cells of cell `c` (3 × 3 × 3 for
    /// ring 1): one run per column, its own column first.
    fn block_ranges(&self, c: usize, ring: u64, out: &mut Vec<Range<usize>>) {
        out.clear();
        let [cx, cy, cz] = self.coords(self.keys[c]);
        let z0 = cz.saturating_sub(ring);
        let z1 = (cz + ring).min(self.dims[2] - 1);
        let r = ring as i64;
        let offsets = std::iter::once(0).chain((-r..=r).filter(|&o| o != 0));
        for dx in offsets.clone() {
            let Some(x) = cx.checked_add_signed(dx).filter(|&x| x < self.dims[0]) else { continue };
            for dy in offsets.clone() {
                let Some(y) = cy.checked_add_signed(dy).filter(|&y| y < self.dims[1]) else { continue };
                let lo_key = cell_key([x, y, z0], self.zbits);
                let hi_key = cell_key([x, y, z1], self.zbits);
                let first = self.seek(c, lo_key);
                let mut last = first;
                while last < self.keys.len() && self.keys[last] <= hi_key {
                    last += 1;
                }
                if last > first {
                    out.push(self.start(first)..self.start(last));
                }
            }
        }
    }

    /// [`Grid::block_ranges`] through a column table when there is one: the same ranges in the
    /// same order, each column found at once instead of by a search.
    #[inline(always)]
    fn block_ranges_with(&self, columns: Option<&Columns>, c: usize, ring: u64, out: &mut Vec<Range<usize>>) {
        let Some(columns) = columns else {
            self.block_ranges(c, ring, out);
            return;
        };
        out.clear();
        let [cx, cy, cz] = self.coords(self.keys[c]);
        let z0 = cz.saturating_sub(ring);
        let z1 = (cz + ring).min(self.dims[2] - 1);
        let zmask = (1u64 << self.zbits) - 1;
        let r = ring as i64;
        let offsets = std::iter::once(0).chain((-r..=r).filter(|&o| o != 0));
        for dx in offsets.clone() {
            let Some(x) = cx.checked_add_signed(dx).filter(|&x| x < self.dims[0]) else { continue };
            for dy in offsets.clone() {
                let Some(y) = cy.checked_add_signed(dy).filter(|&y| y < self.dims[1]) else { continue };
                let Some(mut first) = columns.first(x, y) else { continue };
                let column = self.keys[first] >> self.zbits;
                while first < self.keys.len()
                    && self.keys[first] >> self.zbits == column
                    && self.keys[first] & zmask < z0
                {
                    first += 1;
                }
                let mut last = first;
                while last < self.keys.len()
                    && self.keys[last] >> self.zbits == column
                    && self.keys[last] & zmask <= z1
                {
                    last += 1;
                }
                if last > first {
                    out.push(self.start(first)..self.start(last));
                }
            }
        }
    }

    /// A lower bound on the distance from `q` (in the cell at `cell`) to any point outside the
    /// block of cells within `ring` of it (infinite towards sides where the grid ends).
    fn block_margin(&self, cell: [u64; 3], ring: u64, q: &Xyz) -> f64 {
        self.block_walls(cell, ring).margin(q)
    }

    /// The share of [`PROBE_POINTS`] queries spread evenly over the grid's points whose `k`
    /// nearest do not provably lie in their 3 × 3 × 3 block (fewer than `k` points within its
    /// margin): those the batch passes on to the 5 × 5 × 5 block or the hierarchy.
    fn probe_failures(&self, k: usize) -> f64 {
        let n = self.xyz.len();
        if n == 0 {
            return 0.0;
        }
        let step = (n / PROBE_POINTS).max(1);
        let mut ranges = Vec::new();
        let (mut tried, mut failed) = (0usize, 0usize);
        for s in (0..n).step_by(step) {
            let c = self.starts.partition_point(|&st| st as usize <= s) - 1;
            self.block_ranges(c, 1, &mut ranges);
            let p = &self.xyz[s];
            let m = self.block_walls(self.coords(self.keys[c]), 1).margin(p);
            tried += 1;
            let m2 = m * m;
            let within = if m > 0.0 {
                ranges.iter().flat_map(|r| &self.xyz[r.clone()]).filter(|q| dist2(p, q) <= m2).count()
            } else {
                0
            };
            failed += usize::from(within < k);
        }
        failed as f64 / tried as f64
    }

    /// The walls of the block of cells within `ring` of `cell`, for [`Walls::margin`] (one per
    /// cell serves all its points).
    #[inline(always)]
    fn block_walls(&self, cell: [u64; 3], ring: u64) -> Walls {
        let mut w =
            Walls { lo: [f64::NEG_INFINITY; 3], hi: [f64::INFINITY; 3], slack: 1e-6 * self.h + self.tol };
        for (a, &c) in cell.iter().enumerate() {
            if c >= ring {
                w.lo[a] = self.origin[a] + (c - ring) as f64 * self.h;
            }
            if c + ring < self.dims[a] {
                w.hi[a] = self.origin[a] + (c + ring + 1) as f64 * self.h;
            }
        }
        w
    }
}

/// The walls of a block of cells (infinite towards sides where the grid ends) and the slack
/// [`Walls::margin`] takes off for rounding.
#[derive(Debug, Clone, Copy)]
struct Walls {
    lo: [f64; 3],
    hi: [f64; 3],
    slack: f64,
}

impl Walls {
    /// A lower bound on the distance from `q` (inside the block) to any point outside it.
    #[inline(always)]
    fn margin(&self, q: &Xyz) -> f64 {
        let q = wide(q);
        let m = (q[0] - self.lo[0])
            .min(self.hi[0] - q[0])
            .min((q[1] - self.lo[1]).min(self.hi[1] - q[1]))
            .min((q[2] - self.lo[2]).min(self.hi[2] - q[2]));
        m - self.slack
    }
}

/// The first cell of every column of a grid, for grids whose columns are not many more than
/// their cells (a table no larger than the cell keys).
struct Columns {
    ny: u64,
    /// Cell index of column `(x, y)`'s lowest cell at `x · ny + y`; `u32::MAX` for an empty one.
    first: Vec<u32>,
}

impl Columns {
    fn build(grid: &Grid) -> Option<Columns> {
        let [nx, ny, _] = grid.dims;
        let size = nx.checked_mul(ny)?;
        if size > (2 * grid.keys.len()) as u64 || grid.keys.len() >= u32::MAX as usize {
            return None;
        }
        let mut first = vec![u32::MAX; size as usize];
        for (c, &key) in grid.keys.iter().enumerate() {
            let [x, y, _] = grid.coords(key);
            let slot = &mut first[(x * ny + y) as usize];
            if *slot == u32::MAX {
                *slot = c as u32;
            }
        }
        Some(Columns { ny, first })
    }

    #[inline(always)]
    fn first(&self, x: u64, y: u64) -> Option<usize> {
        let c = self.first[(x * self.ny + y) as usize];
        (c != u32::MAX).then_some(c as usize)
    }
}

/// [`split_ranges_mut`] of an optional array: `None` for every range without it.
fn split_ranges_opt<'a, T>(data: Option<&'a mut [T]>, ranges: &[Range<usize>]) -> Vec<Option<&'a mut [T]>> {
    match data {
        Some(v) => split_ranges_mut(v, ranges).into_iter().map(Some).collect(),
        None => ranges.iter().map(|_| None).collect(),
    }
}

/// Disjoint mutable slices of `data` for `ranges` (ascending, non-overlapping).
fn split_ranges_mut<'a, T>(mut data: &'a mut [T], ranges: &[Range<usize>]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(ranges.len());
    let mut at = 0usize;
    for r in ranges {
        let (_, rest) = data.split_at_mut(r.start - at);
        let (mine, rest) = rest.split_at_mut(r.len());
        out.push(mine);
        data = rest;
        at = r.end;
    }
    out
}

/// Splits `out` (one entry per sorted point) into one slice per chunk of cells.
fn split_by_chunks<'a, T>(out: &'a mut [T], grid: &Grid, chunks: &[Range<usize>]) -> Vec<&'a mut [T]> {
    let ranges: Vec<Range<usize>> = chunks.iter().map(|r| grid.start(r.start)..grid.start(r.end)).collect();
    split_ranges_mut(out, &ranges)
}

/// The `k` smallest squared distances offered so far (a multiset: ties need no tie-break),
/// kept lazily: offers below the bound are appended, and when the buffer fills the `k` smallest
/// are selected and the bound drops to the k-th (so an offer costs an append, not an insertion).
#[derive(Debug)]
struct KBest {
    k: usize,
    d: Vec<f64>,
    /// Values not below this cannot be among the `k` smallest (`+inf` until `k` are in).
    bound: f64,
}

impl KBest {
    fn new(k: usize) -> Self {
        let k = k.max(1);
        KBest { k, d: Vec::with_capacity(Self::cap(k)), bound: f64::INFINITY }
    }

    /// Buffer length at which the k smallest are selected.
    fn cap(k: usize) -> usize {
        4 * k + 32
    }

    fn reset(&mut self) {
        self.d.clear();
        self.bound = f64::INFINITY;
    }

    /// Starts over with a bound the caller knows lies above the `k` smallest values to come.
    fn reset_below(&mut self, bound: f64) {
        self.d.clear();
        self.bound = bound;
    }

    /// Values not below this cannot enter.
    #[inline(always)]
    fn worst(&self) -> f64 {
        self.bound
    }

    /// Offers `x`; the caller has checked `x < self.worst()`.
    #[inline(always)]
    fn push(&mut self, x: f64) {
        self.d.push(x);
        if self.d.len() >= Self::cap(self.k) {
            self.shrink();
        }
    }

    /// Keeps the `k` smallest; the bound becomes the k-th.
    fn shrink(&mut self) {
        if self.d.len() >= self.k {
            let k = self.k;
            self.d.select_nth_unstable_by(k - 1, f64::total_cmp);
            self.d.truncate(k);
            self.bound = self.d[k - 1];
        }
    }

    /// Mean of the square roots of the `k` smallest (all of them when fewer were offered),
    /// summed in ascending order.
    fn mean_distance(&mut self) -> f64 {
        if self.d.len() > self.k {
            self.shrink();
        }
        self.d.sort_unstable_by(f64::total_cmp);
        mean_sqrt(self.d.iter().copied())
    }
}

/// `Σ sqrt(v) / count`, summed in the given order (the callers give ascending order).
#[inline]
fn mean_sqrt(vals: impl ExactSizeIterator<Item = f64>) -> f64 {
    let n = vals.len();
    let mut sum = 0.0f64;
    for v in vals {
        sum += v.sqrt();
    }
    sum / n as f64
}

/// An axis-aligned box of points, in their own single precision (the bounds of `f32` values are
/// `f32` values: exact).
#[derive(Debug, Clone, Copy)]
struct Box3 {
    lo: [f32; 3],
    hi: [f32; 3],
}

impl Box3 {
    fn of(pts: &[Xyz]) -> Box3 {
        let mut b = Box3 { lo: [f32::INFINITY; 3], hi: [f32::NEG_INFINITY; 3] };
        for p in pts {
            for ((lo, hi), c) in b.lo.iter_mut().zip(b.hi.iter_mut()).zip([p.x, p.y, p.z]) {
                *lo = lo.min(c);
                *hi = hi.max(c);
            }
        }
        b
    }

    fn union(&self, o: &Box3) -> Box3 {
        Box3 {
            lo: [self.lo[0].min(o.lo[0]), self.lo[1].min(o.lo[1]), self.lo[2].min(o.lo[2])],
            hi: [self.hi[0].max(o.hi[0]), self.hi[1].max(o.hi[1]), self.hi[2].max(o.hi[2])],
        }
    }

    /// Squared distance from `q` to the box, summed x, y, z like [`dist2`] so that it never
    /// exceeds the computed distance to a point inside.
    fn dist2(&self, q: &Xyz) -> f64 {
        let q = wide(q);
        let e = |a: usize| (f64::from(self.lo[a]) - q[a]).max(q[a] - f64::from(self.hi[a])).max(0.0);
        let (ex, ey, ez) = (e(0), e(1), e(2));
        ex * ex + ey * ey + ez * ez
    }
}

/// A subtree of at most this many points becomes one leaf of the hierarchy.
const LEAF_MAX: usize = 24;

#[derive(Debug, Clone)]
struct BvhNode {
    bounds: Box3,
    /// The subtree's points: `pts[points]`.
    points: Range<usize>,
    /// A leaf holding left-out cells: the grid's cells to scan one run at a time (empty
    /// otherwise).
    mixed: Range<usize>,
    /// Index of the right child (the left child follows the node); 0 for a leaf.
    right: usize,
}

/// Subtrees of more points than this are built in parallel.
const BVH_PARALLEL: usize = 1 << 16;

/// A bounding-volume hierarchy over a [`Grid`]'s points, in the grid's own order (no copy). A
/// node covers a run of cells with a common key prefix ([`cell_key`]: a box of columns and
/// layers, so its points are contiguous) and splits it where the highest differing key bit
/// changes; a run of one big cell (kd-ordered) splits where [`kd_order`] split it. Subtrees of
/// at most `leaf_max` points are leaves; the bounds are the points' own. Built in O(n); used for
/// the k-NN queries the grid cannot answer.
///
/// Cells marked in `skip` are left out (their points neither bound nor get scanned): the grid's
/// isolated cells, which a second hierarchy over a copy of their points holds instead (see
/// [`grid_knn`]). Left in, one stray point in a run of surface cells stretches every box above
/// the run to its height, and a query above the surface then opens every leaf along its way
/// down.
struct Bvh<'g> {
    pts: &'g [Xyz],
    /// Preorder.
    nodes: Vec<BvhNode>,
    /// Where each cell's points start (the grid's `starts`).
    starts: &'g [u32],
    /// One bit per cell left out.
    skip: Option<&'g [u64]>,
}

/// Whether bit `c` of `bits` is set.
#[inline(always)]
fn bit(bits: &[u64], c: usize) -> bool {
    bits[c / 64] >> (c % 64) & 1 == 1
}

impl<'g> Bvh<'g> {
    fn build(grid: &'g Grid, leaf_max: usize, skip: Option<&'g [u64]>) -> Bvh<'g> {
        let leaf_max = leaf_max.max(LEAF);
        let cells = grid.keys.len();
        let nodes = if cells == 0 {
            Vec::new()
        } else {
            Self::build_par(grid, 0..cells, 0..grid.xyz.len(), leaf_max, skip)
        };
        Bvh { pts: &grid.xyz, nodes, starts: &grid.starts, skip }
    }

    /// Where to split a node of `cells` holding `points` (more than a leaf): (left cells, left
    /// points, right cells, right points).
    #[allow(clippy::type_complexity)]
    fn split(
        grid: &Grid,
        cells: &Range<usize>,
        points: &Range<usize>,
    ) -> ((Range<usize>, Range<usize>), (Range<usize>, Range<usize>)) {
        if cells.len() == 1 {
            // One big cell in kd order: its kd splits.
            let mid = points.start + LEAF * points.len().div_ceil(2 * LEAF);
            ((cells.clone(), points.start..mid), (cells.clone(), mid..points.end))
        } else {
            let keys = &grid.keys[cells.clone()];
            let bit = 63 - (keys[0] ^ keys[keys.len() - 1]).leading_zeros();
            let c = cells.start + keys.partition_point(|k| (k >> bit) & 1 == 0);
            let p = grid.start(c);
            ((cells.start..c, points.start..p), (c..cells.end, p..points.end))
        }
    }

    /// Builds the subtree in preorder; big subtrees in parallel.
    fn build_par(
        grid: &Grid,
        cells: Range<usize>,
        points: Range<usize>,
        leaf_max: usize,
        skip: Option<&[u64]>,
    ) -> Vec<BvhNode> {
        if points.len() <= BVH_PARALLEL {
            let mut nodes = Vec::with_capacity(2 * points.len().div_ceil(LEAF));
            Self::build_seq(grid, cells, points, leaf_max, skip, &mut nodes);
            return nodes;
        }
        let ((lc, lp), (rc, rp)) = Self::split(grid, &cells, &points);
        let (left, right) = rayon::join(
            || Self::build_par(grid, lc, lp, leaf_max, skip),
            || Self::build_par(grid, rc, rp, leaf_max, skip),
        );
        let bounds = left[0].bounds.union(&right[0].bounds);
        let right_at = 1 + left.len();
        let mut nodes = Vec::with_capacity(right_at + right.len());
        nodes.push(BvhNode { bounds, points, mixed: 0..0, right: right_at });
        let shift = |off: usize| {
            move |mut n: BvhNode| {
                if n.right != 0 {
                    n.right += off;
                }
                n
            }
        };
        nodes.extend(left.into_iter().map(shift(1)));
        nodes.extend(right.into_iter().map(shift(right_at)));
        nodes
    }

    fn build_seq(
        grid: &Grid,
        cells: Range<usize>,
        points: Range<usize>,
        leaf_max: usize,
        skip: Option<&[u64]>,
        nodes: &mut Vec<BvhNode>,
    ) -> Box3 {
        let me = nodes.len();
        if points.len() <= leaf_max {
            // A run of one big cell (part of it) is never left out: only small cells are.
            let mixed = skip.is_some_and(|b| cells.clone().any(|c| bit(b, c)));
            if mixed {
                let mut bounds = Box3::of(&[]);
                for c in cells.clone() {
                    if !skip.is_some_and(|b| bit(b, c)) {
                        bounds = bounds.union(&Box3::of(&grid.xyz[grid.start(c)..grid.start(c + 1)]));
                    }
                }
                nodes.push(BvhNode { bounds, points, mixed: cells, right: 0 });
                return bounds;
            }
            let bounds = Box3::of(&grid.xyz[points.clone()]);
            nodes.push(BvhNode { bounds, points, mixed: 0..0, right: 0 });
            return bounds;
        }
        let ((lc, lp), (rc, rp)) = Self::split(grid, &cells, &points);
        nodes.push(BvhNode { bounds: Box3::of(&[]), points, mixed: 0..0, right: 0 });
        let left = Self::build_seq(grid, lc, lp, leaf_max, skip, nodes);
        nodes[me].right = nodes.len();
        let right = Self::build_seq(grid, rc, rp, leaf_max, skip, nodes);
        let bounds = left.union(&right);
        nodes[me].bounds = bounds;
        bounds
    }

    /// The `k` nearest of `q` into `best`; `AVX512` scans the leaves with the vector kernel
    /// (set only where the CPU has AVX-512F, see [`simd::has_avx512`]).
    fn knn<const AVX512: bool>(&self, q: &Xyz, best: &mut KBest) {
        if !self.nodes.is_empty() {
            self.visit::<AVX512>(0, q, best);
        }
    }

    fn visit<const AVX512: bool>(&self, node: usize, q: &Xyz, best: &mut KBest) {
        let n = &self.nodes[node];
        if n.right == 0 {
            match self.skip {
                Some(skip) if !n.mixed.is_empty() => {
                    // The runs of cells kept.
                    let mut c = n.mixed.start;
                    while c < n.mixed.end {
                        if bit(skip, c) {
                            c += 1;
                            continue;
                        }
                        let from = c;
                        while c < n.mixed.end && !bit(skip, c) {
                            c += 1;
                        }
                        let run = self.starts[from] as usize..self.starts[c] as usize;
                        simd::leaf_scan::<AVX512>(&self.pts[run], q, best);
                    }
                }
                _ => simd::leaf_scan::<AVX512>(&self.pts[n.points.clone()], q, best),
            }
            return;
        }
        let (a, b) = (node + 1, n.right);
        let (da, db) = (self.nodes[a].bounds.dist2(q), self.nodes[b].bounds.dist2(q));
        let ((first, d_first), (second, d_second)) =
            if da <= db { ((a, da), (b, db)) } else { ((b, db), (a, da)) };
        if d_first < best.worst() {
            self.visit::<AVX512>(first, q, best);
        }
        if d_second < best.worst() {
            self.visit::<AVX512>(second, q, best);
        }
    }
}

/// Queries [`Grid::probe_failures`] tries.
const PROBE_POINTS: usize = 512;
/// Share of probed queries the 3 × 3 × 3 block cannot answer above which the grid is built once
/// more with cells [`GROW`] times larger: the cell edge is sized on the pairs of points in a cell,
/// which the dense parts of a cloud dominate, and a scan's density varies (lines, depth layers),
/// so its sparse parts can miss the block. On the synthetic surface about 2 % miss; on the real
/// scans of the parts set 25 to 70 %.
const PROBE_FAIL: f64 = 0.15;
/// How much larger the cells of the second build are.
const GROW: f64 = 1.6;

/// Sample size for choosing the k-NN cell edge.
const SAMPLE: usize = 1 << 14;

/// SplitMix64: a small deterministic generator for sampling.
fn splitmix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// Points per cell aimed at for `k` neighbours on data of local dimension `d` (1 to 3): the
/// k-th neighbour then lies at about 0.9 cell edges, inside the block's margin (at least one
/// edge) for nearly every query, while the block holds few candidates (~4k on a surface).
fn knn_target(k: usize, d: f64) -> f64 {
    let per_k = if d <= 2.0 { 0.55 - 0.15 * (d - 1.0) } else { 0.4 - 0.07 * (d - 2.0) };
    (k as f64 * per_k).max(2.0)
}

/// A cell edge for which a typical point's cell holds about [`knn_target`] points (itself
/// included), estimated on a random sample: pairs of sample points sharing a cell, scaled by the
/// inverse sampling fraction squared, not counting pairs of identical points (a heap of exact
/// duplicates would otherwise shrink the cells for everyone). The local dimension (population ∝
/// edge^d) is estimated from successive trials, starting from surfaces (d = 2).
fn knn_cell_size(points: &[Point3<f32>], bbox: &UsableBox, k: usize) -> f64 {
    let n = points.len();
    // Distinct indices: all of them for small clouds, else uniformly random ones (a stratified or
    // strided sample would under-count pairs in scan-ordered clouds).
    let mut idx: Vec<usize> = if n <= SAMPLE {
        (0..n).collect()
    } else {
        (0..SAMPLE as u64).map(|j| (splitmix(j) % n as u64) as usize).collect()
    };
    idx.sort_unstable();
    idx.dedup();
    let sample: Vec<[f64; 3]> = idx.iter().map(|&i| &points[i]).filter(|p| usable(*p)).map(wide).collect();
    let h_min = bbox.min_cell();
    let m = bbox.count as f64;
    let s = sample.len();
    if s < 2 {
        return h_min.max(1.0);
    }
    let mut d = 2.0f64;
    // Start: the area of the largest face of the central 98 % box.
    let mut ext = [0.0f64; 3];
    let mut coord = Vec::with_capacity(s);
    for (a, e) in ext.iter_mut().enumerate() {
        coord.clear();
        coord.extend(sample.iter().map(|p| p[a]));
        coord.sort_unstable_by(f64::total_cmp);
        *e = coord[s - 1 - s / 100] - coord[s / 100];
    }
    ext.sort_unstable_by(|a, b| b.total_cmp(a));
    let target = knn_target(k, d);
    let mut h = if ext[1] > 0.0 {
        (target * ext[0] * ext[1] / m).sqrt()
    } else if ext[0] > 0.0 {
        target * ext[0] / m
    } else {
        bbox.max_extent() / 2.0
    };
    if !(h.is_finite() && h > 0.0) {
        h = 1.0;
    }
    h = h.max(h_min);
    let mut keyed: Vec<(u64, [u64; 3])> = Vec::with_capacity(s);
    let mut previous: Option<(f64, f64)> = None; // (edge, population − 1)
    for _ in 0..8 {
        let inv_h = 1.0 / h;
        let dims = grid_dims(bbox, inv_h);
        let zbits = z_bits(dims[2]);
        keyed.clear();
        keyed.extend(
            sample.iter().map(|p| (cell_key(cell_of(p, &bbox.lo, inv_h, &dims), zbits), p.map(f64::to_bits))),
        );
        keyed.sort_unstable();
        // Pairs in a cell minus pairs of identical points.
        let mut pairs = 0.0f64;
        let (mut run, mut same) = (1.0f64, 1.0f64);
        for j in 1..=s {
            let same_cell = j < s && keyed[j].0 == keyed[j - 1].0;
            if same_cell && keyed[j].1 == keyed[j - 1].1 {
                same += 1.0;
            } else {
                pairs -= same * (same - 1.0);
                same = 1.0;
            }
            if same_cell {
                run += 1.0;
            } else {
                pairs += run * (run - 1.0);
                run = 1.0;
            }
        }
        let excess = pairs * (m - 1.0) / (s as f64 * (s as f64 - 1.0)).max(1.0);
        if let Some((h0, e0)) = previous
            && e0 > 0.0
            && excess > 0.0
            && (h / h0 - 1.0).abs() > 0.05
        {
            d = ((excess / e0).ln() / (h / h0).ln()).clamp(1.0, 3.0);
        }
        previous = Some((h, excess));
        let ratio = if excess > 0.0 { (knn_target(k, d) - 1.0) / excess } else { 64.0 };
        if (0.85..=1.18).contains(&ratio) || (ratio < 1.0 && h <= h_min) {
            break;
        }
        h = (h * ratio.powf(1.0 / d).clamp(0.25, 4.0)).max(h_min);
    }
    h
}

/// Per-point k-NN mean distances (`NaN` for unusable points); see [`knn_mean_distances`].
fn knn_means(points: &[Point3<f32>], k: usize) -> Vec<f64> {
    knn_means_with_stats(points, k).0
}

/// How the k-NN queries were answered.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct KnnStats {
    /// Answered from the grid block (3 × 3 × 3 or 5 × 5 × 5).
    grid: usize,
    /// Of those, answered from the 5 × 5 × 5 block.
    second_chance: usize,
    /// Answered by the hierarchy (isolated points, sparse regions, overfull blocks).
    tree: usize,
    /// Cells whose block was overfull.
    overfull_cells: usize,
    /// Points of isolated cells searched in a hierarchy of their own (see [`grid_knn`]).
    stragglers: usize,
    /// Whether the grid was built again with larger cells (see [`PROBE_FAIL`]).
    grown: bool,
}

/// Threshold factor on the previous query's k-th squared distance (about 1.12 in distance): on
/// a scanned surface ~24 points pass for k = 20 and 1 % of the queries need a second pass.
const HINT_FACTOR: f64 = 1.25;

/// Entries a filter buffer holds beyond the block's points (the vector kernel stores whole
/// vectors past the last kept value).
const FILTER_SLACK: usize = 8;

/// The points of a block of cells, coordinate by coordinate, widened to `f64` (exactly): what
/// the distance kernels read. One pack serves every query of a cell.
#[derive(Debug, Default)]
struct Packed {
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
}

impl Packed {
    #[inline(always)]
    fn fill(&mut self, xyz: &[Xyz], ranges: &[Range<usize>]) {
        self.size_for(ranges);
        let mut at = 0usize;
        for r in ranges {
            let to = at + r.len();
            let dest = self.x[at..to].iter_mut().zip(&mut self.y[at..to]).zip(&mut self.z[at..to]);
            for (p, ((x, y), z)) in xyz[r.clone()].iter().zip(dest) {
                *x = f64::from(p.x);
                *y = f64::from(p.y);
                *z = f64::from(p.z);
            }
            at = to;
        }
    }

    /// Room for the points of `ranges`, coordinate by coordinate (zeroed).
    #[inline(always)]
    fn size_for(&mut self, ranges: &[Range<usize>]) {
        let n: usize = ranges.iter().map(|r| r.len()).sum();
        for v in [&mut self.x, &mut self.y, &mut self.z] {
            v.clear();
            v.resize(n, 0.0);
        }
    }

    fn len(&self) -> usize {
        self.x.len()
    }
}

/// Writes the bit patterns of the squared distances from `q` to the block's points (which order
/// like the non-negative values) that are at most `t2` to the front of `buf`, in the points'
/// order, and returns how many there are. Each squared distance is [`dist2`]'s, bit for bit.
/// `buf` holds at least `block.len() + FILTER_SLACK` entries.
#[inline(always)]
fn filter_portable(block: &Packed, q: &[f64; 3], t2: f64, buf: &mut [u64]) -> usize {
    let mut cnt = 0usize;
    for ((&x, &y), &z) in block.x.iter().zip(&block.y).zip(&block.z) {
        let (dx, dy, dz) = (q[0] - x, q[1] - y, q[2] - z);
        let d = dx * dx + dy * dy + dz * dz;
        buf[cnt] = d.to_bits();
        cnt += usize::from(d <= t2);
    }
    cnt
}

/// How the mean of the `k` nearest distances is summed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SumOrder {
    /// In ascending order of distance, like Open3D (the same value to the last bit).
    Ascending,
    /// In any order (within `k` rounding errors of the ascending sum): for callers that
    /// tolerate that and measure again near their threshold.
    Any,
}

/// With [`SumOrder::Any`], up to this many surplus values are stepped over from the top (more
/// go through a selection).
const DROP_MAX: usize = 16;

/// Brings the `k` smallest of the `cnt ≥ k` filtered values to the front of `buf` (ascending
/// with [`SumOrder::Ascending`]); returns the k-th squared distance and the mean distance.
#[inline(always)]
fn finish_knn<const AVX512: bool>(
    buf: &mut [u64],
    cnt: usize,
    k: usize,
    order: SumOrder,
    hint2: f64,
) -> (f64, f64) {
    let v = &mut buf[..cnt];
    if order == SumOrder::Any && cnt - k <= DROP_MAX {
        let lower = if hint2.is_finite() { (hint2 * TOP_FRACTION).to_bits() } else { 0 };
        return simd::finish_any::<AVX512>(v, k, lower);
    }
    if order == SumOrder::Ascending && cnt <= 2 * k + 8 {
        v.sort_unstable();
    } else {
        v.select_nth_unstable(k - 1);
        if order == SumOrder::Ascending {
            v[..k].sort_unstable();
        }
    }
    let best = &buf[..k];
    let kth2 = f64::from_bits(best[k - 1]);
    // Square roots in a separate pass (vectorised), then the sum.
    let mut roots = [0.0f64; 32];
    let mut sum = 0.0f64;
    for part in best.chunks(32) {
        for (r, &b) in roots.iter_mut().zip(part) {
            *r = f64::from_bits(b).sqrt();
        }
        for &r in &roots[..part.len()] {
            sum += r;
        }
    }
    (kth2, sum / k as f64)
}

/// [`finish_any_portable`]'s short list: at most this many values above the lower bound.
const TOP_MAX: usize = 16;

/// The short list's lower bound, relative to the previous query's k-th squared distance.
const TOP_FRACTION: f64 = 0.9;

/// [`finish_knn`] in any order for a few surplus values. The square roots of all values are
/// summed (eight lanes) while the values above `lower` are listed; when there are more of those
/// than the surplus but at most [`TOP_MAX`], they hold the largest, sorted, which give the
/// k-th and the roots to take off. Otherwise [`finish_steps_portable`]. Any `lower` is correct
/// (the caller's guess below the k-th: a fraction of the previous query's).
#[inline(always)]
fn finish_any_portable(v: &[u64], k: usize, lower: u64) -> (f64, f64) {
    let surplus = v.len() - k;
    let mut top = [0u64; TOP_MAX];
    let mut listed = 0usize;
    let mut acc = [0.0f64; 8];
    for (i, &x) in v.iter().enumerate() {
        acc[i % 8] += f64::from_bits(x).sqrt();
        if x > lower {
            if listed < TOP_MAX {
                top[listed] = x;
            }
            listed += 1;
        }
    }
    if listed > surplus && listed <= TOP_MAX {
        let sum = ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]));
        return take_largest(&mut top[..listed], surplus, sum, k);
    }
    finish_steps_portable(v, k)
}

/// The k-th and mean distance from the sum of all roots and a list holding the `surplus + 1`
/// largest values (and maybe more): the `surplus` largest come off the sum.
#[inline(always)]
fn take_largest(top: &mut [u64], surplus: usize, sum: f64, k: usize) -> (f64, f64) {
    // Insertion sort, descending (a short list).
    for i in 1..top.len() {
        let mut j = i;
        while j > 0 && top[j - 1] < top[j] {
            top.swap(j - 1, j);
            j -= 1;
        }
    }
    let cut: f64 = top[..surplus].iter().map(|&x| f64::from_bits(x).sqrt()).sum();
    (f64::from_bits(top[surplus]), (sum - cut) / k as f64)
}

/// [`finish_knn`] in any order for a few surplus values: the k-th smallest found by stepping
/// down from the largest value (each step a vectorised masked maximum and count), then the
/// square roots of the values below it plus the k-th's for the rest, summed in eight lanes.
#[inline(always)]
fn finish_steps_portable(v: &[u64], k: usize) -> (f64, f64) {
    let surplus = v.len() - k;
    // Values above `kth` so far; `kth` steps down through the distinct values.
    let mut above = 0usize;
    let mut kth = u64::MAX;
    loop {
        let top = v.iter().fold(0u64, |a, &x| a.max(if x < kth { x } else { 0 }));
        let ties = v.iter().map(|&x| usize::from(x == top)).sum::<usize>();
        kth = top;
        if above + ties > surplus || top == 0 {
            break;
        }
        above += ties;
    }
    let mut acc = [0.0f64; 8];
    let mut below = 0usize;
    let mut lanes = v.chunks_exact(8);
    for part in &mut lanes {
        for (a, &x) in acc.iter_mut().zip(part) {
            *a += if x < kth { f64::from_bits(x).sqrt() } else { 0.0 };
            below += usize::from(x < kth);
        }
    }
    for (a, &x) in acc.iter_mut().zip(lanes.remainder()) {
        *a += if x < kth { f64::from_bits(x).sqrt() } else { 0.0 };
        below += usize::from(x < kth);
    }
    let kth2 = f64::from_bits(kth);
    let sum = ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]));
    (kth2, (sum + (k - below) as f64 * kth2.sqrt()) / k as f64)
}

/// The k-NN mean of query `q` from its packed block, if its `k` nearest provably lie there:
/// filters to `d² ≤ min(hint2·HINT_FACTOR, margin2)`, then (too few left) to `d² ≤ margin2`.
/// `None` when fewer than `k` points lie within the margin. Returns (k-th squared distance,
/// mean).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn block_knn<const AVX512: bool>(
    block: &Packed,
    q: &[f64; 3],
    k: usize,
    margin2: f64,
    hint2: f64,
    buf: &mut [u64],
    order: SumOrder,
) -> Option<(f64, f64)> {
    let mut t2 = margin2.min(hint2 * HINT_FACTOR);
    loop {
        let cnt = simd::filter::<AVX512>(block, q, t2, buf);
        if cnt >= k {
            return Some(finish_knn::<AVX512>(buf, cnt, k, order, hint2));
        }
        if t2 >= margin2 {
            return None;
        }
        t2 = margin2;
    }
}

/// What one chunk of cells' queries found: the mean per point of the chunk (NaN for the points
/// left to the hierarchy), those points, the overfull cells and the second-chance answers.
struct ChunkKnn {
    means: Vec<f64>,
    fallback: Vec<usize>,
    overfull: usize,
    second_chance: usize,
    /// Cells of at most [`LEAF`] points whose whole 3 × 3 × 3 block holds fewer than `k / 4`
    /// points (isolated points: all theirs are in `fallback`).
    isolated: Vec<usize>,
}

/// The k-NN queries of the cells `cells` that the grid answers (see [`grid_knn`]); `cap` is the
/// most points a block may hold. `AVX512` selects the vector distance kernel (only set where the
/// CPU has it, see [`simd::knn_chunk`]).
#[inline(always)]
fn knn_chunk_with<const AVX512: bool>(
    grid: &Grid,
    columns: Option<&Columns>,
    cells: Range<usize>,
    k: usize,
    cap: usize,
    order: SumOrder,
) -> ChunkKnn {
    let base = grid.start(cells.start);
    let mut out = vec![f64::NAN; grid.start(cells.end) - base];
    let mut fallback = Vec::new();
    let mut overfull = 0usize;
    let mut second_chance = 0usize;
    let mut ranges = Vec::with_capacity(9);
    let mut block = Packed::default();
    let mut buf = vec![0u64; cap + FILTER_SLACK];
    let mut hint2 = f64::INFINITY;
    let mut failed = Vec::new();
    let mut isolated = Vec::new();
    for c in cells {
        let own = grid.start(c)..grid.start(c + 1);
        grid.block_ranges_with(columns, c, 1, &mut ranges);
        let total: usize = ranges.iter().map(|r| r.len()).sum();
        if total > cap {
            overfull += 1;
            fallback.extend(own);
            continue;
        }
        let cell = grid.coords(grid.keys[c]);
        let walls = grid.block_walls(cell, 1);
        failed.clear();
        if total < k {
            failed.extend(own);
        } else {
            simd::fill::<AVX512>(&mut block, &grid.xyz, &ranges);
            for s in own {
                let p = &grid.xyz[s];
                let m = walls.margin(p);
                let found = if m > 0.0 {
                    block_knn::<AVX512>(&block, &wide(p), k, m * m, hint2, &mut buf, order)
                } else {
                    None
                };
                match found {
                    Some((kth2, mean)) => {
                        hint2 = kth2;
                        out[s - base] = mean;
                    }
                    None => failed.push(s),
                }
            }
        }
        // A second chance on the 5 × 5 × 5 block (a cell edge chosen a little too small, a
        // sparse spot), unless even the 3 × 3 × 3 block was nearly empty (isolated points go
        // straight to the hierarchy).
        if failed.is_empty() {
            continue;
        }
        if 4 * total < k {
            fallback.extend_from_slice(&failed);
            if grid.start(c + 1) - grid.start(c) <= LEAF {
                isolated.push(c);
            }
            continue;
        }
        grid.block_ranges_with(columns, c, 2, &mut ranges);
        if ranges.iter().map(|r| r.len()).sum::<usize>() > cap {
            fallback.extend_from_slice(&failed);
            continue;
        }
        simd::fill::<AVX512>(&mut block, &grid.xyz, &ranges);
        let walls2 = grid.block_walls(cell, 2);
        for &s in &failed {
            let p = &grid.xyz[s];
            let m = walls2.margin(p);
            let found = if m > 0.0 {
                block_knn::<AVX512>(&block, &wide(p), k, m * m, m * m, &mut buf, order)
            } else {
                None
            };
            match found {
                Some((kth2, mean)) => {
                    hint2 = kth2;
                    out[s - base] = mean;
                    second_chance += 1;
                }
                None => fallback.push(s),
            }
        }
    }
    ChunkKnn { means: out, fallback, overfull, second_chance, isolated }
}

/// The distance kernel compiled once portably and, on x86-64 with AVX-512, once with vector
/// compression (chosen at run time).
mod simd {
    #![allow(unsafe_code)]

    use super::{ChunkKnn, Columns, Grid, KBest, Keying, Packed, SumOrder, Xyz};
    use std::ops::Range;

    /// Whether this CPU runs the AVX-512 kernel.
    pub(super) fn has_avx512() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("popcnt")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }

    /// [`super::knn_chunk_with`] with the vector kernel when the CPU has it.
    pub(super) fn knn_chunk(
        grid: &Grid,
        columns: Option<&Columns>,
        cells: Range<usize>,
        k: usize,
        cap: usize,
        order: SumOrder,
    ) -> ChunkKnn {
        #[cfg(target_arch = "x86_64")]
        {
            if has_avx512() {
                // SAFETY: `knn_chunk_avx512` only requires the CPU to support AVX-512F, checked
                // just above.
                return unsafe { knn_chunk_avx512(grid, columns, cells, k, cap, order) };
            }
        }
        super::knn_chunk_with::<false>(grid, columns, cells, k, cap, order)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,popcnt")]
    fn knn_chunk_avx512(
        grid: &Grid,
        columns: Option<&Columns>,
        cells: Range<usize>,
        k: usize,
        cap: usize,
        order: SumOrder,
    ) -> ChunkKnn {
        super::knn_chunk_with::<true>(grid, columns, cells, k, cap, order)
    }

    /// [`super::filter_portable`], or [`filter_avx512`] when `AVX512` (set only by
    /// `knn_chunk_avx512`, which runs only where the CPU has AVX-512F).
    #[inline(always)]
    pub(super) fn filter<const AVX512: bool>(
        block: &Packed,
        q: &[f64; 3],
        t2: f64,
        buf: &mut [u64],
    ) -> usize {
        #[cfg(target_arch = "x86_64")]
        {
            if AVX512 {
                // SAFETY: `AVX512` is true only inside `knn_chunk_avx512`, called after the CPU
                // was found to support AVX-512F (and in the tests, after the same check).
                return unsafe { filter_avx512(block, q, t2, buf) };
            }
        }
        super::filter_portable(block, q, t2, buf)
    }

    /// [`Packed::fill`], eight points at a time when `AVX512` (as [`filter`]).
    #[inline(always)]
    pub(super) fn fill<const AVX512: bool>(block: &mut Packed, xyz: &[Xyz], ranges: &[Range<usize>]) {
        #[cfg(target_arch = "x86_64")]
        {
            if AVX512 {
                // SAFETY: as in `filter`.
                unsafe { fill_avx512(block, xyz, ranges) };
                return;
            }
        }
        block.fill(xyz, ranges);
    }

    /// [`Packed::fill`] with [`load_points8`]: the same values (the widening is exact).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn fill_avx512(block: &mut Packed, xyz: &[Xyz], ranges: &[Range<usize>]) {
        use std::arch::x86_64::*;
        block.size_for(ranges);
        let mut at = 0usize;
        for r in ranges {
            let pts = &xyz[r.clone()];
            let mut j = 0usize;
            while j < pts.len() {
                let (lanes, [x, y, z]) = load_points8(pts, j);
                // SAFETY: the lanes stored are the points `j..j + m` of this range (`m` the lanes
                // set), which go to `at + j..at + j + m`, within the entries `size_for` made (the
                // ranges' total) in each vector.
                unsafe {
                    _mm512_mask_storeu_pd(block.x.as_mut_ptr().add(at + j), lanes, x);
                    _mm512_mask_storeu_pd(block.y.as_mut_ptr().add(at + j), lanes, y);
                    _mm512_mask_storeu_pd(block.z.as_mut_ptr().add(at + j), lanes, z);
                }
                j += 8;
            }
            at += pts.len();
        }
    }

    /// Pushes into `best`, in order, every point of `pts` nearer to `q` than `best`'s worst at
    /// the time (what the hierarchy does at a leaf); with the vector kernel when `AVX512` (as
    /// [`filter`]).
    #[inline(always)]
    pub(super) fn leaf_scan<const AVX512: bool>(pts: &[Xyz], q: &Xyz, best: &mut KBest) {
        #[cfg(target_arch = "x86_64")]
        {
            if AVX512 {
                // SAFETY: as in `filter`.
                unsafe { leaf_scan_avx512(pts, q, best) };
                return;
            }
        }
        for p in pts {
            let d = super::dist2(q, p);
            if d < best.worst() {
                best.push(d);
            }
        }
    }

    /// The lanes of a vector of eight holding the first `left` values (all eight from 8 up).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn tail_mask(left: usize) -> std::arch::x86_64::__mmask8 {
        if left >= 8 { 0xff } else { (1u8 << left) - 1 }
    }

    /// Points `j..j + 8` of `pts` (fewer at the end: the lanes returned), coordinate by
    /// coordinate, widened to `f64` exactly: the 24 floats loaded masked and separated by
    /// two-source permutes.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn load_points8(pts: &[Xyz], j: usize) -> (std::arch::x86_64::__mmask8, [std::arch::x86_64::__m512d; 3]) {
        use std::arch::x86_64::*;
        assert!(j < pts.len(), "point {j} beyond {}", pts.len());
        let m = (pts.len() - j).min(8);
        let floats = 3 * m;
        let lo_mask: __mmask16 = if floats >= 16 { 0xffff } else { (1u16 << floats) - 1 };
        let hi_mask: __mmask16 = if floats > 16 { (1u16 << (floats - 16)) - 1 } else { 0 };
        // `Xyz` is `#[repr(C)]` three `f32` (nalgebra's `OPoint` over an array), asserted below.
        let base = pts.as_ptr().cast::<f32>();
        // SAFETY: the masked loads read only the floats of points `j..j + m`, all within `pts`;
        // masked-off lanes are not accessed.
        let (lo, hi) = unsafe {
            (
                _mm512_maskz_loadu_ps(lo_mask, base.add(3 * j)),
                _mm512_maskz_loadu_ps(hi_mask, base.add(3 * j + 16)),
            )
        };
        let coord = |o: i32| {
            let idx = _mm512_setr_epi32(
                o,
                o + 3,
                o + 6,
                o + 9,
                o + 12,
                o + 15,
                o + 18,
                o + 21,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            );
            _mm512_cvtps_pd(_mm512_castps512_ps256(_mm512_permutex2var_ps(lo, idx, hi)))
        };
        (tail_mask(m), [coord(0), coord(1), coord(2)])
    }

    // `load_points8` reads the points as consecutive `f32` triples.
    const _: () = assert!(std::mem::size_of::<Xyz>() == 12 && std::mem::align_of::<Xyz>() == 4);

    /// [`leaf_scan`] eight points at a time ([`load_points8`]): the squared distances computed as [`super::dist2`] computes them (bit
    /// for bit); the lanes below the worst at the start of the eight are offered to `best` one
    /// by one, each checked against the worst at that time (so the same pushes happen).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    pub(super) fn leaf_scan_avx512(pts: &[Xyz], q: &Xyz, best: &mut KBest) {
        use std::arch::x86_64::*;
        let n = pts.len();
        let (qx, qy, qz) =
            (_mm512_set1_pd(f64::from(q.x)), _mm512_set1_pd(f64::from(q.y)), _mm512_set1_pd(f64::from(q.z)));
        let mut d8 = [0.0f64; 8];
        let mut j = 0usize;
        while j < n {
            let (lanes, [x, y, z]) = load_points8(pts, j);
            let (dx, dy, dz) = (_mm512_sub_pd(qx, x), _mm512_sub_pd(qy, y), _mm512_sub_pd(qz, z));
            let d = _mm512_add_pd(
                _mm512_add_pd(_mm512_mul_pd(dx, dx), _mm512_mul_pd(dy, dy)),
                _mm512_mul_pd(dz, dz),
            );
            let mut near = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(lanes, d, _mm512_set1_pd(best.worst()));
            if near != 0 {
                // SAFETY: `d8` holds eight `f64`; `storeu` needs no alignment.
                unsafe { _mm512_storeu_pd(d8.as_mut_ptr(), d) };
                while near != 0 {
                    let i = near.trailing_zeros() as usize;
                    near &= near - 1;
                    if d8[i] < best.worst() {
                        best.push(d8[i]);
                    }
                }
            }
            j += 8;
        }
    }

    /// Whether this CPU runs the AVX-512 cell-key kernel (it also needs AVX-512DQ's unsigned
    /// conversions).
    pub(super) fn has_avx512_keys() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512dq")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }

    /// The cell keys of `pts` into `out` (of the same length): [`Keying::key`] per point, eight
    /// at a time where the CPU has AVX-512F and DQ.
    pub(super) fn keys(keying: &Keying, pts: &[Xyz], out: &mut [u64]) {
        #[cfg(target_arch = "x86_64")]
        {
            if has_avx512_keys() {
                // SAFETY: `keys_avx512` only requires AVX-512F and DQ, checked just above.
                unsafe { keys_avx512(keying, pts, out) };
                return;
            }
        }
        keys_portable(keying, pts, out);
    }

    pub(super) fn keys_portable(keying: &Keying, pts: &[Xyz], out: &mut [u64]) {
        for (o, p) in out.iter_mut().zip(pts) {
            *o = keying.key(p);
        }
    }

    /// [`keys_portable`] eight points at a time, the same keys bit for bit: the coordinates
    /// separated by permutes and widened; usable = all three finite; the cell index from the
    /// same subtraction and product, clamped to `0..=dims − 1` in `f64` (exact: `dims ≤ 2^20`)
    /// and truncated (what `as u64` then `min` give for every finite value); the Morton spread
    /// in vector shifts.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512dq")]
    pub(super) fn keys_avx512(keying: &Keying, pts: &[Xyz], out: &mut [u64]) {
        use std::arch::x86_64::*;
        let n = pts.len();
        assert!(out.len() == n, "key output of another length");
        let inf = _mm512_set1_pd(f64::INFINITY);
        let zero = _mm512_setzero_pd();
        let inv_h = _mm512_set1_pd(keying.inv_h);
        let origin = keying.origin.map(|o| _mm512_set1_pd(o));
        let top = keying.dims.map(|d| _mm512_set1_pd((d - 1) as f64));
        let limit = _mm512_set1_epi64(keying.limit as i64);
        let zbits = _mm_set_epi64x(0, i64::from(keying.zbits));
        let spread = |v: __m512i| {
            let m = |c: u64| _mm512_set1_epi64(c as i64);
            let mut x = _mm512_and_si512(v, m(0xF_FFFF));
            x = _mm512_and_si512(_mm512_or_si512(x, _mm512_slli_epi64::<16>(x)), m(0x0000_FFFF_0000_FFFF));
            x = _mm512_and_si512(_mm512_or_si512(x, _mm512_slli_epi64::<8>(x)), m(0x00FF_00FF_00FF_00FF));
            x = _mm512_and_si512(_mm512_or_si512(x, _mm512_slli_epi64::<4>(x)), m(0x0F0F_0F0F_0F0F_0F0F));
            x = _mm512_and_si512(_mm512_or_si512(x, _mm512_slli_epi64::<2>(x)), m(0x3333_3333_3333_3333));
            _mm512_and_si512(_mm512_or_si512(x, _mm512_slli_epi64::<1>(x)), m(0x5555_5555_5555_5555))
        };
        let mut j = 0usize;
        while j < n {
            let (lanes, c) = load_points8(pts, j);
            let mut usable: __mmask8 = lanes;
            let mut cell = [_mm512_setzero_si512(); 3];
            for a in 0..3 {
                usable &= _mm512_cmp_pd_mask::<_CMP_LT_OQ>(_mm512_abs_pd(c[a]), inf);
                let v = _mm512_mul_pd(_mm512_sub_pd(c[a], origin[a]), inv_h);
                let v = _mm512_min_pd(_mm512_max_pd(v, zero), top[a]);
                cell[a] = _mm512_cvttpd_epu64(v);
            }
            let column = _mm512_or_si512(spread(cell[0]), _mm512_slli_epi64::<1>(spread(cell[1])));
            let key = _mm512_or_si512(_mm512_sll_epi64(column, zbits), cell[2]);
            let key = _mm512_mask_blend_epi64(usable, limit, key);
            // SAFETY: the masked store writes only `lanes`, the points left from `j` (at most
            // eight), entries below `n` of `out`, which has `n` entries (asserted above).
            unsafe { _mm512_mask_storeu_epi64(out.as_mut_ptr().add(j).cast::<i64>(), lanes, key) };
            j += 8;
        }
    }

    /// [`super::finish_any_portable`], or [`finish_any_avx512`] when `AVX512` (as [`filter`]).
    #[inline(always)]
    pub(super) fn finish_any<const AVX512: bool>(v: &[u64], k: usize, lower: u64) -> (f64, f64) {
        #[cfg(target_arch = "x86_64")]
        {
            if AVX512 {
                // SAFETY: as in `filter`.
                return unsafe { finish_any_avx512(v, k, lower) };
            }
        }
        super::finish_any_portable(v, k, lower)
    }

    /// [`super::finish_any_portable`] eight values at a time (the list compressed into place;
    /// the sum in another order).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,popcnt")]
    pub(super) fn finish_any_avx512(v: &[u64], k: usize, lower: u64) -> (f64, f64) {
        use std::arch::x86_64::*;
        let n = v.len();
        assert!(k >= 1 && k <= n, "k outside 1..=values");
        let surplus = n - k;
        let bound = _mm512_set1_epi64(lower as i64);
        let mut top = [0u64; super::TOP_MAX + 8];
        let mut listed = 0usize;
        let mut acc = _mm512_setzero_pd();
        for j in (0..n).step_by(8) {
            let lanes = tail_mask(n - j);
            // SAFETY: only the lanes below `n - j` are read, all within `v`.
            let x = unsafe { _mm512_maskz_loadu_epi64(lanes, v.as_ptr().add(j).cast::<i64>()) };
            acc = _mm512_add_pd(acc, _mm512_maskz_sqrt_pd(lanes, _mm512_castsi512_pd(x)));
            let big = _mm512_mask_cmpgt_epu64_mask(lanes, x, bound);
            if listed <= super::TOP_MAX {
                // SAFETY: `listed ≤ TOP_MAX`, so the eight entries from `listed` lie within
                // `top` (`TOP_MAX + 8` entries); `storeu` needs no alignment.
                unsafe {
                    _mm512_storeu_si512(
                        top.as_mut_ptr().add(listed).cast(),
                        _mm512_maskz_compress_epi64(big, x),
                    )
                };
            }
            listed += big.count_ones() as usize;
        }
        if listed > surplus && listed <= super::TOP_MAX {
            return super::take_largest(&mut top[..listed], surplus, _mm512_reduce_add_pd(acc), k);
        }
        finish_steps_avx512(v, k)
    }

    /// [`super::finish_steps_portable`] eight values at a time (the same steps; the sum in
    /// another order).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,popcnt")]
    pub(super) fn finish_steps_avx512(v: &[u64], k: usize) -> (f64, f64) {
        use std::arch::x86_64::*;
        let n = v.len();
        assert!(k >= 1 && k <= n, "k outside 1..=values");
        let load = |j: usize| {
            let lanes = tail_mask(n - j);
            // SAFETY: only the lanes below `n - j` are read, all within `v`.
            (lanes, unsafe { _mm512_maskz_loadu_epi64(lanes, v.as_ptr().add(j).cast::<i64>()) })
        };
        let surplus = n - k;
        let mut above = 0usize;
        let mut kth = u64::MAX;
        loop {
            let limit = _mm512_set1_epi64(kth as i64);
            let mut top = _mm512_setzero_si512();
            for j in (0..n).step_by(8) {
                let (lanes, x) = load(j);
                let below = _mm512_mask_cmplt_epu64_mask(lanes, x, limit);
                top = _mm512_mask_max_epu64(top, below, top, x);
            }
            let top = _mm512_reduce_max_epu64(top);
            let at = _mm512_set1_epi64(top as i64);
            let mut ties = 0usize;
            for j in (0..n).step_by(8) {
                let (lanes, x) = load(j);
                ties += _mm512_mask_cmpeq_epu64_mask(lanes, x, at).count_ones() as usize;
            }
            kth = top;
            if above + ties > surplus || top == 0 {
                break;
            }
            above += ties;
        }
        let limit = _mm512_set1_epi64(kth as i64);
        let mut acc = _mm512_setzero_pd();
        let mut below = 0usize;
        for j in (0..n).step_by(8) {
            let (lanes, x) = load(j);
            let m = _mm512_mask_cmplt_epu64_mask(lanes, x, limit);
            acc = _mm512_add_pd(acc, _mm512_maskz_sqrt_pd(m, _mm512_castsi512_pd(x)));
            below += m.count_ones() as usize;
        }
        let kth2 = f64::from_bits(kth);
        let sum = _mm512_reduce_add_pd(acc);
        (kth2, (sum + (k - below) as f64 * kth2.sqrt()) / k as f64)
    }

    /// [`super::filter_portable`] eight points at a time: the kept squared distances compressed
    /// to the front of a vector and stored whole at the end of the kept run (hence
    /// [`super::FILTER_SLACK`]). The same values in the same order, bit for bit (the same
    /// operations in the same order; no fused multiply-add).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,popcnt")]
    pub(super) fn filter_avx512(block: &Packed, q: &[f64; 3], t2: f64, buf: &mut [u64]) -> usize {
        use std::arch::x86_64::*;
        let n = block.len();
        assert!(block.y.len() == n && block.z.len() == n, "packed coordinates of unequal length");
        assert!(buf.len() >= n + super::FILTER_SLACK, "filter buffer too short");
        let (qx, qy, qz) = (_mm512_set1_pd(q[0]), _mm512_set1_pd(q[1]), _mm512_set1_pd(q[2]));
        let t = _mm512_set1_pd(t2);
        let out = buf.as_mut_ptr().cast::<f64>();
        let mut cnt = 0usize;
        let mut j = 0usize;
        while j < n {
            let lanes = tail_mask(n - j);
            // SAFETY: the masked loads read only the lanes below `n - j`, all within the three
            // vectors of length `n`; masked-off lanes are not accessed.
            let (x, y, z) = unsafe {
                (
                    _mm512_maskz_loadu_pd(lanes, block.x.as_ptr().add(j)),
                    _mm512_maskz_loadu_pd(lanes, block.y.as_ptr().add(j)),
                    _mm512_maskz_loadu_pd(lanes, block.z.as_ptr().add(j)),
                )
            };
            let (dx, dy, dz) = (_mm512_sub_pd(qx, x), _mm512_sub_pd(qy, y), _mm512_sub_pd(qz, z));
            let d = _mm512_add_pd(
                _mm512_add_pd(_mm512_mul_pd(dx, dx), _mm512_mul_pd(dy, dy)),
                _mm512_mul_pd(dz, dz),
            );
            let keep = _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(lanes, d, t);
            // SAFETY: `cnt ≤ j < n`, so the eight entries from `cnt` lie within `buf`, which
            // holds `n + FILTER_SLACK` (asserted above); `f64` and `u64` share size and
            // alignment, and `storeu` needs no alignment.
            unsafe { _mm512_storeu_pd(out.add(cnt), _mm512_maskz_compress_pd(keep, d)) };
            cnt += keep.count_ones() as usize;
            j += 8;
        }
        cnt
    }
}

fn knn_means_with_stats(points: &[Point3<f32>], k: usize) -> (Vec<f64>, KnnStats) {
    let mut means = vec![f64::NAN; points.len()];
    let Some(bbox) = UsableBox::of(points) else {
        return (means, KnnStats::default());
    };
    let k = k.min(bbox.count);
    let h = knn_cell_size(points, &bbox, k);
    let mut grid = Grid::build(points, &bbox, h, true);
    let grown = grid.probe_failures(k) > PROBE_FAIL;
    if grown {
        grid = Grid::build(points, &bbox, h * GROW, true);
    }
    let mut sorted = vec![f64::NAN; grid.xyz.len()];
    let (mut stats, _) = grid_knn(&grid, k, LEAF_MAX, SumOrder::Ascending, &mut sorted, |d| d);
    stats.grown = grown;
    for (s, &d) in sorted.iter().enumerate() {
        means[grid.order[s]] = d;
    }
    (means, stats)
}

/// The exact k-NN mean distance of the grid's point `s` (`k` at most the grid's points): the
/// distances to the points of its block of cells, the block doubling in ring until the `k`-th
/// nearest lies within its margin (or it covers the grid). For the few queries that need an
/// exact answer outside the batch (the block scans cost `O(ring²)` column seeks each).
fn ring_knn(grid: &Grid, s: usize, k: usize) -> f64 {
    mean_sqrt(ring_knn_nearest(grid, s, k).iter().map(|&(d2, _)| d2))
}

/// The grid's `k` points nearest to its point `s` (`s` itself among them, at distance 0) as
/// (squared distance, grid index), nearest first; all of them when the grid holds fewer. The
/// block of cells doubles in ring until the `k`-th nearest lies within its margin (or it covers
/// the grid).
fn ring_knn_nearest(grid: &Grid, s: usize, k: usize) -> Vec<(f64, usize)> {
    let c = grid.starts.partition_point(|&st| st as usize <= s) - 1;
    let cell = grid.coords(grid.keys[c]);
    let q = &grid.xyz[s];
    let (mut ranges, mut d) = (Vec::new(), Vec::<(f64, usize)>::new());
    let widest = grid.dims.iter().copied().max().unwrap_or(1);
    let by_distance = |a: &(f64, usize), b: &(f64, usize)| a.0.total_cmp(&b.0);
    let mut ring = 1u64;
    loop {
        grid.block_ranges(c, ring, &mut ranges);
        d.clear();
        for r in &ranges {
            d.extend(r.clone().map(|j| (dist2(q, &grid.xyz[j]), j)));
        }
        let whole = ring >= widest;
        if k > 0 && d.len() >= k {
            d.select_nth_unstable_by(k - 1, by_distance);
            let m = grid.block_margin(cell, ring, q);
            if whole || (m > 0.0 && d[k - 1].0 <= m * m) {
                d.truncate(k);
                d.sort_unstable_by(by_distance);
                return d;
            }
        }
        if whole {
            // Fewer than k points in the whole grid: all of them.
            d.sort_unstable_by(by_distance);
            return d;
        }
        ring = (ring * 2).min(widest);
    }
}

/// How flat the neighbours of a point must lie for [`on_sampled_surface`]: the RMS distance
/// from their plane at most this share of their spread across it (the second largest).
const SURFACE_FLATNESS: f64 = 0.25;
/// How far from the neighbours' plane the point may lie, in units of their RMS distance from it.
const SURFACE_RESIDUALS: f64 = 4.0;
/// How far along the neighbours' plane from their centroid the point may lie, in units of their
/// RMS spread along it.
const SURFACE_REACH: f64 = 2.0;
/// Fewest neighbours a surface is judged from.
const SURFACE_MIN_NEIGHBOURS: usize = 5;
/// How compact the neighbourhood must be: its farthest point at most this many times as far
/// from the point as its median one (an evenly sampled patch: about 1.4; scan lines: 2 to 3; a
/// row of stray points with the surface far below: tens).
const SURFACE_COMPACT: f64 = 4.0;

/// Whether `q` lies on the surface its neighbours `nb` sample: they lie close together (the
/// farthest within [`SURFACE_COMPACT`] times the median's distance) and flat (a surface, not a
/// cloud of stray points nor a single line), `q` lies on their plane within
/// [`SURFACE_RESIDUALS`] of their own scatter about it, and among them rather than beyond them.
/// The rule that keeps a point statistical outlier removal flagged only for lying where the
/// surface is sampled sparsely (a steep wall seen at a glancing angle, a pass from afar): see
/// [`statistical_outlier_removal_keeping_surface`].
fn on_sampled_surface(q: &[f64; 3], nb: &[[f64; 3]]) -> bool {
    if nb.len() < SURFACE_MIN_NEIGHBOURS {
        return false;
    }
    let mut dist: Vec<f64> = nb.iter().map(|p| (Vector3::from(*p) - Vector3::from(*q)).norm()).collect();
    dist.sort_by(f64::total_cmp);
    if dist[dist.len() - 1] > SURFACE_COMPACT * dist[dist.len() / 2] {
        return false;
    }
    let n = nb.len() as f64;
    let mut c = Vector3::zeros();
    for p in nb {
        c += Vector3::from(*p);
    }
    c /= n;
    let mut cov = Matrix3::zeros();
    for p in nb {
        let d = Vector3::from(*p) - c;
        cov += d * d.transpose();
    }
    cov /= n;
    let eig = nalgebra::SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let l = order.map(|i| eig.eigenvalues[i].max(0.0));
    // `max` made every value a number (a NaN eigenvalue reads 0).
    if l[0] > SURFACE_FLATNESS * SURFACE_FLATNESS * l[1] || l[1] <= 0.0 {
        return false;
    }
    let normal = eig.eigenvectors.column(order[0]).into_owned();
    let d = Vector3::from(*q) - c;
    let off = normal.dot(&d);
    // A floor for exact data (no scatter at all): a millionth of the neighbourhood's size.
    let floor = 1e-6 * (l[1] + l[2]).sqrt();
    if off.abs() > SURFACE_RESIDUALS * l[0].sqrt() + floor {
        return false;
    }
    let along = (d - normal * off).norm_squared();
    along <= SURFACE_REACH * SURFACE_REACH * (l[1] + l[2])
}

/// Of the grid's points `dropped`, those [`grid_point_on_surface`] keeps after all.
fn kept_back(grid: &Grid, k: usize, dropped: Vec<usize>) -> Vec<usize> {
    let back: Vec<bool> = dropped.par_iter().map(|&s| grid_point_on_surface(grid, s, k)).collect();
    dropped.into_iter().zip(back).filter_map(|(s, b)| b.then_some(s)).collect()
}

/// [`on_sampled_surface`] for the grid's point `s` and its `k` nearest other points.
fn grid_point_on_surface(grid: &Grid, s: usize, k: usize) -> bool {
    let nb: Vec<[f64; 3]> = ring_knn_nearest(grid, s, k + 1)
        .into_iter()
        .filter(|&(_, j)| j != s)
        .map(|(_, j)| wide(&grid.xyz[j]))
        .collect();
    on_sampled_surface(&wide(&grid.xyz[s]), &nb)
}

/// Count, mean and sum of squared deviations of a set of values (Welford), mergeable (Chan et
/// al.), so the statistics of values computed in parallel need not store them.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Moments {
    n: usize,
    mean: f64,
    m2: f64,
}

impl Moments {
    fn add(&mut self, x: f64) {
        self.n += 1;
        let d = x - self.mean;
        self.mean += d / self.n as f64;
        self.m2 += d * (x - self.mean);
    }

    fn merge(self, o: Moments) -> Moments {
        if o.n == 0 {
            return self;
        }
        if self.n == 0 {
            return o;
        }
        let n = self.n + o.n;
        let d = o.mean - self.mean;
        Moments {
            n,
            mean: self.mean + d * (o.n as f64 / n as f64),
            m2: self.m2 + o.m2 + d * d * (self.n as f64 * o.n as f64 / n as f64),
        }
    }
}

/// The k-NN mean distance of every point of `grid` (in grid order) into `out` through `put`, with
/// how the queries were answered and the moments of the means. `k` is at most the number of
/// points; `leaf_max` is the hierarchy's leaf size for the queries the grid cannot answer;
/// `order` is how the grid's answers sum their distances (the hierarchy's sum in ascending
/// order).
fn grid_knn<T: Copy + Send>(
    grid: &Grid,
    k: usize,
    leaf_max: usize,
    order: SumOrder,
    out_all: &mut [T],
    put: impl Fn(f64) -> T + Sync,
) -> (KnnStats, Moments) {
    let mut stats = KnnStats::default();
    // A block with more candidates than this goes to the hierarchy (heaps of duplicates).
    let cap = 48 * k + 2048;
    let chunks = grid.chunks();
    let slices = split_by_chunks(out_all, grid, &chunks);
    let columns = Columns::build(grid);
    // Each chunk's answers go to `out_all` at once; its means vector is dropped.
    let per_chunk: Vec<(ChunkKnn, Moments)> = chunks
        .into_par_iter()
        .zip(slices)
        .map(|(cells, dest)| {
            let mut found = simd::knn_chunk(grid, columns.as_ref(), cells, k, cap, order);
            let mut moments = Moments::default();
            for (d, &m) in dest.iter_mut().zip(&found.means) {
                *d = put(m);
                if !m.is_nan() {
                    moments.add(m);
                }
            }
            found.means = Vec::new();
            (found, moments)
        })
        .collect();
    stats.overfull_cells = per_chunk.iter().map(|f| f.0.overfull).sum();
    stats.second_chance = per_chunk.iter().map(|f| f.0.second_chance).sum();
    let mut moments = per_chunk.iter().fold(Moments::default(), |a, f| a.merge(f.1));
    let mut isolated = Vec::new();
    let mut fallback = Vec::new();
    // In grid order, so consecutive queries are near each other and share cache.
    for (f, _) in per_chunk {
        fallback.extend(f.fallback);
        isolated.extend(f.isolated);
    }
    stats.tree = fallback.len();
    stats.grid = grid.xyz.len() - fallback.len();
    if !fallback.is_empty() {
        // The isolated cells' points go to a hierarchy of their own (a copy, at most an eighth
        // of the points), so that the boxes over the dense cells stay tight.
        let strays: usize = isolated.iter().map(|&c| grid.start(c + 1) - grid.start(c)).sum();
        let split = strays > 0 && strays * 8 <= grid.xyz.len();
        let (skip, stray_grid) = if split {
            let mut bits = vec![0u64; grid.keys.len().div_ceil(64)];
            let mut pts = Vec::with_capacity(strays);
            for &c in &isolated {
                bits[c / 64] |= 1 << (c % 64);
                pts.extend_from_slice(&grid.xyz[grid.start(c)..grid.start(c + 1)]);
            }
            let g = UsableBox::of(&pts).map(|b| Grid::build(&pts, &b, 4.0 * grid.h, true));
            (Some(bits), g)
        } else {
            (None, None)
        };
        stats.stragglers = stray_grid.as_ref().map_or(0, |g| g.xyz.len());
        let bvh = Bvh::build(grid, leaf_max, skip.as_deref().filter(|_| stray_grid.is_some()));
        let stray_bvh = stray_grid.as_ref().map(|g| Bvh::build(g, LEAF_MAX, None));
        let vector = simd::has_avx512();
        let results: Vec<(usize, f64)> = fallback
            .par_chunks(256)
            .flat_map_iter(|part| {
                let mut best = KBest::new(k);
                // The previous query and its k-th squared distance: its k nearest lie within
                // that distance plus the step from it (the triangle inequality), a bound that
                // prunes from the first node on.
                let mut prev: Option<(&Xyz, f64)> = None;
                part.iter()
                    .map(|&s| {
                        let q = &grid.xyz[s];
                        match prev {
                            Some((p, kth2)) => {
                                let r = kth2.sqrt() + dist2(q, p).sqrt();
                                best.reset_below(r * r * (1.0 + 1e-9) + f64::MIN_POSITIVE);
                            }
                            None => best.reset(),
                        }
                        for tree in stray_bvh.iter().chain(std::iter::once(&bvh)) {
                            if vector {
                                tree.knn::<true>(q, &mut best);
                            } else {
                                tree.knn::<false>(q, &mut best);
                            }
                        }
                        let mean = best.mean_distance();
                        prev = (best.d.len() == k).then(|| (q, best.d[k - 1]));
                        (s, mean)
                    })
                    .collect::<Vec<_>>()
            })
            .collect();
        for (s, d) in results {
            out_all[s] = put(d);
            moments.add(d);
        }
    }
    (stats, moments)
}

// ---------------------------------------------------------------------------------------------
// Spheres, beacons, frames, user transforms.
// ---------------------------------------------------------------------------------------------

/// A fitted sphere: centre and radius (mm), RMS of the geometric residuals `|p − c| − r` (mm),
/// and the number of points the fit used.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SphereFit {
    pub center: Point3<f64>,
    pub radius_mm: f64,
    pub rms_mm: f64,
    pub points: usize,
}

fn sphere_param(n: usize, reason: impl Into<String>) -> ReconError {
    ReconError::param("sphere_fit.points", n, reason)
}

/// Fits a sphere to `points` (mm) by algebraic least squares, refined by Levenberg–Marquardt on
/// the geometric distance.
///
/// Errors ([`ReconError::InvalidParameter`], field `sphere_fit.points`): fewer than 4 points, a
/// point that is not finite, points that are coplanar or collinear (no unique sphere).
pub fn fit_sphere(points: &[Point3<f64>]) -> Result<SphereFit> {
    let n = points.len();
    if n < 4 {
        return Err(sphere_param(n, "a sphere fit needs at least 4 points"));
    }
    if let Some((i, p)) = points.iter().enumerate().find(|(_, p)| !usable(*p)) {
        return Err(ReconError::param(
            format!("sphere_fit.points[{i}]"),
            format!("({}, {}, {})", p.x, p.y, p.z),
            "must be finite",
        ));
    }
    // Centre and scale for conditioning: u = (p − mean) / scale.
    let mean = points.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n as f64;
    let scale = (points.iter().map(|p| (p.coords - mean).norm_squared()).sum::<f64>() / n as f64).sqrt();
    if !(scale > 0.0 && scale.is_finite()) {
        return Err(sphere_param(n, "all points coincide"));
    }
    let u: Vec<Vector3<f64>> = points.iter().map(|p| (p.coords - mean) / scale).collect();
    let cov = u.iter().fold(Matrix3::zeros(), |c, v| c + v * v.transpose()) / n as f64;
    let eig = cov.symmetric_eigenvalues();
    let (emin, emax) = (eig.min(), eig.max());
    if !matches!(emin.partial_cmp(&(1e-12 * emax)), Some(Ordering::Greater)) {
        return Err(sphere_param(n, "the points are coplanar or collinear, so no unique sphere fits them"));
    }
    // Algebraic fit: |u|² = 2 c·u + d, d = r² − |c|².
    let mut ata = Matrix4::<f64>::zeros();
    let mut atb = Vector4::<f64>::zeros();
    for v in &u {
        let row = Vector4::new(2.0 * v.x, 2.0 * v.y, 2.0 * v.z, 1.0);
        ata += row * row.transpose();
        atb += row * v.norm_squared();
    }
    let sol = ata.lu().solve(&atb).ok_or_else(|| sphere_param(n, "the algebraic sphere fit is singular"))?;
    let c0 = Vector3::new(sol.x, sol.y, sol.z);
    let r0_sq = sol.w + c0.norm_squared();
    if !(r0_sq > 0.0 && r0_sq.is_finite()) {
        return Err(sphere_param(n, "no sphere fits these points (degenerate configuration)"));
    }
    let (c, r) = refine_sphere(&u, c0, r0_sq.sqrt());
    let center = Point3::from(mean + c * scale);
    let radius_mm = r * scale;
    if !(radius_mm > 0.0 && radius_mm.is_finite() && center.coords.iter().all(|v| v.is_finite())) {
        return Err(sphere_param(n, "no sphere fits these points (degenerate configuration)"));
    }
    let rms_mm =
        (points.iter().map(|p| ((p - center).norm() - radius_mm).powi(2)).sum::<f64>() / n as f64).sqrt();
    Ok(SphereFit { center, radius_mm, rms_mm, points: n })
}

/// Sum of squared geometric residuals.
fn sphere_cost(u: &[Vector3<f64>], c: &Vector3<f64>, r: f64) -> f64 {
    u.iter().map(|v| ((v - c).norm() - r).powi(2)).sum()
}

/// Levenberg–Marquardt on `Σ (|u − c| − r)²`, from `(c, r)`.
fn refine_sphere(u: &[Vector3<f64>], mut c: Vector3<f64>, mut r: f64) -> (Vector3<f64>, f64) {
    let mut lambda = 1e-3;
    let mut cost = sphere_cost(u, &c, r);
    for _ in 0..100 {
        let mut jtj = Matrix4::<f64>::zeros();
        let mut jtr = Vector4::<f64>::zeros();
        for v in u {
            let d = v - c;
            let dist = d.norm();
            let dir = if dist > 0.0 { d / dist } else { Vector3::zeros() };
            let j = Vector4::new(-dir.x, -dir.y, -dir.z, -1.0);
            let res = dist - r;
            jtj += j * j.transpose();
            jtr += j * res;
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj;
            for i in 0..4 {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(step) = a.lu().solve(&(-jtr)) else {
                lambda *= 10.0;
                continue;
            };
            let c_new = c + Vector3::new(step.x, step.y, step.z);
            let r_new = r + step.w;
            let cost_new = sphere_cost(u, &c_new, r_new);
            if cost_new.is_finite() && cost_new <= cost {
                let small = step.norm() <= 1e-13 * (1.0 + r.abs());
                c = c_new;
                r = r_new;
                cost = cost_new;
                lambda = (lambda / 10.0).max(1e-12);
                improved = !small;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (c, r)
}

/// The sphere through 4 points (algebraic), if they are not (nearly) coplanar.
fn sphere_through(p: [&Point3<f64>; 4]) -> Option<(Point3<f64>, f64)> {
    let o = p[0].coords;
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    // |x − c|² = r² for all four: 2 (pᵢ − p₀)·(c − p₀) = |pᵢ − p₀|².
    for i in 1..4 {
        let d = p[i].coords - o;
        a.set_row(i - 1, &(2.0 * d).transpose());
        b[i - 1] = d.norm_squared();
    }
    let scale = b.max();
    if scale.is_nan() || scale <= 0.0 || a.determinant().abs() <= 1e-9 * scale.powf(1.5) {
        return None;
    }
    let c = a.lu().solve(&b)?;
    let center = Point3::from(o + c);
    let r = c.norm();
    (r.is_finite() && r > 0.0).then_some((center, r))
}

/// Points of `pts` whose residual to the sphere `(c, r)` is at most `thr`.
fn sphere_inliers(pts: &[Point3<f64>], c: &Point3<f64>, r: f64, thr: f64) -> Vec<Point3<f64>> {
    pts.iter().filter(|p| ((*p - c).norm() - r).abs() <= thr).copied().collect()
}

/// Fits a beacon sphere among the points within `search_radius_mm` of `approx_center`, robustly:
/// least median of squares over deterministic random 4-point spheres whose centre lies in the
/// search ball (tolerates up to half of the selected points off the sphere, e.g. table or part
/// around it), then least-squares refits on the points within 3·rms of the current sphere until
/// that set is stable. `points` in the result is the number of inliers used.
///
/// Errors: `beacon.search_radius_mm` / `beacon.approx_center` when not finite (and positive), or
/// when fewer than 4 points lie in the search ball; [`fit_sphere`]'s errors.
pub fn fit_beacon(
    points: &[Point3<f64>],
    approx_center: Point3<f64>,
    search_radius_mm: f64,
) -> Result<SphereFit> {
    if !(search_radius_mm.is_finite() && search_radius_mm > 0.0) {
        return Err(ReconError::param(
            "beacon.search_radius_mm",
            search_radius_mm,
            "must be finite and positive",
        ));
    }
    if !usable(&approx_center) {
        return Err(ReconError::param(
            "beacon.approx_center",
            format!("({}, {}, {})", approx_center.x, approx_center.y, approx_center.z),
            "must be finite",
        ));
    }
    let r2 = search_radius_mm * search_radius_mm;
    let sel: Vec<Point3<f64>> =
        points.iter().filter(|p| (*p - approx_center).norm_squared() <= r2).copied().collect();
    let m = sel.len();
    if m < 4 {
        return Err(ReconError::param(
            "beacon.search_radius_mm",
            search_radius_mm,
            format!(
                "only {m} points lie within it of ({}, {}, {}); a sphere fit needs at least 4",
                approx_center.x, approx_center.y, approx_center.z
            ),
        ));
    }
    // Scoring subset: at most 2000 points, evenly spread over the selection.
    let stride = m.div_ceil(2000);
    let score: Vec<Point3<f64>> = sel.iter().step_by(stride).copied().collect();
    let mut res2 = Vec::with_capacity(score.len());
    let mut best: Option<(f64, Point3<f64>, f64)> = None;
    let mut state = 0x5EED_u64 ^ m as u64;
    for _ in 0..600 {
        let mut pick = [0usize; 4];
        for slot in &mut pick {
            state = splitmix(state);
            *slot = (state % m as u64) as usize;
        }
        let [a, b, c, d] = pick;
        if a == b || a == c || a == d || b == c || b == d || c == d {
            continue;
        }
        let Some((center, r)) = sphere_through([&sel[a], &sel[b], &sel[c], &sel[d]]) else { continue };
        if (center - approx_center).norm_squared() > r2 {
            continue;
        }
        res2.clear();
        res2.extend(score.iter().map(|p| ((p - center).norm() - r).powi(2)));
        let mid = res2.len() / 2;
        let (_, med, _) = res2.select_nth_unstable_by(mid, f64::total_cmp);
        let med = *med;
        if best.is_none_or(|(b, _, _)| med < b) {
            best = Some((med, center, r));
        }
    }
    let mut inliers = match best {
        Some((med, center, r)) => {
            let ms = score.len() as f64;
            let sigma = 1.4826 * (1.0 + 5.0 / (ms - 4.0).max(1.0)) * med.sqrt();
            let set = sphere_inliers(&sel, &center, r, (2.5 * sigma).max(1e-9 * r));
            if set.len() >= 4 { set } else { sel.clone() }
        }
        None => sel.clone(),
    };
    let mut fit = fit_sphere(&inliers)?;
    for _ in 0..20 {
        let thr = (3.0 * fit.rms_mm).max(1e-9 * fit.radius_mm);
        let next = sphere_inliers(&sel, &fit.center, fit.radius_mm, thr);
        if next.len() < 4 || next == inliers {
            break;
        }
        inliers = next;
        fit = fit_sphere(&inliers)?;
    }
    Ok(fit)
}

/// Smallest sine of the angle at `c[0]` between the directions to `c[1]` and `c[2]` that
/// [`beacon_frame`] accepts (about 0.57°): the frame's Y axis is only as good as
/// `centre error / (distance · sine)`.
pub const MIN_BEACON_SINE: f64 = 1e-2;

/// The frame three beacon centres define: origin at c[0], X towards c[1], Z along
/// (c1-c0)×(c2-c0), Y = Z×X. Returns `beacon_from_cloud`, the isometry that maps cloud
/// coordinates into that frame (apply with PointCloud::transform). Error if the centres are
/// (nearly) collinear.
///
/// In the beacon frame the centres land at `(0, 0, 0)`, `(|c1 − c0|, 0, 0)` and `(x, y, 0)` with
/// `y > 0`. Errors (`beacon_frame.centers`): a centre that is not finite, or a sine of the angle
/// at `c[0]` below [`MIN_BEACON_SINE`] (which includes coincident centres).
pub fn beacon_frame(c: [Point3<f64>; 3]) -> Result<Isometry3<f64>> {
    let shown = || c.iter().map(|p| format!("({}, {}, {})", p.x, p.y, p.z)).collect::<Vec<_>>().join(", ");
    if !c.iter().all(usable) {
        return Err(ReconError::param("beacon_frame.centers", shown(), "must be finite"));
    }
    let a = c[1] - c[0];
    let b = c[2] - c[0];
    let z = a.cross(&b);
    let denom = a.norm() * b.norm();
    let sine = if denom > 0.0 { z.norm() / denom } else { 0.0 };
    if sine.is_nan() || sine < MIN_BEACON_SINE {
        return Err(ReconError::param(
            "beacon_frame.centers",
            shown(),
            format!(
                "are (nearly) collinear: sine of the angle at the first centre {sine:.3e} < {MIN_BEACON_SINE}"
            ),
        ));
    }
    let x = a.normalize();
    let z = z.normalize();
    let y = z.cross(&x);
    // Rows of beacon_from_cloud's rotation are the frame's axes in cloud coordinates.
    let rot =
        Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]));
    let q = UnitQuaternion::from_rotation_matrix(&rot);
    let q = UnitQuaternion::new_normalize(q.into_inner());
    let t = -(q * c[0].coords);
    Ok(Isometry3::from_parts(Translation3::from(t), q))
}

/// Tolerance of [`rigid_from_matrix`]'s checks.
pub const RIGID_TOLERANCE: f64 = 1e-6;

/// Parses/validates a user transform given as a 4x4 row-major matrix `m[row][col]` (`p ↦ R·p + t`
/// with `R = m[0..3][0..3]`, `t = m[0..3][3]`): every entry finite, `R` orthonormal (`|RᵀR − I|`
/// entrywise) and `det R = +1` within 1e-6, last row `0 0 0 1` within 1e-6. The rotation is
/// re-orthonormalised.
///
/// Errors: [`ReconError::InvalidParameter`] on `reconstruct.filters.transform`, naming the entry
/// or the check that failed.
pub fn rigid_from_matrix(m: [[f64; 4]; 4]) -> Result<Isometry3<f64>> {
    const FIELD: &str = "reconstruct.filters.transform";
    for (r, row) in m.iter().enumerate() {
        for (col, v) in row.iter().enumerate() {
            if !v.is_finite() {
                return Err(ReconError::param(format!("{FIELD}[{r}][{col}]"), v, "must be finite"));
            }
        }
    }
    let last = [0.0, 0.0, 0.0, 1.0];
    if let Some(col) = (0..4).find(|&col| (m[3][col] - last[col]).abs() > RIGID_TOLERANCE) {
        return Err(ReconError::param(
            format!("{FIELD}[3][{col}]"),
            m[3][col],
            format!("the last row must be 0 0 0 1 (within {RIGID_TOLERANCE})"),
        ));
    }
    let rot = Matrix3::from_fn(|r, c| m[r][c]);
    let err = (rot.transpose() * rot - Matrix3::identity()).abs().max();
    if err > RIGID_TOLERANCE {
        return Err(ReconError::param(
            FIELD,
            format!("{m:?}"),
            format!("the rotation part is not orthonormal: |RᵀR − I| = {err:.3e} > {RIGID_TOLERANCE}"),
        ));
    }
    let det = rot.determinant();
    if (det - 1.0).abs() > RIGID_TOLERANCE {
        return Err(ReconError::param(
            FIELD,
            format!("{m:?}"),
            format!("the rotation part has determinant {det} (a reflection), not +1"),
        ));
    }
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rot));
    let q = UnitQuaternion::new_normalize(q.into_inner());
    Ok(Isometry3::from_parts(Translation3::new(m[0][3], m[1][3], m[2][3]), q))
}

/// A user transform given as a translation (mm) and yaw/pitch/roll (degrees, ZYX:
/// `R = Rz(yaw)·Ry(pitch)·Rx(roll)`, as [`depthmill_geometry::XyzYpr`]): `p ↦ R·p + t`.
///
/// Errors: `reconstruct.filters.transform.<x_mm|y_mm|z_mm|yaw_deg|pitch_deg|roll_deg>` when not
/// finite.
pub fn rigid_from_xyz_ypr(
    translation_mm: [f64; 3],
    yaw_deg: f64,
    pitch_deg: f64,
    roll_deg: f64,
) -> Result<Isometry3<f64>> {
    let fields = [
        ("x_mm", translation_mm[0]),
        ("y_mm", translation_mm[1]),
        ("z_mm", translation_mm[2]),
        ("yaw_deg", yaw_deg),
        ("pitch_deg", pitch_deg),
        ("roll_deg", roll_deg),
    ];
    if let Some((name, v)) = fields.into_iter().find(|(_, v)| !v.is_finite()) {
        return Err(ReconError::param(format!("reconstruct.filters.transform.{name}"), v, "must be finite"));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(translation_mm[0], translation_mm[1], translation_mm[2]),
        rotation_from_ypr_deg(yaw_deg, pitch_deg, roll_deg),
    ))
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use depthmill_geometry::XyzYpr;
    use nalgebra::{Matrix4, Point3, Vector3};
    use proptest::prelude::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;

    fn p(x: f64, y: f64, z: f64) -> Point3<f64> {
        Point3::new(x, y, z)
    }

    /// A cloud's point (single precision) from double-precision coordinates.
    fn pt(x: f64, y: f64, z: f64) -> Point3<f32> {
        depthmill_geometry::cloud::single(&p(x, y, z))
    }

    fn gauss(rng: &mut StdRng) -> f64 {
        let u1 = 1.0 - rng.random::<f64>();
        let u2 = rng.random::<f64>();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    // ----- Slow, obviously correct references -----------------------------------------------

    /// O(n²): every squared distance to a usable point, sorted; the `k` smallest (the point
    /// itself included) as square roots summed in ascending order, over `k`. One result per `k`.
    fn brute_means_multi(points: &[Point3<f32>], ks: &[usize]) -> Vec<Vec<f64>> {
        let all: Vec<Xyz> = points.iter().filter(|q| usable(*q)).copied().collect();
        let kmax = ks.iter().copied().max().unwrap_or(1).min(all.len()).max(1);
        let mut out = vec![Vec::with_capacity(points.len()); ks.len()];
        for q in points {
            if !usable(q) {
                out.iter_mut().for_each(|o| o.push(f64::NAN));
                continue;
            }
            let mut d: Vec<f64> = all.iter().map(|o| dist2(q, o)).collect();
            if d.len() > kmax {
                d.select_nth_unstable_by(kmax - 1, f64::total_cmp);
            }
            d.truncate(kmax);
            d.sort_by(f64::total_cmp);
            for (o, &k) in out.iter_mut().zip(ks) {
                let k = k.min(all.len());
                let mut sum = 0.0;
                for v in &d[..k] {
                    sum += v.sqrt();
                }
                o.push(sum / k as f64);
            }
        }
        out
    }

    fn brute_means(points: &[Point3<f32>], k: usize) -> Vec<f64> {
        brute_means_multi(points, &[k]).remove(0)
    }

    /// Open3D's rule on the brute-force means (sample σ), with the two documented differences.
    fn brute_sor_mask(points: &[Point3<f32>], k: usize, n_sigma: f64) -> Vec<bool> {
        let means = brute_means(points, k);
        let valid: Vec<f64> = means.iter().copied().filter(|d| !d.is_nan()).collect();
        if valid.len() < 2 {
            return means.iter().map(|d| !d.is_nan()).collect();
        }
        let mean = valid.iter().fold(0.0, |a, d| a + d) / valid.len() as f64;
        let var = valid.iter().fold(0.0, |a, d| a + (d - mean) * (d - mean)) / (valid.len() - 1) as f64;
        let threshold = mean + n_sigma * var.sqrt();
        means.iter().map(|&d| !d.is_nan() && (d < threshold || d <= mean)).collect()
    }

    /// O(n²): per point, the sorted squared distances to every usable point (itself included);
    /// empty for unusable points.
    fn brute_sorted_d2(points: &[Point3<f32>]) -> Vec<Vec<f64>> {
        points
            .iter()
            .map(|q| {
                if !usable(q) {
                    return Vec::new();
                }
                let mut d: Vec<f64> = points.iter().filter(|o| usable(*o)).map(|o| dist2(q, o)).collect();
                d.sort_by(f64::total_cmp);
                d
            })
            .collect()
    }

    /// At least `min` other usable points strictly within `r` (the point itself is one of the
    /// distances below `r²`).
    fn brute_ror_mask(sorted_d2: &[Vec<f64>], r: f64, min: usize) -> Vec<bool> {
        sorted_d2.iter().map(|d| !d.is_empty() && d.partition_point(|&v| v < r * r) > min).collect()
    }

    /// Group by voxel in a hash map (members in index order), keep the member nearest the
    /// centroid `p₀ + Σ(p − p₀)/m`, the lowest index on ties.
    fn brute_voxel_mask(points: &[Point3<f32>], voxel: f64) -> Vec<bool> {
        let mut groups: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
        for (i, q) in points.iter().enumerate().filter(|(_, q)| usable(*q)) {
            let q = q.at();
            let key =
                [(q.x / voxel).floor() as i64, (q.y / voxel).floor() as i64, (q.z / voxel).floor() as i64];
            groups.entry(key).or_default().push(i);
        }
        let mut keep = vec![false; points.len()];
        for members in groups.values() {
            let p0 = points[members[0]].at();
            let sum = members.iter().fold(Vector3::zeros(), |s, &i| s + (points[i].at() - p0));
            let centroid = p0 + sum / members.len() as f64;
            let mut best = members[0];
            for &i in members {
                if (points[i].at() - centroid).norm_squared() < (points[best].at() - centroid).norm_squared()
                {
                    best = i;
                }
            }
            keep[best] = true;
        }
        keep
    }

    // ----- Random clouds ----------------------------------------------------------------------

    /// A wavy height field on a jittered grid (pitch 0.5 mm) with 20 µm noise.
    fn surface(rng: &mut StdRng, n: usize) -> Vec<Point3<f32>> {
        let side = (n as f64).sqrt().ceil() as usize;
        (0..n)
            .map(|i| {
                let x = (i % side) as f64 * 0.5 + rng.random_range(-0.15..0.15);
                let y = (i / side) as f64 * 0.5 + rng.random_range(-0.15..0.15);
                pt(x, y, 2.0 * (x / 7.0).sin() * (y / 5.0).cos() + 0.02 * gauss(rng))
            })
            .collect()
    }

    /// `n` uniformly random points in a box of side `size`.
    fn uniform(rng: &mut StdRng, n: usize, size: f64) -> Vec<Point3<f32>> {
        (0..n)
            .map(|_| pt(rng.random::<f64>() * size, rng.random::<f64>() * size, rng.random::<f64>() * size))
            .collect()
    }

    /// Points on a coarse integer lattice: many exact duplicates and tied distances.
    fn lattice(rng: &mut StdRng, n: usize, side: i32) -> Vec<Point3<f32>> {
        (0..n)
            .map(|_| {
                let c = |rng: &mut StdRng| f64::from(rng.random_range(0..side)) * 0.5;
                pt(c(rng), c(rng), c(rng))
            })
            .collect()
    }

    /// Tight clusters, a heap of exact duplicates, scattered points.
    fn clustered(rng: &mut StdRng, n: usize) -> Vec<Point3<f32>> {
        let centres: Vec<Point3<f64>> =
            (0..5).map(|_| p(rng.random::<f64>() * 50.0, rng.random::<f64>() * 50.0, 0.0)).collect();
        let mut pts: Vec<Point3<f32>> = (0..n)
            .map(|i| match i % 10 {
                0 => pt(rng.random::<f64>() * 60.0, rng.random::<f64>() * 60.0, rng.random::<f64>() * 20.0),
                1 => pt(7.0, 7.0, 7.0),
                _ => {
                    let c = centres[i % 5];
                    pt(c.x + 0.3 * gauss(rng), c.y + 0.3 * gauss(rng), c.z + 0.3 * gauss(rng))
                }
            })
            .collect();
        pts.swap(0, n / 2);
        pts
    }

    fn same_means(fast: &[f64], slow: &[f64]) -> bool {
        fast.len() == slow.len()
            && fast.iter().zip(slow).all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()))
    }

    // ----- retain, intensity, reports, errors --------------------------------------------------

    #[test]
    fn retain_keeps_attributes_in_order() {
        let cloud = PointCloud::new(
            (0..5).map(|i| pt(f64::from(i), 0.0, 0.0)).collect(),
            Some(vec![0.0, 1.0, 2.0, 3.0, 4.0]),
            Some((0..5).map(|i| Vector3::new(i as f32, 0.0, 0.0)).collect()),
        )
        .expect("valid");
        let out = retain(cloud.clone(), &[true, false, true, false, true]);
        assert_eq!(out.points.iter().map(|q| q.x).collect::<Vec<_>>(), vec![0.0, 2.0, 4.0]);
        assert_eq!(out.intensity, Some(vec![0.0, 2.0, 4.0]));
        assert_eq!(
            out.normals.as_ref().map(|n| n.iter().map(|v| v.x).collect::<Vec<_>>()),
            Some(vec![0.0, 2.0, 4.0])
        );
        // A short mask drops the points it does not cover.
        let out = retain(cloud, &[true, true]);
        assert_eq!(out.len(), 2);
        assert_eq!(out.intensity.map(|i| i.len()), Some(2));
    }

    #[test]
    fn intensity_window_is_inclusive_and_checks_its_input() {
        let cloud = PointCloud::new(
            (0..6).map(|i| pt(f64::from(i), 0.0, 0.0)).collect(),
            Some(vec![0.5, 1.0, 1.5, 2.0, f32::NAN, 3.0]),
            None,
        )
        .expect("valid");
        let (out, report) = intensity_window(cloud.clone(), 1.0, 2.0).expect("window");
        assert_eq!(out.points.iter().map(|q| q.x).collect::<Vec<_>>(), vec![1.0, 2.0, 3.0]);
        assert_eq!(report, FilterReport { filter: "intensity", kept: 3, removed: 3 });

        let e = intensity_window(cloud.clone(), 2.0, 1.0).expect_err("min > max");
        assert_eq!(e.to_string(), "invalid reconstruct.filters.intensity.max = 1: must be at least min = 2");
        let e = intensity_window(cloud.clone(), f32::NAN, 1.0).expect_err("NaN");
        assert!(e.to_string().starts_with("invalid reconstruct.filters.intensity.min = NaN"), "{e}");
        let bare = PointCloud::new(cloud.points.clone(), None, None).expect("bare");
        let e = intensity_window(bare, 0.0, 1.0).expect_err("no intensity");
        assert!(matches!(e, ReconError::MissingAttribute { what: "intensity", .. }), "{e}");
        let mut broken = cloud;
        broken.intensity = Some(vec![1.0]);
        assert!(matches!(intensity_window(broken, 0.0, 1.0), Err(ReconError::Geometry(_))));
    }

    #[test]
    fn empty_clouds_report_zero() {
        let empty = PointCloud::default();
        let reports = [
            statistical_outlier_removal(empty.clone(), 8, 2.0).expect("sor").1,
            radius_outlier_removal(empty.clone(), 1.0, 3).expect("ror").1,
            voxel_decimate(empty.clone(), 1.0).expect("voxel").1,
        ];
        for r in reports {
            assert_eq!((r.kept, r.removed), (0, 0), "{r:?}");
        }
        let with_intensity = PointCloud::new(vec![], Some(vec![]), None).expect("valid");
        assert_eq!(intensity_window(with_intensity, 0.0, 1.0).expect("window").1.kept, 0);
    }

    #[test]
    fn parameter_errors_name_the_field() {
        let pts = vec![pt(0.0, 0.0, 0.0); 3];
        let msg = |r: Result<Vec<bool>>| r.expect_err("must fail").to_string();
        assert_eq!(
            msg(statistical_outlier_mask(&pts, 0, 2.0)),
            "invalid reconstruct.filters.statistical.k = 0: must be at least 1"
        );
        assert!(
            msg(statistical_outlier_mask(&pts, 4, 0.0))
                .starts_with("invalid reconstruct.filters.statistical.n_sigma = 0")
        );
        assert!(msg(statistical_outlier_mask(&pts, 4, f64::INFINITY)).contains("n_sigma = inf"));
        assert!(
            msg(radius_outlier_mask(&pts, -1.0, 2))
                .starts_with("invalid reconstruct.filters.radius.radius_mm = -1")
        );
        assert!(msg(radius_outlier_mask(&pts, f64::NAN, 2)).contains("radius_mm = NaN"));
        assert!(
            msg(radius_outlier_mask(&pts, 1.0, 0))
                .starts_with("invalid reconstruct.filters.radius.min_neighbours = 0")
        );
        assert!(msg(voxel_keep_mask(&pts, 0.0)).starts_with("invalid reconstruct.filters.voxel_mm = 0"));
        assert!(knn_mean_distances(&pts, 0).is_err());
        // Voxels too small for the coordinates: an error, not an overflow.
        let far = vec![pt(0.0, 0.0, 0.0), pt(2f64.powi(40), 0.0, 0.0)];
        let e = msg(voxel_keep_mask(&far, 1e-6));
        assert!(e.contains("point 1 at (1099511627776, 0, 0) mm lies more than 2^53 voxels"), "{e}");
    }

    // ----- statistical outlier removal ---------------------------------------------------------

    #[test]
    fn sor_rule_matches_open3d_on_a_hand_example() {
        // x = 0, 1, 2, 3, 10 with k = 2 (the point itself and its nearest neighbour):
        // d = 0.5, 0.5, 0.5, 0.5, 3.5; μ = 1.1; sample σ = sqrt(1.8) = 1.342.
        // n_sigma = 1: threshold 2.44 drops x = 10. n_sigma = 2: threshold 3.78 keeps it (a
        // population σ = 1.2 would give 3.5 and drop it). Open3D 0.20 gives the same:
        // remove_statistical_outlier(2, 1.0) keeps [0, 1, 2, 3], (2, 2.0) keeps all five.
        let pts: Vec<Point3<f32>> = [0.0, 1.0, 2.0, 3.0, 10.0].iter().map(|&x| pt(x, 0.0, 0.0)).collect();
        assert_eq!(knn_mean_distances(&pts, 2).expect("means"), vec![0.5, 0.5, 0.5, 0.5, 3.5]);
        assert_eq!(
            statistical_outlier_mask(&pts, 2, 1.0).expect("mask"),
            vec![true, true, true, true, false]
        );
        assert_eq!(statistical_outlier_mask(&pts, 2, 2.0).expect("mask"), vec![true; 5]);
        // k larger than the cloud: the mean is over all points.
        assert_eq!(knn_mean_distances(&pts[..2], 10).expect("means"), vec![0.5, 0.5]);
    }

    #[test]
    fn sor_degenerate_clouds_keep_their_usable_points() {
        // Every mean equal (σ = 0): nothing stands out.
        let same = vec![pt(1.0, 2.0, 3.0); 50];
        assert_eq!(statistical_outlier_mask(&same, 8, 2.0).expect("mask"), vec![true; 50]);
        // One usable point; non-finite points are removed.
        let one = vec![pt(1.0, 2.0, 3.0), pt(f64::NAN, 0.0, 0.0), pt(0.0, f64::INFINITY, 0.0)];
        assert_eq!(statistical_outlier_mask(&one, 8, 2.0).expect("mask"), vec![true, false, false]);
        let (out, report) =
            statistical_outlier_removal(PointCloud::new(one, None, None).expect("cloud"), 8, 2.0)
                .expect("sor");
        assert_eq!((out.len(), report.kept, report.removed), (1, 1, 2));
    }

    /// The k smallest of `v` in ascending order, their k-th and mean of square roots (the
    /// obviously right way).
    fn sorted_knn(v: &[u64], k: usize) -> (f64, f64) {
        let mut w = v.to_vec();
        w.sort_unstable();
        let best: Vec<f64> = w[..k].iter().map(|&b| f64::from_bits(b)).collect();
        (best[k - 1], mean_sqrt(best.iter().copied()))
    }

    #[test]
    fn distance_kernels_match_the_portable_and_sorted_references() {
        let mut rng = StdRng::seed_from_u64(41);
        let avx512 = simd::has_avx512();
        for round in 0..400 {
            // A block on a coarse lattice (ties, duplicates, the query itself) or spread out.
            let n = rng.random_range(0..300usize);
            let coarse = round % 2 == 0;
            let coord = |rng: &mut StdRng| -> f32 {
                if coarse {
                    rng.random_range(-4i32..=4) as f32 * 0.25
                } else {
                    rng.random_range(-1.0f32..1.0)
                }
            };
            let pts: Vec<Xyz> =
                (0..n).map(|_| Xyz::new(coord(&mut rng), coord(&mut rng), coord(&mut rng))).collect();
            let mut block = Packed::default();
            let cut = rng.random_range(0..=n);
            block.fill(&pts, &[0..cut, cut..n]);
            if avx512 {
                let mut fast = Packed::default();
                simd::fill::<true>(&mut fast, &pts, &[0..cut, cut..n]);
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                for (a, b) in [(&block.x, &fast.x), (&block.y, &fast.y), (&block.z, &fast.z)] {
                    assert_eq!(bits(a), bits(b), "round {round}: vector fill");
                }
            }
            let q = if n > 0 && rng.random_bool(0.5) {
                wide(&pts[rng.random_range(0..n)])
            } else {
                wide(&Xyz::new(coord(&mut rng), coord(&mut rng), coord(&mut rng)))
            };
            let t2 = match round % 5 {
                0 => f64::INFINITY,
                1 => 0.0,
                _ => rng.random_range(0.0..2.0),
            };
            let mut slow = vec![0u64; n + FILTER_SLACK];
            let cnt = filter_portable(&block, &q, t2, &mut slow);
            // Bit for bit what `dist2` gives, in the points' order.
            let want: Vec<u64> = pts
                .iter()
                .map(|p| dist2(&Xyz::new(q[0] as f32, q[1] as f32, q[2] as f32), p))
                .filter(|&d| d <= t2)
                .map(f64::to_bits)
                .collect();
            assert_eq!(&slow[..cnt], &want[..], "round {round}: portable filter");
            if avx512 {
                let mut fast = vec![0u64; n + FILTER_SLACK];
                let c = simd::filter::<true>(&block, &q, t2, &mut fast);
                assert_eq!(&fast[..c], &want[..], "round {round}: vector filter");
            }
            // The hierarchy's leaf scan: the same pushes, from a fresh or a half-full set.
            if avx512 {
                let qp = Xyz::new(q[0] as f32, q[1] as f32, q[2] as f32);
                for k in [1, 7, 20, 70] {
                    let (mut a, mut b) = (KBest::new(k), KBest::new(k));
                    let split = n / 3;
                    for part in [&pts[..split], &pts[split..]] {
                        simd::leaf_scan::<false>(part, &qp, &mut a);
                        simd::leaf_scan::<true>(part, &qp, &mut b);
                        assert_eq!(a.worst().to_bits(), b.worst().to_bits(), "round {round}, k {k}: worst");
                    }
                    assert_eq!(
                        a.mean_distance().to_bits(),
                        b.mean_distance().to_bits(),
                        "round {round}, k {k}: mean"
                    );
                }
            }
            // The k-NN finish on the kept values: 0 to 20 surplus values.
            if cnt == 0 {
                continue;
            }
            let k = rng.random_range(cnt.saturating_sub(20).max(1)..=cnt);
            let (kth, mean) = sorted_knn(&want, k);
            let close = |m: f64| (m - mean).abs() <= 1e-13 * mean.max(1e-300);
            // The short list's bound: none, a kept value, one between, the top.
            let hint2 = match round % 4 {
                0 => f64::INFINITY,
                1 => f64::from_bits(want[rng.random_range(0..cnt)]) / TOP_FRACTION,
                2 => f64::from_bits(want[rng.random_range(0..cnt)] + 1),
                _ => 0.0,
            };
            let lower = if hint2.is_finite() { (hint2 * TOP_FRACTION).to_bits() } else { 0 };
            for (a_kth, a_mean) in [finish_any_portable(&want, k, lower), finish_steps_portable(&want, k)] {
                assert!(
                    a_kth == kth && close(a_mean),
                    "round {round}: any order {a_kth} {a_mean} vs {kth} {mean}"
                );
            }
            for order in [SumOrder::Ascending, SumOrder::Any] {
                let mut buf = want.clone();
                let (f_kth, f_mean) = finish_knn::<false>(&mut buf, cnt, k, order, hint2);
                assert_eq!(f_kth, kth, "round {round}: {order:?}");
                if order == SumOrder::Ascending {
                    assert_eq!(f_mean.to_bits(), mean.to_bits(), "round {round}: ascending sum");
                } else {
                    assert!(close(f_mean), "round {round}: {f_mean} vs {mean}");
                }
                if avx512 {
                    let mut buf = want.clone();
                    let (v_kth, v_mean) = finish_knn::<true>(&mut buf, cnt, k, order, hint2);
                    assert_eq!(v_kth, kth, "round {round}: vector {order:?}");
                    assert!(close(v_mean), "round {round}: vector {v_mean} vs {mean}");
                }
            }
        }
    }

    #[test]
    fn vector_cell_keys_match_the_portable_ones() {
        let mut rng = StdRng::seed_from_u64(43);
        for round in 0..300 {
            let dims =
                [rng.random_range(1..2000u64), rng.random_range(1..2000u64), rng.random_range(1..70_000u64)];
            let zbits = z_bits(dims[2]);
            let keying = Keying {
                origin: [
                    rng.random_range(-50.0..50.0),
                    rng.random_range(-50.0..50.0),
                    rng.random_range(-50.0..50.0),
                ],
                inv_h: 1.0 / rng.random_range(0.01..2.0),
                dims,
                zbits,
                limit: cell_key([dims[0].next_power_of_two() - 1, dims[1].next_power_of_two() - 1, 0], zbits)
                    + (1 << zbits),
            };
            let n = rng.random_range(0..100usize);
            let special = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1e30, 1e30, 0.0, -0.0];
            let coord = |rng: &mut StdRng| -> f32 {
                if rng.random_bool(0.05) {
                    special[rng.random_range(0..special.len())]
                } else {
                    rng.random_range(-2000.0f32..2000.0)
                }
            };
            let pts: Vec<Xyz> =
                (0..n).map(|_| Xyz::new(coord(&mut rng), coord(&mut rng), coord(&mut rng))).collect();
            let mut slow = vec![0u64; n];
            simd::keys_portable(&keying, &pts, &mut slow);
            for (p, &k) in pts.iter().zip(&slow) {
                assert_eq!(k, keying.key(p));
            }
            let mut fast = vec![0u64; n];
            simd::keys(&keying, &pts, &mut fast);
            assert_eq!(fast, slow, "round {round}");
        }
    }

    #[test]
    fn flag_sort_matches_a_sort_by_key_and_moves_every_lane() {
        let mut rng = StdRng::seed_from_u64(21);
        for (n, bits) in [(0usize, 8u32), (1, 8), (47, 12), (300, 20), (5000, 9), (70_000, 27), (40_000, 40)]
        {
            let keys: Vec<u64> = (0..n).map(|_| rng.random::<u64>() >> (64 - bits)).collect();
            // Every lane carries the point's original index, so the tuples can be checked.
            let pts: Vec<Xyz> = (0..n).map(|i| Point3::new(i as f32, 0.0, 0.0)).collect();
            let intensity: Vec<f32> = (0..n).map(|i| i as f32 + 0.5).collect();
            let normals: Vec<Vector3<f32>> = (0..n).map(|i| Vector3::new(0.0, i as f32, 0.0)).collect();
            let mut want: Vec<(u64, usize)> = keys.iter().copied().zip(0..).collect();
            want.sort_unstable();
            let check = |sorted: Vec<u64>, pts: &[Xyz], intensity: &[f32], normals: &[Vector3<f32>]| {
                let got: Vec<(u64, usize)> =
                    sorted.iter().zip(pts).map(|(&k, p)| (k, p.x as usize)).collect();
                let mut same = got.clone();
                same.sort_unstable();
                assert_eq!(same, want, "n = {n}, bits = {bits}: the same (key, point) pairs");
                assert!(got.windows(2).all(|w| w[0].0 <= w[1].0), "n = {n}, bits = {bits}: sorted");
                for (i, p) in pts.iter().enumerate() {
                    assert_eq!(intensity[i], p.x + 0.5);
                    assert_eq!(normals[i].y, p.x);
                }
            };
            let (mut p64, mut i64_, mut n64) = (pts.clone(), intensity.clone(), normals.clone());
            let mut k64 = keys.clone();
            let lanes =
                Lanes { keys: &mut k64, pts: &mut p64, intensity: Some(&mut i64_), normals: Some(&mut n64) };
            flag_sort(lanes, top_shift(1 << bits));
            check(k64, &p64, &i64_, &n64);
            if bits <= 32 {
                let (mut p32, mut i32_, mut n32) = (pts.clone(), intensity.clone(), normals.clone());
                let mut k32: Vec<u32> = keys.iter().map(|&k| k as u32).collect();
                let lanes = Lanes {
                    keys: &mut k32,
                    pts: &mut p32,
                    intensity: Some(&mut i32_),
                    normals: Some(&mut n32),
                };
                flag_sort(lanes, top_shift(1 << bits));
                check(k32.iter().map(|&k| u64::from(k)).collect(), &p32, &i32_, &n32);
            }
        }
    }

    #[test]
    fn sor_in_place_keeps_what_the_mask_keeps_with_the_attributes() {
        let mut rng = StdRng::seed_from_u64(23);
        let (planted_pts, _) = planted(&mut rng, false);
        let mut with_nan = surface(&mut rng, 3000);
        with_nan[17] = pt(f64::NAN, 1.0, 1.0);
        with_nan[2000] = pt(0.0, f64::INFINITY, 1.0);
        let clouds: Vec<(&str, Vec<Point3<f32>>)> = vec![
            ("planted", planted_pts),
            ("clustered", clustered(&mut rng, 6000)),
            ("lattice", lattice(&mut rng, 4000, 12)),
            ("non-finite", with_nan),
        ];
        for (name, pts) in clouds {
            let n = pts.len();
            // Attributes that name their point.
            let intensity: Vec<f32> = (0..n).map(|i| i as f32).collect();
            let normals: Vec<Vector3<f32>> = (0..n).map(|i| Vector3::new(i as f32, 0.0, 0.0)).collect();
            let cloud = PointCloud::new(pts.clone(), Some(intensity), Some(normals)).expect("cloud");
            for (k, n_sigma) in [(8usize, 1.0f64), (20, 2.0)] {
                let mask = statistical_outlier_mask(&pts, k, n_sigma).expect("mask");
                let mut want: Vec<usize> = (0..n).filter(|&i| mask[i]).collect();
                want.sort_unstable();
                // The stored single-precision means, and every mean measured again exactly.
                for slack in [STORED_SLACK, 1.0] {
                    let (out, report) = sor_in_place(cloud.clone(), k, n_sigma, slack, false).expect("sor");
                    let (intensity, normals) =
                        (out.intensity.expect("intensity"), out.normals.expect("normals"));
                    let mut got: Vec<usize> = intensity.iter().map(|&i| i as usize).collect();
                    for (j, &i) in got.iter().enumerate() {
                        assert_eq!(
                            out.points[j].coords, pts[i].coords,
                            "{name}: the point follows its attributes"
                        );
                        assert_eq!(normals[j].x as usize, i, "{name}");
                    }
                    got.sort_unstable();
                    assert_eq!(got, want, "{name}, k = {k}, n_sigma = {n_sigma}, slack = {slack}");
                    assert_eq!((report.kept, report.removed), (want.len(), n - want.len()), "{name}");
                }
            }
        }
    }

    #[test]
    fn knn_means_match_brute_force_on_random_clouds() {
        let mut rng = StdRng::seed_from_u64(11);
        let mut clouds: Vec<(&str, Vec<Point3<f32>>)> = vec![
            ("surface", surface(&mut rng, 2500)),
            ("uniform", uniform(&mut rng, 2000, 10.0)),
            ("lattice", lattice(&mut rng, 2000, 6)),
            ("clustered", clustered(&mut rng, 2000)),
        ];
        // Surface with 1 % far outliers, two non-finite points and a huge offset.
        let mut s = surface(&mut rng, 2000);
        s.extend(uniform(&mut rng, 20, 40.0).into_iter().map(|q| q + Vector3::new(-5.0, -5.0, 5.0)));
        s.push(pt(f64::NAN, 1.0, 1.0));
        s.push(pt(1.0, f64::NEG_INFINITY, 1.0));
        clouds.push(("outliers", s.clone()));
        clouds.push(("offset", s.iter().map(|q| q + Vector3::new(1e6, -2e6, 5e5)).collect()));
        let mut far = uniform(&mut rng, 1000, 5.0);
        far.push(pt(1e9, 1e9, 0.0));
        far.push(pt(-3e8, 0.0, 7e8));
        clouds.push(("huge extent", far));
        // Surface with 3 % stray points in the slab just around it (isolated cells among the
        // surface's: searched apart from the surface, and each other's neighbours).
        let mut near = surface(&mut rng, 2500);
        let strays: Vec<Point3<f32>> =
            uniform(&mut rng, 75, 25.0).into_iter().map(|q| Point3::new(q.x, q.y, q.z / 5.0 - 2.5)).collect();
        near.extend(strays);
        clouds.push(("near strays", near));
        // Scan lines: dense along x, 1.5 mm apart in y (the cell edge sized on the pairs is too
        // small for the gaps between lines, and the grid is built again larger).
        let lines: Vec<Point3<f32>> = (0..3000)
            .map(|i| {
                let (x, y) = ((i % 300) as f64 * 0.05, (i / 300) as f64 * 1.5);
                pt(x, y, 0.3 * (x / 4.0).sin() + 0.01 * gauss(&mut rng))
            })
            .collect();
        clouds.push(("scan lines", lines));

        let (mut tree_used, mut second_chance_used, mut strays_apart, mut grown) =
            (false, false, false, false);
        let ks = [1, 2, 5, 20, 70];
        for (name, pts) in &clouds {
            let slow = brute_means_multi(pts, &ks);
            for (k, slow) in ks.into_iter().zip(&slow) {
                let (fast, stats) = knn_means_with_stats(pts, k);
                assert!(same_means(&fast, slow), "{name}, k = {k}");
                assert_eq!(stats.grid + stats.tree, pts.iter().filter(|q| usable(*q)).count(), "{name}");
                tree_used |= stats.tree > 0;
                second_chance_used |= stats.second_chance > 0;
                strays_apart |= stats.stragglers > 0;
                grown |= stats.grown;
                if *name == "surface" && k == 20 {
                    assert!(!stats.grown, "{name}: {stats:?}");
                }
                assert!(stats.stragglers <= stats.tree, "{name}: {stats:?}");
                if *name == "surface" && k == 20 {
                    assert!(stats.tree * 10 < stats.grid, "{name}: {stats:?}");
                }
            }
        }
        assert!(tree_used && second_chance_used && strays_apart && grown);
    }

    #[test]
    fn knn_means_with_a_heap_of_duplicates() {
        let mut rng = StdRng::seed_from_u64(5);
        let mut pts = vec![pt(3.0, 3.0, 3.0); 4000];
        pts.extend(uniform(&mut rng, 500, 6.0));
        let ks = [5, 20];
        for (k, slow) in ks.into_iter().zip(brute_means_multi(&pts, &ks)) {
            let (fast, stats) = knn_means_with_stats(&pts, k);
            assert!(stats.overfull_cells > 0, "{stats:?}");
            assert!(same_means(&fast, &slow), "k = {k}");
            assert_eq!(fast[0], 0.0);
        }
        // The duplicates are the densest points: kept (Open3D would drop them, see the module docs).
        let keep = statistical_outlier_mask(&pts, 20, 2.0).expect("mask");
        assert!(keep[..4000].iter().all(|&k| k));
    }

    #[test]
    fn sor_mask_matches_reference() {
        let mut rng = StdRng::seed_from_u64(21);
        let mut pts = surface(&mut rng, 1500);
        pts.extend(uniform(&mut rng, 30, 25.0));
        pts.extend(lattice(&mut rng, 300, 4));
        for (k, n_sigma) in [(1, 1.0), (8, 0.5), (12, 3.0), (20, 2.0)] {
            assert_eq!(
                statistical_outlier_mask(&pts, k, n_sigma).expect("mask"),
                brute_sor_mask(&pts, k, n_sigma),
                "k = {k}, n_sigma = {n_sigma}"
            );
        }
    }

    /// A plane-like surface or a sphere, with noise, plus 1 % far outliers.
    fn planted(rng: &mut StdRng, sphere: bool) -> (Vec<Point3<f32>>, usize) {
        let mut pts: Vec<Point3<f64>> = if sphere {
            (0..20_000)
                .map(|_| {
                    let v = Vector3::new(gauss(rng), gauss(rng), gauss(rng)).normalize();
                    Point3::from(v * (20.0 + 0.02 * gauss(rng)))
                })
                .collect()
        } else {
            surface(rng, 20_000).iter().map(CloudPoint::at).collect()
        };
        let n = pts.len();
        let lo = pts.iter().fold(Vector3::repeat(f64::INFINITY), |a, q| a.inf(&q.coords));
        let hi = pts.iter().fold(Vector3::repeat(f64::NEG_INFINITY), |a, q| a.sup(&q.coords));
        while pts.len() < n + n / 100 {
            let q = Point3::from(
                lo - Vector3::repeat(10.0)
                    + (hi - lo + Vector3::repeat(20.0)).component_mul(&Vector3::new(
                        rng.random::<f64>(),
                        rng.random::<f64>(),
                        rng.random::<f64>(),
                    )),
            );
            // Far: at least 3 mm from the surface.
            let off = if sphere {
                (q.coords.norm() - 20.0).abs()
            } else {
                (q.z - 2.0 * (q.x / 7.0).sin() * (q.y / 5.0).cos()).abs()
            };
            if off >= 3.0 {
                pts.push(q);
            }
        }
        (pts.iter().map(depthmill_geometry::cloud::single).collect(), n)
    }

    #[test]
    fn planted_outliers_are_removed() {
        let mut rng = StdRng::seed_from_u64(3);
        for sphere in [false, true] {
            let (pts, n) = planted(&mut rng, sphere);
            let keep = statistical_outlier_mask(&pts, 20, 2.0).expect("sor");
            assert!(keep[n..].iter().all(|&k| !k), "sphere = {sphere}: an outlier survived SOR");
            let lost = keep[..n].iter().filter(|&&k| !k).count();
            assert!(lost * 200 <= n, "sphere = {sphere}: SOR removed {lost} of {n} surface points");

            let radius = if sphere { 2.0 } else { 1.5 };
            let keep = radius_outlier_mask(&pts, radius, 8).expect("ror");
            assert!(keep[n..].iter().all(|&k| !k), "sphere = {sphere}: an outlier survived ROR");
            let lost = keep[..n].iter().filter(|&&k| !k).count();
            assert!(lost * 1000 <= n, "sphere = {sphere}: ROR removed {lost} of {n} surface points");
        }
    }

    /// A densely scanned floor (0.1 mm apart), a steep wall beside it sampled four times more
    /// sparsely (as a scanner sees a 79° face), and stray points 1 to 3 mm over the floor.
    /// Returns the points and the ranges of the wall's and the strays'.
    fn floor_wall_strays(rng: &mut StdRng) -> (Vec<Point3<f32>>, Range<usize>, Range<usize>) {
        let mut pts = Vec::new();
        for i in 0..120 {
            for j in 0..120 {
                let (x, y) = (f64::from(i) * 0.1, f64::from(j) * 0.1);
                pts.push(pt(
                    x + rng.random_range(-0.03..0.03),
                    y + rng.random_range(-0.03..0.03),
                    0.01 * gauss(rng),
                ));
            }
        }
        let wall = pts.len();
        for i in 0..12 {
            for j in 0..30 {
                // Rising 5 mm per mm: 0.41 mm apart along the slope, 0.4 mm along Y.
                let t = f64::from(i) * 0.08;
                let y = f64::from(j) * 0.4 + rng.random_range(-0.05..0.05);
                pts.push(pt(12.0 + t, y, 5.0 * t + 0.01 * gauss(rng)));
            }
        }
        let strays = pts.len();
        for _ in 0..40 {
            let (x, y) = (rng.random_range(1.0..11.0), rng.random_range(1.0..11.0));
            pts.push(pt(x, y, rng.random_range(1.0..3.0)));
        }

        let n = pts.len();
        (pts, wall..strays, strays..n)
    }

    /// O(n²) reference of the surface rule: the brute-force SOR mask, then for every point it
    /// drops, its `k` nearest other usable points by sorting every distance.
    fn brute_sor_keeping_surface(points: &[Point3<f32>], k: usize, n_sigma: f64) -> Vec<bool> {
        let mut keep = brute_sor_mask(points, k, n_sigma);
        let all: Vec<usize> = (0..points.len()).filter(|&i| usable(&points[i])).collect();
        let k = k.min(all.len());
        for i in 0..points.len() {
            if keep[i] || !usable(&points[i]) {
                continue;
            }
            let mut others: Vec<(f64, usize)> =
                all.iter().filter(|&&j| j != i).map(|&j| (dist2(&points[i], &points[j]), j)).collect();
            others.sort_by(|a, b| a.0.total_cmp(&b.0));
            let nb: Vec<[f64; 3]> = others.iter().take(k).map(|&(_, j)| wide(&points[j])).collect();
            keep[i] = on_sampled_surface(&wide(&points[i]), &nb);
        }
        keep
    }

    #[test]
    fn sor_keeping_surface_matches_its_brute_force_reference_in_place_and_as_a_mask() {
        let mut rng = StdRng::seed_from_u64(29);
        let (planted_pts, _) = planted(&mut rng, false);
        let (wall_pts, _, _) = floor_wall_strays(&mut rng);
        let mut with_nan = surface(&mut rng, 3000);
        with_nan[5] = pt(f64::NAN, 1.0, 1.0);
        let clouds: Vec<(&str, Vec<Point3<f32>>)> = vec![
            ("planted", planted_pts[..6000].to_vec()),
            ("floor, wall, strays", wall_pts),
            ("clustered", clustered(&mut rng, 3000)),
            ("uniform", uniform(&mut rng, 2000, 10.0)),
            ("non-finite", with_nan),
        ];
        for (name, pts) in clouds {
            let n = pts.len();
            let intensity: Vec<f32> = (0..n).map(|i| i as f32).collect();
            let cloud = PointCloud::new(pts.clone(), Some(intensity), None).expect("cloud");
            for (k, n_sigma) in [(8usize, 1.0f64), (12, 3.0)] {
                let want = brute_sor_keeping_surface(&pts, k, n_sigma);
                let plain = brute_sor_mask(&pts, k, n_sigma);
                let rescued = (0..n).filter(|&i| want[i] && !plain[i]).count();
                let mask = statistical_outlier_mask_keeping_surface(&pts, k, n_sigma).expect("mask");
                assert_eq!(
                    mask, want,
                    "{name}, k = {k}, n_sigma = {n_sigma}: the mask ({rescued} kept back)"
                );
                let (out, report) = sor_in_place(cloud.clone(), k, n_sigma, STORED_SLACK, true).expect("sor");
                let mut got: Vec<usize> =
                    out.intensity.expect("intensity").iter().map(|&i| i as usize).collect();
                got.sort_unstable();
                let want_idx: Vec<usize> = (0..n).filter(|&i| want[i]).collect();
                assert_eq!(got, want_idx, "{name}, k = {k}, n_sigma = {n_sigma}: in place");
                assert_eq!(report.kept, want_idx.len());
            }
        }
    }

    #[test]
    fn sor_keeping_surface_keeps_a_sparsely_sampled_wall_and_still_drops_strays() {
        let mut rng = StdRng::seed_from_u64(31);
        let (pts, wall, strays) = floor_wall_strays(&mut rng);
        let plain = statistical_outlier_mask(&pts, 12, 3.0).expect("sor");
        let kept = statistical_outlier_mask_keeping_surface(&pts, 12, 3.0).expect("sor");
        let wall_n = wall.len();
        let lost_plain = wall.clone().filter(|&i| !plain[i]).count();
        let lost_kept = wall.clone().filter(|&i| !kept[i]).count();
        // Open3D's rule takes much of the wall as outliers (its points are 4x farther apart).
        assert!(lost_plain * 4 >= wall_n, "plain SOR removed only {lost_plain} of {wall_n} wall points");
        assert!(lost_kept * 100 <= wall_n, "{lost_kept} of {wall_n} wall points removed");
        assert!(strays.clone().all(|i| !plain[i] && !kept[i]), "a stray point survived");
        // Nothing the plain rule keeps is lost.
        assert!(plain.iter().zip(&kept).all(|(&p, &k)| !p || k));

        // A row of strays 1 mm apart 70 mm over the floor: with the floor's nearest points they
        // make a flat neighbourhood, but not a compact one.
        let mut pts = pts[..wall.start].to_vec();
        let row = pts.len();
        pts.extend((0..10).map(|i| pt(1.0 + f64::from(i), 4.0, 70.0)));
        let kept = statistical_outlier_mask_keeping_surface(&pts, 12, 3.0).expect("sor");
        assert!(kept[row..].iter().all(|&k| !k), "a stray of the row survived");
    }

    // ----- radius outlier removal --------------------------------------------------------------

    #[test]
    fn ror_matches_brute_force() {
        let mut rng = StdRng::seed_from_u64(8);
        let mut outliers = surface(&mut rng, 1500);
        outliers.extend(uniform(&mut rng, 40, 30.0));
        outliers.push(pt(f64::NAN, 0.0, 0.0));
        let clouds =
            [outliers, lattice(&mut rng, 1500, 7), clustered(&mut rng, 1500), uniform(&mut rng, 1000, 8.0)];
        for pts in &clouds {
            let sorted = brute_sorted_d2(pts);
            for (r, min) in [(0.5, 1), (0.5, 4), (1.0, 10), (3.0, 30), (1e-3, 1), (100.0, 2)] {
                assert_eq!(
                    radius_outlier_mask(pts, r, min).expect("mask"),
                    brute_ror_mask(&sorted, r, min),
                    "r = {r}, min = {min}"
                );
            }
        }
    }

    #[test]
    fn ror_radius_is_strict_and_counts_others() {
        // Open3D 0.20: remove_radius_outlier(1, 1.0) on (0,0,0), (1,0,0), (5,0,0) keeps none;
        // with radius 1.0000001 it keeps the first two.
        let pts = vec![pt(0.0, 0.0, 0.0), pt(1.0, 0.0, 0.0), pt(5.0, 0.0, 0.0)];
        assert_eq!(radius_outlier_mask(&pts, 1.0, 1).expect("mask"), vec![false; 3]);
        assert_eq!(radius_outlier_mask(&pts, 1.000_000_1, 1).expect("mask"), vec![true, true, false]);
        let (out, report) =
            radius_outlier_removal(PointCloud::new(pts, None, None).expect("cloud"), 1.000_000_1, 1)
                .expect("ror");
        assert_eq!((out.len(), report), (2, FilterReport { filter: "radius", kept: 2, removed: 1 }));
    }

    // ----- voxel decimation --------------------------------------------------------------------

    #[test]
    fn voxel_decimation_matches_brute_force() {
        let mut rng = StdRng::seed_from_u64(13);
        let mut with_nan = surface(&mut rng, 2000);
        with_nan.push(pt(0.0, f64::NAN, 0.0));
        let clouds =
            [with_nan, lattice(&mut rng, 2000, 9), clustered(&mut rng, 2000), uniform(&mut rng, 2000, 3.0)];
        for pts in &clouds {
            for voxel in [0.1, 0.7, 2.0, 50.0] {
                assert_eq!(
                    voxel_keep_mask(pts, voxel).expect("mask"),
                    brute_voxel_mask(pts, voxel),
                    "voxel {voxel}"
                );
            }
        }
    }

    #[test]
    fn packed_voxel_path_keeps_what_the_general_one_keeps() {
        let mut rng = StdRng::seed_from_u64(45);
        let mut packed = 0;
        for round in 0..60 {
            let mut pts = match round % 3 {
                0 => uniform(&mut rng, 3000, 20.0),
                1 => surface(&mut rng, 3000),
                _ => clustered(&mut rng, 3000),
            };
            pts.push(Xyz::new(f32::NAN, 0.0, 0.0));
            // Voxels from a tenth of a millimetre to wider than the cloud; coordinates around
            // negative and positive offsets.
            let offset = rng.random_range(-1000.0f32..1000.0);
            for p in &mut pts {
                p.x += offset;
            }
            let voxel = 10f64.powf(rng.random_range(-1.0..1.5));
            let general = voxel_keep_general(&pts, voxel).expect("general");
            if let Some(fast) = voxel_keep_packed(&pts, voxel) {
                assert_eq!(fast, general, "round {round}, voxel {voxel}");
                packed += 1;
            }
            assert_eq!(voxel_keep_mask(&pts, voxel).expect("mask"), general, "round {round}");
        }
        assert!(packed > 40, "only {packed} clouds took the packed path");
        // Clouds of several tasks' chunks with unusable points among them: the chunked passes,
        // and voxels whose runs straddle the cuts between spans (the surface's rows and the
        // clusters' heaps span chunks).
        for round in 0..4 {
            let mut pts =
                if round % 2 == 0 { surface(&mut rng, 60_000) } else { clustered(&mut rng, 60_000) };
            for i in (round..pts.len()).step_by(997) {
                pts[i] = Xyz::new(0.0, f32::NAN, 0.0);
            }
            for voxel in [0.3, 2.0, 40.0] {
                let general = voxel_keep_general(&pts, voxel).expect("general");
                let fast = voxel_keep_packed(&pts, voxel).expect("packed path");
                assert_eq!(fast, general, "large round {round}, voxel {voxel}");
            }
        }
        // The voxel index is the floor, negative coordinates and exact multiples included.
        for _ in 0..20_000 {
            let voxel = 10f64.powf(rng.random_range(-3.0..2.0));
            let c = match rng.random_range(0..3) {
                0 => rng.random_range(-1e4..1e4),
                1 => rng.random_range(-50i32..50) as f64 * voxel,
                _ => -rng.random_range(0.0..1e-9),
            };
            let p = Point3::new(c, -c, c * 0.5);
            let want = [c, -c, c * 0.5].map(|x| (x / voxel).floor() as i64);
            assert_eq!(voxel_of(&p, voxel), Some(want), "{c} / {voxel}");
        }
        assert_eq!(voxel_of(&Point3::new(f64::NAN, 0.0, 0.0), 1.0), None);
        assert_eq!(voxel_of(&Point3::new(1e300, 0.0, 0.0), 1.0), None);
        // More than 32 bits of voxels: the general path.
        let wide = vec![Xyz::new(0.0, 0.0, 0.0), Xyz::new(1e4, 1e4, 1e4), Xyz::new(5e3, 1.0, 2.0)];
        assert!(voxel_keep_packed(&wide, 0.01).is_none());
        assert_eq!(voxel_keep_mask(&wide, 0.01).expect("mask"), vec![true; 3]);
    }

    #[test]
    fn voxel_decimation_keeps_original_points_and_attributes() {
        // Voxel 1: (0.1, 0.1), (0.5, 0.5), (0.9, 0.9) -> centroid (0.5, 0.5) -> the middle point.
        // Voxel 2: one point. Voxel 3: two points equally far from their centroid -> the first.
        let pts = vec![
            pt(0.1, 0.1, 0.0),
            pt(5.5, 0.5, 0.5),
            pt(0.5, 0.5, 0.0),
            pt(-0.2, 0.0, 0.0),
            pt(0.9, 0.9, 0.0),
            pt(-0.8, 0.0, 0.0),
        ];
        let cloud = PointCloud::new(pts, Some(vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]), None).expect("valid");
        let (out, report) = voxel_decimate(cloud, 1.0).expect("voxel");
        assert_eq!(out.intensity, Some(vec![1.0, 2.0, 3.0]));
        assert_eq!(out.points[1], pt(0.5, 0.5, 0.0));
        assert_eq!(report, FilterReport { filter: "voxel", kept: 3, removed: 3 });
        // Huge extents with a reasonable voxel are fine.
        let far = vec![pt(-1e12, 0.0, 0.0), pt(1e12, 0.0, 0.0), pt(1e12, 0.0, 0.5)];
        assert_eq!(voxel_keep_mask(&far, 1.0).expect("mask"), vec![true, true, false]);
    }

    #[test]
    fn radix_sort_is_a_stable_sort_on_the_key_bits() {
        let mut rng = StdRng::seed_from_u64(2);
        let mut items: Vec<u64> = (0..5000u64).map(|i| (rng.random_range(0..3000u64) << 32) | i).collect();
        let mut expected = items.clone();
        expected.sort_unstable();
        radix_sort_bits(&mut items, 32, 12);
        assert_eq!(items, expected);
    }

    #[test]
    fn column_table_finds_the_blocks_the_search_finds() {
        let mut rng = StdRng::seed_from_u64(44);
        let mut tables = 0;
        for (round, h) in [0.4, 0.9, 2.5, 7.0].into_iter().enumerate() {
            // Uniform, a surface and clusters: full, sparse and empty columns.
            let mut pts = uniform(&mut rng, 2000, 20.0);
            pts.extend(surface(&mut rng, 3000));
            pts.extend(clustered(&mut rng, 1000));
            let bbox = UsableBox::of(&pts).expect("box");
            let grid = Grid::build(&pts, &bbox, h, false);
            let Some(columns) = Columns::build(&grid) else {
                continue;
            };
            let (mut a, mut b) = (Vec::new(), Vec::new());
            for c in 0..grid.keys.len() {
                for ring in [1, 2, 3] {
                    grid.block_ranges(c, ring, &mut a);
                    grid.block_ranges_with(Some(&columns), c, ring, &mut b);
                    assert_eq!(a, b, "round {round}, cell {c}, ring {ring}");
                }
            }
            tables += 1;
        }
        assert!(tables >= 2, "only {tables} grids small enough for a column table");
    }

    #[test]
    fn cell_keys_round_trip_and_seek_finds_lower_bounds() {
        let mut rng = StdRng::seed_from_u64(4);
        let pts = uniform(&mut rng, 3000, 20.0);
        let bbox = UsableBox::of(&pts).expect("box");
        let grid = Grid::build(&pts, &bbox, 0.7, false);
        for &key in &grid.keys {
            let c = grid.coords(key);
            assert!(c.iter().zip(&grid.dims).all(|(c, d)| c < d));
            assert_eq!(cell_key(c, grid.zbits), key);
        }
        assert!(grid.keys.windows(2).all(|w| w[0] < w[1]));
        let max = grid.keys.last().copied().unwrap_or(0) + 3;
        for _ in 0..2000 {
            let target = rng.random_range(0..max);
            let from = rng.random_range(0..=grid.keys.len());
            assert_eq!(grid.seek(from, target), grid.keys.partition_point(|&k| k < target));
        }
        for v in [0, 1, 0xF_FFFF, 0xA_BCDE] {
            assert_eq!(compact2(spread2(v)), v);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn fast_filters_match_references_on_lattice_clouds(
            coords in proptest::collection::vec((0i32..6, 0i32..6, 0i32..4), 1..160),
            k in 1usize..30,
            n_sigma in 0.1f64..3.0,
            radius in 0.2f64..2.5,
            min in 1usize..12,
            voxel in 0.3f64..3.0,
        ) {
            let pts: Vec<Point3<f32>> =
                coords.iter().map(|&(x, y, z)| pt(f64::from(x) * 0.5, f64::from(y) * 0.5, f64::from(z) * 0.75)).collect();
            prop_assert!(same_means(&knn_mean_distances(&pts, k).expect("means"), &brute_means(&pts, k)));
            prop_assert_eq!(statistical_outlier_mask(&pts, k, n_sigma).expect("sor"), brute_sor_mask(&pts, k, n_sigma));
            prop_assert_eq!(
                radius_outlier_mask(&pts, radius, min).expect("ror"),
                brute_ror_mask(&brute_sorted_d2(&pts), radius, min)
            );
            prop_assert_eq!(voxel_keep_mask(&pts, voxel).expect("voxel"), brute_voxel_mask(&pts, voxel));
        }
    }

    // ----- spheres and beacons -------------------------------------------------------------------

    /// Points on the cap of polar angle up to `cap_deg` (from +Z) of a sphere, with radial
    /// Gaussian noise `sigma`.
    fn cap(rng: &mut StdRng, c: Point3<f64>, r: f64, cap_deg: f64, n: usize, sigma: f64) -> Vec<Point3<f64>> {
        let cos_max = cap_deg.to_radians().cos();
        (0..n)
            .map(|_| {
                // Uniform on the cap: cos θ uniform in [cos_max, 1].
                let ct = cos_max + (1.0 - cos_max) * rng.random::<f64>();
                let st = (1.0 - ct * ct).max(0.0).sqrt();
                let ph = rng.random::<f64>() * std::f64::consts::TAU;
                let dir = Vector3::new(st * ph.cos(), st * ph.sin(), ct);
                c + dir * (r + sigma * gauss(rng))
            })
            .collect()
    }

    #[test]
    fn fit_sphere_exact_points() {
        let c = p(1.0, -2.0, 3.0);
        let pts: Vec<Point3<f64>> =
            [Vector3::x(), -Vector3::x(), Vector3::y(), Vector3::z(), Vector3::new(0.6, 0.0, 0.8)]
                .iter()
                .map(|d| c + d * 4.0)
                .collect();
        let fit = fit_sphere(&pts).expect("fit");
        assert!((fit.center - c).norm() < 1e-9 && (fit.radius_mm - 4.0).abs() < 1e-9, "{fit:?}");
        assert!(fit.rms_mm < 1e-9 && fit.points == 5);
    }

    #[test]
    fn fit_sphere_on_a_noisy_120_degree_cap() {
        let mut rng = StdRng::seed_from_u64(17);
        let (c, r) = (p(10.0, -5.0, 30.0), 12.7);
        let pts = cap(&mut rng, c, r, 60.0, 5000, 0.035);
        let fit = fit_sphere(&pts).expect("fit");
        assert!((fit.center - c).norm() < 0.02, "centre off by {}", (fit.center - c).norm());
        assert!((fit.radius_mm - r).abs() < 0.01, "radius {}", fit.radius_mm);
        assert!((fit.rms_mm - 0.035).abs() < 0.003, "rms {}", fit.rms_mm);
    }

    #[test]
    fn fit_sphere_rejects_bad_input() {
        let e = fit_sphere(&[p(0.0, 0.0, 0.0); 3]).expect_err("3 points");
        assert_eq!(e.to_string(), "invalid sphere_fit.points = 3: a sphere fit needs at least 4 points");
        let plane: Vec<Point3<f64>> = (0..20).map(|i| p(f64::from(i % 5), f64::from(i / 5), 2.0)).collect();
        assert!(fit_sphere(&plane).expect_err("coplanar").to_string().contains("coplanar"));
        let line: Vec<Point3<f64>> = (0..20).map(|i| p(f64::from(i), 2.0 * f64::from(i), 0.0)).collect();
        assert!(fit_sphere(&line).is_err());
        assert!(fit_sphere(&[p(1.0, 1.0, 1.0); 6]).is_err());
        let e = fit_sphere(&[p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(0.0, f64::NAN, 0.0), p(0.0, 0.0, 1.0)])
            .expect_err("NaN");
        assert!(e.to_string().starts_with("invalid sphere_fit.points[2] = (0, NaN, 0)"), "{e}");
    }

    #[test]
    fn fit_beacon_ignores_the_table_around_it() {
        let mut rng = StdRng::seed_from_u64(29);
        // A 20 mm ball on a table (z = 0), scanned from above: 4 points/mm² on what is visible.
        let (c, r) = (p(50.0, 20.0, 10.0), 10.0);
        let mut pts = cap(&mut rng, c, r, 107.0, 3300, 0.035);
        for _ in 0..6400 {
            let (x, y) = (30.0 + 40.0 * rng.random::<f64>(), 40.0 * rng.random::<f64>());
            if (x - c.x).hypot(y - c.y) > r {
                pts.push(p(x, y, 0.035 * gauss(&mut rng)));
            }
        }
        // Some clutter inside the search ball.
        for _ in 0..30 {
            pts.push(c + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 4.0);
        }
        let approx = p(50.8, 19.5, 10.6);
        let fit = fit_beacon(&pts, approx, 16.0).expect("beacon");
        assert!((fit.center - c).norm() < 0.02, "centre off by {}", (fit.center - c).norm());
        assert!((fit.radius_mm - r).abs() < 0.01, "radius {}", fit.radius_mm);
        assert!(fit.rms_mm < 0.045, "rms {}", fit.rms_mm);
        // A plain least-squares fit of the same selection is pulled off by the table.
        let sel: Vec<Point3<f64>> = pts.iter().filter(|q| (*q - approx).norm() <= 16.0).copied().collect();
        let plain = fit_sphere(&sel).expect("plain");
        assert!((plain.center - c).norm() > 0.1, "plain fit unexpectedly good: {plain:?}");

        let e = fit_beacon(&pts, p(500.0, 0.0, 0.0), 5.0).expect_err("nothing there");
        assert!(e.to_string().contains("only 0 points lie within it of (500, 0, 0)"), "{e}");
        assert!(fit_beacon(&pts, approx, 0.0).is_err());
    }

    #[test]
    fn beacon_frame_places_the_centres() {
        let mut rng = StdRng::seed_from_u64(31);
        for _ in 0..20 {
            let canon = [
                p(0.0, 0.0, 0.0),
                p(120.0, 0.0, 0.0),
                p(rng.random_range(-50.0..150.0), rng.random_range(20.0..90.0), 0.0),
            ];
            let cloud_from_beacon = Isometry3::from_parts(
                Translation3::new(
                    rng.random_range(-100.0..100.0),
                    rng.random_range(-100.0..100.0),
                    rng.random_range(-100.0..100.0),
                ),
                UnitQuaternion::from_euler_angles(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(-3.0..3.0),
                ),
            );
            let seen = canon.map(|q| cloud_from_beacon * q);
            let iso = beacon_frame(seen).expect("frame");
            for (s, c) in seen.iter().zip(&canon) {
                assert!((iso * s - c).norm() < 1e-9, "{} vs {}", iso * s, c);
            }
            assert!((iso * cloud_from_beacon).to_homogeneous().relative_eq(&Matrix4::identity(), 1e-9, 1e-9));
        }
        // Swapping the last two centres flips Z and still puts the third at y > 0.
        let iso = beacon_frame([p(0.0, 0.0, 0.0), p(0.0, 10.0, 0.0), p(5.0, 0.0, 0.0)]).expect("frame");
        let third = iso * p(5.0, 0.0, 0.0);
        assert!(third.y > 0.0 && third.z.abs() < 1e-12, "{third}");
    }

    #[test]
    fn beacon_frame_rejects_collinear_centres() {
        let e =
            beacon_frame([p(0.0, 0.0, 0.0), p(10.0, 0.0, 0.0), p(20.0, 0.01, 0.0)]).expect_err("collinear");
        assert!(e.to_string().contains("(nearly) collinear"), "{e}");
        assert!(beacon_frame([p(1.0, 1.0, 1.0); 3]).is_err());
        assert!(beacon_frame([p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(f64::NAN, 1.0, 0.0)]).is_err());
    }

    // ----- user transforms -------------------------------------------------------------------------

    fn rows(m: Matrix4<f64>) -> [[f64; 4]; 4] {
        std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
    }

    #[test]
    fn rigid_from_matrix_accepts_rigid_transforms_only() {
        let iso = Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 3.5),
            rotation_from_ypr_deg(30.0, -10.0, 75.0),
        );
        let got = rigid_from_matrix(rows(iso.to_homogeneous())).expect("rigid");
        assert!(got.to_homogeneous().relative_eq(&iso.to_homogeneous(), 1e-12, 1e-12));
        // Within the tolerance.
        let mut m = rows(iso.to_homogeneous());
        m[0][1] += 1e-8;
        assert!(rigid_from_matrix(m).is_ok());

        let scaled = rows(Matrix4::new_scaling(2.0));
        assert!(rigid_from_matrix(scaled).expect_err("scale").to_string().contains("not orthonormal"));
        let mut mirror = rows(Matrix4::identity());
        mirror[2][2] = -1.0;
        assert!(rigid_from_matrix(mirror).expect_err("mirror").to_string().contains("determinant -1"));
        let mut last = rows(Matrix4::identity());
        last[3][0] = 0.5;
        assert_eq!(
            rigid_from_matrix(last).expect_err("last row").to_string(),
            "invalid reconstruct.filters.transform[3][0] = 0.5: the last row must be 0 0 0 1 (within 0.000001)"
        );
        let mut nan = rows(Matrix4::identity());
        nan[1][2] = f64::NAN;
        assert!(
            rigid_from_matrix(nan)
                .expect_err("NaN")
                .to_string()
                .starts_with("invalid reconstruct.filters.transform[1][2] = NaN")
        );
    }

    #[test]
    fn rigid_from_xyz_ypr_matches_the_geometry_pose() {
        let v = XyzYpr { x_mm: 5.0, y_mm: -1.0, z_mm: 2.0, yaw_deg: 90.0, pitch_deg: 10.0, roll_deg: -20.0 };
        let got = rigid_from_xyz_ypr([5.0, -1.0, 2.0], 90.0, 10.0, -20.0).expect("pose");
        assert!(got.to_homogeneous().relative_eq(&v.to_pose().expect("pose").to_homogeneous(), 1e-12, 1e-12));
        let e = rigid_from_xyz_ypr([0.0, 0.0, 0.0], 0.0, f64::NAN, 0.0).expect_err("NaN");
        assert_eq!(e.to_string(), "invalid reconstruct.filters.transform.pitch_deg = NaN: must be finite");
    }
}

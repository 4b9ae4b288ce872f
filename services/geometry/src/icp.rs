//! Point-to-plane ICP with a robust kernel: refines the rigid transform that places a source cloud
//! on a target cloud (pairwise registration of partial scans).
//!
//! Each iteration pairs every transformed source point with its nearest target point within
//! `max_correspondence_mm` (a k-d tree over the target, `kiddo`), and solves the linearised
//! point-to-plane problem `min Σ w(rᵢ)·rᵢ²`, `rᵢ = nᵢ·(R pᵢ + t − qᵢ)`, for a small rotation ω
//! and translation t: `(Σ w JJᵀ) x = −Σ w J r` with `J = [p × n; n]` (6×6 normal equations,
//! Cholesky), then applies `exp(ω), t` on the left. `w` is the robust kernel's weight
//! (iteratively reweighted least squares): Tukey's biweight by default, so correspondences
//! farther than its width from the plane (overlap edges, outliers, another surface) stop pulling.
//! The width is graduated: it starts at the correspondence distance and halves every iteration
//! down to the kernel's own, so a misplaced start is not left with nothing inside the kernel.
//! The correspondences and the sums run in parallel (rayon). It stops like Open3D's
//! `registration_icp`: when fitness and inlier RMSE change by less than their relative
//! tolerances, or after `max_iterations`.
//!
//! Target normals are given or estimated by PCA over the `normal_k` nearest points. Where the
//! initial transform is poor (a table angle off by degrees), [`icp_with_coarse_start`] first tries
//! turns about the vertical axis through the source's centre and keeps the one that fits best.

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{
    Isometry3, Matrix3, Matrix6, Point3, SymmetricEigen, Translation3, UnitQuaternion, Vector3, Vector6,
};
use rayon::prelude::*;
use serde::Serialize;

/// A step smaller than this (its translation plus its rotation at 100 correspondence distances,
/// mm: a micrometre, far under any scanner's noise) ends the iterations, as settled fitness and
/// RMSE do.
const MIN_STEP_MM: f64 = 1e-3;

/// Why registration cannot run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IcpError {
    #[error("invalid {field} = {value}: {reason}")]
    Invalid { field: &'static str, value: String, reason: &'static str },
    #[error("the {which} cloud has {n} points, at least {min} are needed")]
    TooFewPoints { which: &'static str, n: usize, min: usize },
    #[error("the {which} cloud has a non-finite point at index {index}")]
    NotFinite { which: &'static str, index: usize },
    #[error("{0}")]
    Degenerate(String),
}

/// The robust kernel of the reweighted least squares.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum Kernel {
    /// Plain least squares.
    L2,
    /// Huber: quadratic within `k`, linear beyond.
    Huber(f64),
    /// Tukey's biweight: no pull beyond `k`.
    Tukey(f64),
    /// Cauchy (Lorentzian) with scale `k`.
    Cauchy(f64),
}

impl Kernel {
    /// IRLS weight of residual `r`.
    pub fn weight(&self, r: f64) -> f64 {
        match *self {
            Kernel::L2 => 1.0,
            Kernel::Huber(k) => {
                let a = r.abs();
                if a <= k { 1.0 } else { k / a }
            }
            Kernel::Tukey(k) => {
                let u = r / k;
                if u.abs() >= 1.0 { 0.0 } else { (1.0 - u * u).powi(2) }
            }
            Kernel::Cauchy(k) => 1.0 / (1.0 + (r / k).powi(2)),
        }
    }

    /// The kernel of iteration `it`: its width starts at the correspondence distance and halves
    /// every iteration down to its own (graduated: from a misplaced start every residual may be
    /// beyond a narrow kernel, which would then weigh nothing).
    pub fn annealed(&self, it: u32, max_correspondence_mm: f64) -> Kernel {
        let w = |k: f64| k.max(max_correspondence_mm * 0.5f64.powi(it.min(60) as i32));
        match *self {
            Kernel::L2 => Kernel::L2,
            Kernel::Huber(k) => Kernel::Huber(w(k)),
            Kernel::Tukey(k) => Kernel::Tukey(w(k)),
            Kernel::Cauchy(k) => Kernel::Cauchy(w(k)),
        }
    }

    fn width(&self) -> Option<f64> {
        match *self {
            Kernel::L2 => None,
            Kernel::Huber(k) | Kernel::Tukey(k) | Kernel::Cauchy(k) => Some(k),
        }
    }
}

/// ICP settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct IcpOptions {
    /// Farthest a correspondence may be, mm.
    pub max_correspondence_mm: f64,
    pub max_iterations: u32,
    /// Stop when fitness changes by less than this, relatively.
    pub relative_fitness: f64,
    /// ... and the inlier RMSE by less than this, relatively.
    pub relative_rmse: f64,
    pub kernel: Kernel,
}

impl Default for IcpOptions {
    fn default() -> Self {
        Self {
            max_correspondence_mm: 1.0,
            max_iterations: 30,
            relative_fitness: 1e-6,
            relative_rmse: 1e-6,
            kernel: Kernel::Tukey(0.3),
        }
    }
}

impl IcpOptions {
    fn validate(&self) -> Result<(), IcpError> {
        let m = self.max_correspondence_mm;
        if !(m.is_finite() && m > 0.0) {
            return Err(IcpError::Invalid {
                field: "max_correspondence_mm",
                value: m.to_string(),
                reason: "a positive distance",
            });
        }
        if self.max_iterations == 0 || self.max_iterations > 10_000 {
            return Err(IcpError::Invalid {
                field: "max_iterations",
                value: self.max_iterations.to_string(),
                reason: "1 to 10000",
            });
        }
        for (field, v) in [("relative_fitness", self.relative_fitness), ("relative_rmse", self.relative_rmse)]
        {
            if !(v.is_finite() && v >= 0.0) {
                return Err(IcpError::Invalid { field, value: v.to_string(), reason: "a tolerance >= 0" });
            }
        }
        if let Some(k) = self.kernel.width()
            && !(k.is_finite() && k > 0.0)
        {
            return Err(IcpError::Invalid {
                field: "kernel",
                value: k.to_string(),
                reason: "a positive width",
            });
        }
        Ok(())
    }
}

/// The result of a registration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct IcpResult {
    /// `target_from_source`.
    #[serde(skip)]
    pub transform: Isometry3<f64>,
    /// Share of source points with a correspondence within the distance.
    pub fitness: f64,
    /// RMS distance between corresponding points (point to point), mm.
    pub inlier_rmse_mm: f64,
    /// RMS of the point-to-plane residuals, mm.
    pub plane_rmse_mm: f64,
    pub correspondences: usize,
    pub iterations: u32,
}

/// The cloud registered onto: points, normals and a k-d tree over the points.
///
/// The tree holds `f32` coordinates about the cloud's centre (half the memory, faster
/// traversal); every answer is made exact in `f64` ([`Target::nearest_two`]): the `f32` search
/// names the candidates, their distances are computed exactly, and where rounding could have
/// swapped two neighbours the ball that must hold the true nearest is searched and settled in
/// `f64`.
pub struct Target {
    points: Vec<Point3<f64>>,
    normals: Vec<Vector3<f64>>,
    tree: ImmutableKdTree<f32, 3>,
    origin: Vector3<f64>,
    /// Largest distance of a point from `origin`, mm.
    radius: f64,
}

fn check_points(which: &'static str, pts: &[Point3<f64>], min: usize) -> Result<(), IcpError> {
    if pts.len() < min {
        return Err(IcpError::TooFewPoints { which, n: pts.len(), min });
    }
    if let Some(index) = pts.iter().position(|p| !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite())) {
        return Err(IcpError::NotFinite { which, index });
    }
    Ok(())
}

impl Target {
    /// A target with normals estimated by PCA over each point's `normal_k` nearest points.
    pub fn new(points: Vec<Point3<f64>>, normal_k: usize) -> Result<Self, IcpError> {
        check_points("target", &points, 6)?;
        if !(3..=200).contains(&normal_k) {
            return Err(IcpError::Invalid {
                field: "normal_k",
                value: normal_k.to_string(),
                reason: "3 to 200",
            });
        }
        let (tree, origin, radius) = build_tree(&points)?;
        let k = std::num::NonZero::new(normal_k.min(points.len())).unwrap_or(std::num::NonZero::<usize>::MIN);
        let normals = points
            .par_iter()
            .map(|p| {
                let near = tree.query(&centred(p, &origin)).nearest_n::<SquaredEuclidean<f32>>(k).execute();
                let n = near.len() as f64;
                let c = near.iter().fold(Vector3::zeros(), |a, r| a + points[r.item as usize].coords) / n;
                let cov = near.iter().fold(Matrix3::zeros(), |a, r| {
                    let d = points[r.item as usize].coords - c;
                    a + d * d.transpose()
                });
                smallest_eigenvector(&cov)
            })
            .collect();
        Ok(Self { points, normals, tree, origin, radius })
    }

    /// A target with given unit normals (one per point).
    pub fn with_normals(points: Vec<Point3<f64>>, normals: Vec<Vector3<f64>>) -> Result<Self, IcpError> {
        check_points("target", &points, 6)?;
        if normals.len() != points.len() {
            return Err(IcpError::Invalid {
                field: "normals",
                value: normals.len().to_string(),
                reason: "one normal per target point",
            });
        }
        let (tree, origin, radius) = build_tree(&points)?;
        Ok(Self { points, normals, tree, origin, radius })
    }

    /// The points.
    pub fn points(&self) -> &[Point3<f64>] {
        &self.points
    }

    /// The unit normals.
    pub fn normals(&self) -> &[Vector3<f64>] {
        &self.normals
    }

    /// Nearest target point to `p` within `max` (mm): its index and squared distance (exact).
    pub fn nearest_within(&self, p: &Point3<f64>, max: f64) -> Option<(usize, f64)> {
        match self.nearest_two(p, max) {
            (Some(i), d1, _) if d1 <= max => Some((i, d1 * d1)),
            _ => None,
        }
    }

    /// Bound on how far an `f32` distance from `p` to a target point can be from the exact one,
    /// mm: coordinates about the centre rounded to `f32` (relative 2⁻²⁴ each), the differences
    /// and the sum of squares rounded again; with a factor 4 of margin.
    fn rounding(&self, p: &Point3<f64>) -> f64 {
        let u = f64::from(f32::EPSILON);
        let q = (p.coords - self.origin).norm();
        4.0 * u * (2.0 * (q + self.radius) + 1.0) + 1e-9
    }

    /// The exact nearest target point of `p` within `bound` mm (its index and distance) and a
    /// lower bound on the distance of every other target point; `None` and a lower bound on the
    /// nearest distance when no point lies within `bound`.
    ///
    /// The `f32` tree gives the two nearest candidates within `bound` by `f32` distance. With
    /// `e1 <= e2` their exact distances and `ε` the rounding bound, every point not returned is
    /// at least `L = e2 − 2ε` away (two returned) or `bound − ε` (fewer), so the first is the
    /// exact nearest when `L > e1`. Otherwise every point within `e1 + 3ε` in `f32` holds the
    /// exact nearest, and the candidates there are compared in `f64`.
    pub fn nearest_two(&self, p: &Point3<f64>, bound: f64) -> (Option<usize>, f64, f64) {
        let two = std::num::NonZero::new(2).unwrap_or(std::num::NonZero::<usize>::MIN);
        let c = centred(p, &self.origin);
        let eps = self.rounding(p);
        let b2 = if bound.is_finite() { (bound * bound) as f32 } else { f32::INFINITY };
        let near = self.tree.query(&c).nearest_n::<SquaredEuclidean<f32>>(two).within(b2).execute();
        let exact = |i: u32| (p - self.points[i as usize]).norm();
        let (mut e1, mut i1, mut e2) = (f64::INFINITY, u32::MAX, f64::INFINITY);
        for r in &near {
            let e = exact(r.item);
            if e < e1 || (e == e1 && r.item < i1) {
                (e2, e1, i1) = (e1, e, r.item);
            } else if e < e2 {
                e2 = e;
            }
        }
        // `b2` rounded to f32 may sit below bound² by a relative 2⁻²⁴.
        let outside = bound * (1.0 - 2.0 * f64::from(f32::EPSILON)) - eps;
        let others = if near.len() >= 2 { e2 - 2.0 * eps } else { outside };
        if i1 == u32::MAX {
            return (None, outside.max(0.0), outside.max(0.0));
        }
        if others > e1 {
            return (Some(i1 as usize), e1, others.min(e2));
        }
        let r = e1 + 3.0 * eps;
        let ball = self
            .tree
            .query(&c)
            .within::<SquaredEuclidean<f32>>((r * r) as f32 * (1.0 + 4.0 * f32::EPSILON))
            .execute();
        let mut all: Vec<(f64, u32)> = ball.iter().map(|r| (exact(r.item), r.item)).collect();
        all.push((e1, i1));
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.dedup_by_key(|c| c.1);
        let (d1, i) = all[0];
        // Points outside the ball are at least `r − ε = e1 + 2ε` away.
        let floor = e1 + 2.0 * eps;
        let d2 = all.get(1).map_or(floor, |c| c.0.min(floor));
        (Some(i as usize), d1, d2)
    }
}

/// `p` about `origin`, in `f32`.
fn centred(p: &Point3<f64>, origin: &Vector3<f64>) -> [f32; 3] {
    let q = p.coords - origin;
    [q.x as f32, q.y as f32, q.z as f32]
}

/// The `f32` tree about the points' centre, the centre and the largest distance from it.
fn build_tree(points: &[Point3<f64>]) -> Result<(ImmutableKdTree<f32, 3>, Vector3<f64>, f64), IcpError> {
    let origin = points.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / points.len().max(1) as f64;
    let radius = points.iter().map(|p| (p.coords - origin).norm()).fold(0.0, f64::max);
    let coords: Vec<[f32; 3]> = points.iter().map(|p| centred(p, &origin)).collect();
    let tree = ImmutableKdTree::new_from_slice(&coords)
        .map_err(|e| IcpError::Degenerate(format!("building the k-d tree: {e:?}")))?;
    Ok((tree, origin, radius))
}

fn smallest_eigenvector(cov: &Matrix3<f64>) -> Vector3<f64> {
    let eig = SymmetricEigen::new(*cov);
    let (k, _) = eig.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1)).unwrap_or((2, &0.0));
    let n: Vector3<f64> = eig.eigenvectors.column(k).into_owned();
    if n.norm() > 0.0 { n.normalize() } else { Vector3::z() }
}

/// Sums of one correspondence pass.
#[derive(Clone, Copy)]
struct Sums {
    a: Matrix6<f64>,
    b: Vector6<f64>,
    n: usize,
    dist_sq: f64,
    plane_sq: f64,
}

impl Sums {
    fn zero() -> Self {
        Self { a: Matrix6::zeros(), b: Vector6::zeros(), n: 0, dist_sq: 0.0, plane_sq: 0.0 }
    }

    fn add(mut self, o: Sums) -> Sums {
        self.a += o.a;
        self.b += o.b;
        self.n += o.n;
        self.dist_sq += o.dist_sq;
        self.plane_sq += o.plane_sq;
        self
    }
}

/// One correspondence of `p` (already transformed): its contribution.
fn contribution(p: &Point3<f64>, q: &Point3<f64>, n: &Vector3<f64>, d2: f64, kernel: &Kernel) -> Sums {
    let r = (p - q).dot(n);
    let w = kernel.weight(r);
    let c = p.coords.cross(n);
    let j = Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z);
    Sums { a: j * j.transpose() * w, b: j * (w * r), n: 1, dist_sq: d2, plane_sq: r * r }
}

/// The step from the normal equations: `exp(ω)`, `t`.
pub(crate) fn step(a: &Matrix6<f64>, b: &Vector6<f64>) -> Result<Isometry3<f64>, IcpError> {
    let x = a.cholesky().map(|c| c.solve(&(-b))).ok_or_else(|| {
        IcpError::Degenerate(
            "the correspondences do not pin the transform down (a plane or a line slides along itself); give a better start or more overlap".into(),
        )
    })?;
    Ok(Isometry3::from_parts(
        Translation3::new(x[3], x[4], x[5]),
        UnitQuaternion::from_scaled_axis(Vector3::new(x[0], x[1], x[2])),
    ))
}

/// A source point's last nearest-neighbour search: where the point was, its nearest target
/// point, and half the gap between the nearest and the second nearest distance. While the point
/// stays within that half gap of where it was searched, its nearest neighbour cannot have
/// changed (triangle inequality), so the search is skipped: exact, and most points move far less
/// than that once the transform settles.
#[derive(Clone, Copy)]
struct Nearest {
    at: Point3<f64>,
    index: u32,
    half_gap: f64,
}

/// No target point near enough.
const NONE: u32 = u32::MAX;

const UNSEARCHED: Nearest =
    Nearest { at: Point3::new(f64::NAN, f64::NAN, f64::NAN), index: 0, half_gap: -1.0 };

impl Target {
    /// Nearest target point of `p` (its index) when one may lie within `max` of it, reusing
    /// `cache` when `p` has not moved out of its half gap. The search looks `2 max` around `p`;
    /// a point with nothing there cannot gain a correspondence before it has moved by the
    /// distance to the nearest target point less `max`, and is not searched again before.
    fn nearest_cached(&self, p: &Point3<f64>, cache: &mut Nearest, max: f64) -> Option<usize> {
        if (p - cache.at).norm() < cache.half_gap {
            return (cache.index != NONE).then_some(cache.index as usize);
        }
        *cache = match self.nearest_two(p, 2.0 * max) {
            (Some(i), d1, d2) => Nearest { at: *p, index: i as u32, half_gap: 0.5 * (d2 - d1) },
            (None, at_least, _) => Nearest { at: *p, index: NONE, half_gap: at_least - max },
        };
        (cache.index != NONE).then_some(cache.index as usize)
    }
}

fn pass(
    source: &[Point3<f64>],
    target: &Target,
    t: &Isometry3<f64>,
    opts: &IcpOptions,
    it: u32,
    cache: &mut [Nearest],
) -> Sums {
    let kernel = opts.kernel.annealed(it, opts.max_correspondence_mm);
    let max2 = opts.max_correspondence_mm * opts.max_correspondence_mm;
    source
        .par_iter()
        .zip(cache.par_iter_mut())
        .fold(Sums::zero, |s, (p, c)| {
            let p = t * p;
            let Some(i) = target.nearest_cached(&p, c, opts.max_correspondence_mm) else { return s };
            let q = &target.points[i];
            let d2 = (p - q).norm_squared();
            if d2 <= max2 { s.add(contribution(&p, q, &target.normals[i], d2, &kernel)) } else { s }
        })
        .reduce(Sums::zero, Sums::add)
}

fn result_of(s: &Sums, source_len: usize, transform: Isometry3<f64>, iterations: u32) -> IcpResult {
    let n = s.n.max(1) as f64;
    IcpResult {
        transform,
        fitness: s.n as f64 / source_len.max(1) as f64,
        inlier_rmse_mm: if s.n > 0 { (s.dist_sq / n).sqrt() } else { 0.0 },
        plane_rmse_mm: if s.n > 0 { (s.plane_sq / n).sqrt() } else { 0.0 },
        correspondences: s.n,
        iterations,
    }
}

/// Source points the coarse level works on at most (every `stride`-th point).
const COARSE_POINTS: usize = 8000;
/// The coarse level ends when its step falls under this, mm (same measure as [`MIN_STEP_MM`]).
const COARSE_STEP_MM: f64 = 0.01;

/// The stride of the coarse level for a source of `n` points (1: no coarse level).
pub(crate) fn coarse_stride(n: usize) -> usize {
    (n / COARSE_POINTS).max(1)
}

/// Iterations on one level from `t`, numbered from `first_it` (the kernel's graduation goes on
/// across levels): the transform, the last result and the next iteration number.
fn iterate(
    source: &[Point3<f64>],
    target: &Target,
    mut t: Isometry3<f64>,
    opts: &IcpOptions,
    first_it: u32,
    stop_step_mm: f64,
) -> Result<(Isometry3<f64>, IcpResult, u32), IcpError> {
    let mut cache = vec![UNSEARCHED; source.len()];
    let mut s = pass(source, target, &t, opts, first_it, &mut cache);
    let mut last = result_of(&s, source.len(), t, first_it);
    let mut it = first_it;
    for _ in 0..opts.max_iterations {
        if s.n < 6 {
            return Err(IcpError::Degenerate(format!(
                "only {} source points have a target point within {} mm: the clouds do not overlap from this start",
                s.n, opts.max_correspondence_mm
            )));
        }
        it += 1;
        let d = step(&s.a, &s.b)?;
        t = d * t;
        s = pass(source, target, &t, opts, it, &mut cache);
        let now = result_of(&s, source.len(), t, it);
        let df = (now.fitness - last.fitness).abs() / last.fitness.max(1e-300);
        let dr = (now.inlier_rmse_mm - last.inlier_rmse_mm).abs() / last.inlier_rmse_mm.max(1e-300);
        last = now;
        // Near the optimum nearest neighbours switch back and forth and the RMSE jitters by a few
        // parts per million: a settled transform ends it too.
        let moved = d.translation.vector.norm() + d.rotation.angle() * opts.max_correspondence_mm * 100.0;
        if (df < opts.relative_fitness && dr < opts.relative_rmse) || moved < stop_step_mm {
            break;
        }
    }
    Ok((t, last, it))
}

/// Registers `source` onto `target` from `init` (`target_from_source`); see the module doc.
/// A large source is first registered by every `stride`-th point (at most [`COARSE_POINTS`])
/// until the step is under [`COARSE_STEP_MM`], then by all of them: the far-moving first
/// iterations, whose every point needs a new search, cost a fraction. `max_iterations` applies
/// to each level.
pub fn icp(
    source: &[Point3<f64>],
    target: &Target,
    init: &Isometry3<f64>,
    opts: &IcpOptions,
) -> Result<IcpResult, IcpError> {
    opts.validate()?;
    check_points("source", source, 6)?;
    let stride = coarse_stride(source.len());
    let (mut t, mut it) = (*init, 0);
    if stride > 1 {
        let coarse: Vec<Point3<f64>> = source.iter().step_by(stride).copied().collect();
        let (tc, _, next) = iterate(&coarse, target, t, opts, 0, COARSE_STEP_MM)?;
        t = tc;
        it = next;
    }
    let (_, last, _) = iterate(source, target, t, opts, it, MIN_STEP_MM)?;
    Ok(last)
}

/// [`icp`] after a coarse search for the start: turns of the source about the vertical axis
/// through its centre (every `360 / turns` degrees, centres matched), each refined for a few
/// iterations with a wide correspondence distance; the best fitting start goes on to the full
/// ICP. For views whose chain is off by degrees about the table's axis.
pub fn icp_with_coarse_start(
    source: &[Point3<f64>],
    target: &Target,
    init: &Isometry3<f64>,
    opts: &IcpOptions,
    turns: u32,
) -> Result<IcpResult, IcpError> {
    opts.validate()?;
    check_points("source", source, 6)?;
    if !(1..=360).contains(&turns) {
        return Err(IcpError::Invalid { field: "turns", value: turns.to_string(), reason: "1 to 360" });
    }
    let centre =
        |pts: &[Point3<f64>]| pts.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / pts.len() as f64;
    let moved: Vec<Point3<f64>> = source.iter().map(|p| init * p).collect();
    let cs = centre(&moved);
    let ct = centre(target.points());
    let wide = IcpOptions {
        max_correspondence_mm: opts.max_correspondence_mm * 10.0,
        max_iterations: 5,
        kernel: Kernel::Huber(opts.max_correspondence_mm),
        ..*opts
    };
    let mut best: Option<(f64, Isometry3<f64>)> = None;
    let turned = (0..turns).map(|k| {
        let a = std::f64::consts::TAU * f64::from(k) / f64::from(turns);
        let turn = Isometry3::from_parts(
            Translation3::from(ct),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), a),
        ) * Isometry3::from_parts(Translation3::from(-cs), UnitQuaternion::identity());
        turn * init
    });
    // The given start is a candidate too (its centres need not match on a partial overlap).
    for start in std::iter::once(*init).chain(turned) {
        if let Ok(r) = icp(source, target, &start, &wide) {
            let score = r.fitness / (1.0 + r.inlier_rmse_mm);
            if best.is_none_or(|(b, _)| score > b) {
                best = Some((score, r.transform));
            }
        }
    }
    let Some((_, start)) = best else {
        return Err(IcpError::Degenerate("no turn of the source overlaps the target".into()));
    };
    icp(source, target, &start, opts)
}

#[cfg(test)]
mod tests;

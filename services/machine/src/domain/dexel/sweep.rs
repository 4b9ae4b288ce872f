//! The tool as convex pieces and the exact interval a ray spends inside one piece swept along a
//! straight move at a fixed orientation.
//!
//! # The tool
//!
//! A [`ToolSolid`] lives in its own frame: tip at the origin, axis `+w`. It is a union of convex
//! [`Piece`]s: frusta (cylinder and cone pieces, one per rising segment of the profile's polyline,
//! plus the cylinder of radius `R` from the profile's top up to the tool's length, which stands
//! for the shank and holder as the Z-map's column does) and, for a ball mill, the exact sphere of
//! its end. A bull nose's torus is its 64-segment polyline, inscribed in the arc: within
//! `1.3e-4 · c` of it along the normal and within `c·π/512` (`c` the corner radius) along the
//! axis, where the last chord meets the vertical end of the arc; never outside the true tool.
//!
//! # The swept piece and a ray
//!
//! The tip moves `P(s) = P0 + s·V`, `s ∈ [0, 1]`, the axis `u` fixed; a ray is `X(t) = O + t·D`.
//! The point `X(t)` lies in the piece at `P(s)` when `Y = X(t) − P(s)` does, and every coordinate
//! of `Y` in the tool frame is affine in `(t, s)`: the axial `w(t, s)`, the radial vector
//! `M(t, s)` (2-D for a frustum, 3-D offset from the centre for a sphere). A frustum is
//! `h0 <= w <= h1`, `|M| <= L(t, s) = r0 + k·(w − h0)`; a sphere `|M| <= r`. Each is a convex set
//! in `(t, s)` bounded by lines (`s = 0`, `s = 1`, `w = h0`, `w = h1`, `L = 0`) and the conic
//! `F = |M|² − L² = 0`, so its extent in `t` (the interval the ray spends in the swept piece:
//! the swept volume of a convex solid along a segment is convex, so it is one interval) is
//! reached at one of:
//!
//! - a vertex of two lines,
//! - a point of the conic on one of the lines,
//! - a point of the conic where its tangent is parallel to the `s` axis (`∂F/∂s = 0`),
//! - the conic's singular point (`∇F = 0`, the apex of a cone seen edge-on).
//!
//! [`extent`] solves for each candidate in closed form (quadratics and 2 x 2 systems), keeps the
//! feasible ones (within [`FEAS_TOL_MM`]) and returns the smallest and largest `t`. Exact up to
//! floating-point rounding, with no sampling along the move.

use nalgebra::{Point3, Unit, Vector3};
use smallvec::SmallVec;

use depthmill_geometry::{ToolProfile, ToolSpec};

use super::DexelError;

/// Feasibility tolerance of a candidate point, mm.
pub const FEAS_TOL_MM: f64 = 1.0e-7;

/// One convex piece of a tool, in the tool frame (tip at the origin, axis `+w`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Piece {
    /// `h0 <= w <= h1` and radial distance `<= r0 + (r1 − r0)·(w − h0)/(h1 − h0)`; `h1 > h0`.
    Frustum { h0: f64, h1: f64, r0: f64, r1: f64 },
    /// The ball of radius `r` centred on the axis at `w = c`.
    Sphere { c: f64, r: f64 },
}

impl Piece {
    /// Whether the tool-frame point (radial distance `rho`, axial `w`) lies in the piece, with a
    /// tolerance `tol` (mm).
    pub fn contains(&self, rho: f64, w: f64, tol: f64) -> bool {
        match *self {
            Piece::Frustum { h0, h1, r0, r1 } => {
                w >= h0 - tol && w <= h1 + tol && {
                    let k = (r1 - r0) / (h1 - h0);
                    rho <= r0 + k * (w.clamp(h0, h1) - h0) + tol
                }
            }
            Piece::Sphere { c, r } => (rho * rho + (w - c) * (w - c)).sqrt() <= r + tol,
        }
    }

    /// The piece's axial range and largest radius.
    pub fn bounds(&self) -> (f64, f64, f64) {
        match *self {
            Piece::Frustum { h0, h1, r0, r1 } => (h0, h1, r0.max(r1)),
            Piece::Sphere { c, r } => (c - r, c + r, r),
        }
    }
}

/// A tool of revolution as convex pieces (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct ToolSolid {
    pieces: Vec<Piece>,
    radius: f64,
    length: f64,
    /// `lower` at `d² = k·R²/LOWER_STEPS`, `k = 0..=LOWER_STEPS`: a lower bound of the lower
    /// surface at any `d²` from the entry below it (the surface rises with the distance).
    lower_by_d2: Vec<f64>,
    /// `LOWER_STEPS / R²`.
    steps_per_d2: f64,
    /// A ball mill's radius: its lower surface is its sphere's, in closed form.
    ball: Option<f64>,
}

/// Entries of [`ToolSolid::lower_bound_d2`]'s table.
const LOWER_STEPS: usize = 1024;

impl ToolSolid {
    /// The solid of `profile` up to `length_mm` above the tip (the gauge length: flutes, shank
    /// and holder, all taken as the tool's radius above the profile).
    ///
    /// Errors: a length not finite or not above the profile's top.
    pub fn new(profile: &ToolProfile, length_mm: f64) -> Result<Self, DexelError> {
        let top = profile.max_height_mm();
        if !(length_mm.is_finite() && length_mm > top) {
            return Err(DexelError::Invalid {
                field: "tool length_mm".into(),
                value: length_mm,
                expected: "a finite length above the profile's top",
            });
        }
        let radius = profile.radius_mm();
        let mut pieces = Vec::new();
        let ball = matches!(profile.spec(), Some(ToolSpec::Ball { .. })).then_some(radius);
        if ball.is_some() {
            pieces.push(Piece::Sphere { c: radius, r: radius });
            pieces.push(Piece::Frustum { h0: radius, h1: length_mm, r0: radius, r1: radius });
        } else {
            let (rs, hs) = (profile.radii_mm(), profile.heights_mm());
            for k in 1..rs.len().min(hs.len()) {
                if hs[k] > hs[k - 1] {
                    pieces.push(Piece::Frustum { h0: hs[k - 1], h1: hs[k], r0: rs[k - 1], r1: rs[k] });
                }
            }
            pieces.push(Piece::Frustum { h0: top, h1: length_mm, r0: radius, r1: radius });
        }
        let r2 = radius * radius;
        let mut solid = ToolSolid {
            pieces,
            radius,
            length: length_mm,
            lower_by_d2: Vec::new(),
            steps_per_d2: LOWER_STEPS as f64 / r2,
            ball,
        };
        solid.lower_by_d2 = (0..=LOWER_STEPS)
            .map(|k| solid.lower((k as f64 * r2 / LOWER_STEPS as f64).sqrt()).unwrap_or(f64::INFINITY))
            .collect();
        Ok(solid)
    }

    /// The pieces, tip first.
    pub fn pieces(&self) -> &[Piece] {
        &self.pieces
    }

    /// The tool's radius, mm.
    pub fn radius_mm(&self) -> f64 {
        self.radius
    }

    /// The tool's length above the tip, mm.
    pub fn length_mm(&self) -> f64 {
        self.length
    }

    /// The lowest axial height of the tool at radial distance `rho` (its lower surface
    /// `h(rho)`), or `None` beyond its radius.
    pub fn lower(&self, rho: f64) -> Option<f64> {
        self.pieces
            .iter()
            .filter_map(|p| match *p {
                Piece::Sphere { c, r } => (rho <= r).then(|| c - (r * r - rho * rho).max(0.0).sqrt()),
                Piece::Frustum { h0, h1, r0, r1 } => {
                    if rho <= r0 {
                        Some(h0)
                    } else if rho <= r1 && r1 > r0 {
                        Some(h0 + (rho - r0) * (h1 - h0) / (r1 - r0))
                    } else {
                        None
                    }
                }
            })
            .reduce(f64::min)
    }

    /// A lower bound of [`lower`](Self::lower) at the squared distance `d2` (`≤ R²`): for a ball
    /// mill its sphere's cap (one square root, within rounding of `lower`, so that a ray the
    /// move before left on the same surface is seen as untouched), otherwise from a table (no
    /// square root, no walk over the pieces).
    #[inline]
    pub fn lower_bound_d2(&self, d2: f64) -> f64 {
        if let Some(r) = self.ball {
            return r - (r * r - d2).max(0.0).sqrt();
        }
        // Truncation is the floor here (the argument is not negative; NaN and negatives give 0),
        // and needs no call to libm's floor on the baseline x86-64 target.
        let k = ((d2 * self.steps_per_d2).max(0.0) as usize).min(LOWER_STEPS);
        self.lower_by_d2.get(k).copied().unwrap_or(f64::INFINITY)
    }

    /// Whether `other` is the same solid (pieces and length).
    pub fn same_shape(&self, other: &ToolSolid) -> bool {
        self.length == other.length && self.pieces == other.pieces
    }

    /// Each piece's axial interval `[w_lo, w_hi]` at radial distance `rho` (pieces that reach
    /// `rho`), in piece order. A piece's interval only shrinks as `rho` grows (every piece is
    /// convex and of revolution), so a level move's sweep seen along a ray parallel to the axis is
    /// these intervals at the ray's nearest distance from the tip's path.
    pub fn intervals_at(&self, rho: f64) -> SmallVec<[(f64, f64); 4]> {
        self.pieces
            .iter()
            .filter_map(|p| match *p {
                Piece::Sphere { c, r } => (rho <= r).then(|| {
                    let half = (r * r - rho * rho).max(0.0).sqrt();
                    (c - half, c + half)
                }),
                Piece::Frustum { h0, h1, r0, r1 } => {
                    if rho > r0.max(r1) {
                        None
                    } else if r1 >= r0 {
                        // Rising: from where the radius reaches rho up to the top.
                        let w = if rho <= r0 { h0 } else { h0 + (rho - r0) * (h1 - h0) / (r1 - r0) };
                        Some((w, h1))
                    } else {
                        // Falling: from the bottom up to where the radius drops below rho.
                        let w = if rho <= r1 { h1 } else { h0 + (r0 - rho) * (h1 - h0) / (r0 - r1) };
                        Some((h0, w))
                    }
                }
            })
            .collect()
    }

    /// The radius of the tool's cross-section at axial height `w` (the largest of its pieces'
    /// there), or `None` where no piece reaches. Every piece is of revolution about the axis, so
    /// the section is a disc: a move across the axis sweeps it into a capsule in its plane.
    pub fn radius_at(&self, w: f64) -> Option<f64> {
        self.pieces
            .iter()
            .filter_map(|p| match *p {
                Piece::Sphere { c, r } => {
                    ((w - c).abs() <= r).then(|| (r * r - (w - c) * (w - c)).max(0.0).sqrt())
                }
                Piece::Frustum { h0, h1, r0, r1 } => {
                    (w >= h0 && w <= h1).then(|| r0 + (r1 - r0) * (w - h0) / (h1 - h0))
                }
            })
            .reduce(f64::max)
    }

    /// Whether a tool-frame point (radial `rho`, axial `w`) is in the tool, within `tol`.
    pub fn contains(&self, rho: f64, w: f64, tol: f64) -> bool {
        self.pieces.iter().any(|p| p.contains(rho, w, tol))
    }
}

/// An orthonormal frame around a tool axis: `e1`, `e2` across, `u` along.
#[derive(Debug, Clone, Copy)]
pub struct AxisFrame {
    pub e1: Vector3<f64>,
    pub e2: Vector3<f64>,
    pub u: Vector3<f64>,
}

impl AxisFrame {
    pub fn new(axis: &Unit<Vector3<f64>>) -> Self {
        let u = axis.into_inner();
        let a = if u.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let e1 = (a - u * a.dot(&u)).normalize();
        let e2 = u.cross(&e1);
        AxisFrame { e1, e2, u }
    }
}

/// An affine function `c + t·T + s·S` of the ray parameter `t` and the move parameter `s`.
#[derive(Debug, Clone, Copy, Default)]
struct Aff {
    c: f64,
    t: f64,
    s: f64,
}

impl Aff {
    fn at(&self, t: f64, s: f64) -> f64 {
        self.c + self.t * t + self.s * s
    }

    fn scaled(self, k: f64) -> Aff {
        Aff { c: self.c * k, t: self.t * k, s: self.s * k }
    }

    fn shifted(self, k: f64) -> Aff {
        Aff { c: self.c + k, ..self }
    }

    /// Whether it does not depend on `(t, s)` (to rounding, against its own scale).
    fn is_constant(&self) -> bool {
        self.t.abs() + self.s.abs() <= 1e-12 * (1.0 + self.c.abs())
    }
}

/// The ray and the move in the tool's frame, set up once per (ray, move).
#[derive(Debug, Clone, Copy)]
pub struct RayMove {
    /// Axial coordinate `w(t, s)`.
    w: Aff,
    /// Radial coordinates across the axis.
    m1: Aff,
    m2: Aff,
    /// `s` constraints scaled to millimetres (`|V|·s >= 0`, `|V|·(1 − s) >= 0`).
    s_scale: f64,
}

impl RayMove {
    /// Ray `O + t·D`, tip moving `P0 → P0 + V`, axis frame `f`.
    pub fn new(o: &Point3<f64>, d: &Vector3<f64>, p0: &Point3<f64>, v: &Vector3<f64>, f: &AxisFrame) -> Self {
        let q = o - p0;
        let aff = |e: &Vector3<f64>| Aff { c: e.dot(&q), t: e.dot(d), s: -e.dot(v) };
        RayMove { w: aff(&f.u), m1: aff(&f.e1), m2: aff(&f.e2), s_scale: v.norm().max(1.0) }
    }

    /// The `t` interval the ray spends in `piece` swept along the move, or `None`.
    pub fn extent(&self, piece: &Piece) -> Option<(f64, f64)> {
        match *piece {
            Piece::Frustum { h0, h1, r0, r1 } => {
                let k = (r1 - r0) / (h1 - h0);
                let l = self.w.shifted(-h0).scaled(k).shifted(r0);
                let lins = [
                    Aff { c: 0.0, t: 0.0, s: self.s_scale },
                    Aff { c: self.s_scale, t: 0.0, s: -self.s_scale },
                    self.w.shifted(-h0),
                    self.w.scaled(-1.0).shifted(h1),
                    l,
                ];
                // A cylinder's radius is a constant: `l >= 0` always holds and only adds
                // degenerate candidates.
                let n = if k == 0.0 { 4 } else { 5 };
                extent(&[self.m1, self.m2], l, &lins[..n])
            }
            Piece::Sphere { c, r } => {
                let lins = [
                    Aff { c: 0.0, t: 0.0, s: self.s_scale },
                    Aff { c: self.s_scale, t: 0.0, s: -self.s_scale },
                ];
                extent(&[self.m1, self.m2, self.w.shifted(-c)], Aff { c: r, t: 0.0, s: 0.0 }, &lins)
            }
        }
    }
}

/// The `t` interval the ray `o + t·d` (`d` a unit vector) spends within `r` of the segment
/// `c0 → c0 + v`: a ball piece swept along a straight move (a capsule), in closed form. The capsule
/// is convex, so the interval is the hull of the ray's chords through the two end balls and
/// through the cylinder between them (clipped to the segment's span). Equal to
/// [`RayMove::extent`] of the sphere piece (tested), at a fraction of its cost.
pub fn capsule_extent(
    o: &Point3<f64>,
    d: &Vector3<f64>,
    c0: &Point3<f64>,
    v: &Vector3<f64>,
    r: f64,
) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let w = o - c0;
    let r2 = r * r;
    // The end balls: |w + t·d − e|² ≤ r², |d| = 1.
    for e in [Vector3::zeros(), *v] {
        let q = w - e;
        let b = q.dot(d);
        let disc = b * b - (q.norm_squared() - r2);
        if disc >= 0.0 {
            let root = disc.sqrt();
            lo = lo.min(-b - root);
            hi = hi.max(-b + root);
        }
    }
    let vv = v.norm_squared();
    if vv > 0.0 {
        // The cylinder: the part of the ray whose projection on the segment falls inside it
        // (s ∈ [0, 1]) and whose distance across it is at most r.
        let (wv, dv) = (w.dot(v) / vv, d.dot(v) / vv);
        let wp = w - v * wv;
        let dp = d - v * dv;
        let (a, b, c) = (dp.norm_squared(), wp.dot(&dp), wp.norm_squared() - r2);
        let (mut t0, mut t1) = if a > 1e-18 {
            let disc = b * b - a * c;
            if disc < 0.0 {
                (f64::INFINITY, f64::NEG_INFINITY)
            } else {
                let root = disc.sqrt();
                ((-b - root) / a, (-b + root) / a)
            }
        } else if c <= 0.0 {
            (f64::NEG_INFINITY, f64::INFINITY)
        } else {
            (f64::INFINITY, f64::NEG_INFINITY)
        };
        // s(t) = wv + t·dv within [0, 1].
        if dv.abs() > 1e-18 {
            let (sa, sb) = ((0.0 - wv) / dv, (1.0 - wv) / dv);
            t0 = t0.max(sa.min(sb));
            t1 = t1.min(sa.max(sb));
        } else if !(0.0..=1.0).contains(&wv) {
            t1 = f64::NEG_INFINITY;
        }
        if t0 <= t1 && t0.is_finite() && t1.is_finite() {
            lo = lo.min(t0);
            hi = hi.max(t1);
        }
    }
    (lo <= hi).then_some((lo, hi))
}

/// The `t` interval the ray `o + t·d` spends in the cylinder of radius `r` between axial heights
/// `h0..h1` above the tip, the tip moving `from → from + v` with the axis `u` fixed, for a ray
/// across the axis (`d ⊥ u`). The ray stays at one height `w` above the tip's start; at move
/// fraction `s` the cylinder's section there is the disc of radius `r` about
/// `from + u·w + s·v⊥` (`v⊥` the move across the axis), present while `h0 <= w − s·(v·u) <= h1`.
/// Those discs make the capsule about the segment of centres over the `s` range where the
/// section exists, so the interval is that capsule's chord: one closed form, equal to
/// [`RayMove::extent`] of the piece (tested).
pub fn cylinder_across_extent(
    o: &Point3<f64>,
    d: &Vector3<f64>,
    from: &Point3<f64>,
    v: &Vector3<f64>,
    u: &Vector3<f64>,
    (h0, h1): (f64, f64),
    r: f64,
) -> Option<(f64, f64)> {
    let w = (o - from).dot(u);
    let vu = v.dot(u);
    let v_perp = v - u * vu;
    let (s0, s1) = if vu.abs() < 1e-15 {
        if w < h0 || w > h1 {
            return None;
        }
        (0.0, 1.0)
    } else {
        let (a, b) = ((w - h1) / vu, (w - h0) / vu);
        (a.min(b).max(0.0), a.max(b).min(1.0))
    };
    if s0 > s1 {
        return None;
    }
    capsule_extent(o, d, &(from + u * w + v_perp * s0), &(v_perp * (s1 - s0)), r)
}

/// A level move across the tool's axis seen along grid rays across it too (the X and Y grids of
/// a 3-axis cut; the grids across the A axis's plane on a face turned about X): each ray lies in
/// one plane across the axis, where the tool is a disc of radius
/// [`ToolSolid::radius_at`] its height, swept into a 2-D capsule. The plane's coordinates are
/// along the ray and along `n = u × d`; per ray only the height, the offset along `n` and one
/// capsule chord remain (equal to [`capsule_extent`] of the disc, tested).
#[derive(Debug, Clone, Copy)]
pub struct AcrossMove {
    u: Vector3<f64>,
    n: Vector3<f64>,
    /// The move along the rays and along `n`.
    v: (f64, f64),
    /// Its unit direction (0 for no move) and length.
    unit: (f64, f64),
    len: f64,
    /// The rays' axis.
    k: usize,
}

impl AcrossMove {
    /// Rays along grid axis `k` (unit `d`), the tool's axis `u` across them, the move `v`
    /// across `u`.
    pub fn new(u: &Vector3<f64>, d: &Vector3<f64>, k: usize, v: &Vector3<f64>) -> Self {
        let n = u.cross(d);
        let (vd, vn) = (v.dot(d), v.dot(&n));
        let len = vd.hypot(vn);
        let unit = if len > 0.0 { (vd / len, vn / len) } else { (0.0, 0.0) };
        AcrossMove { u: *u, n, v: (vd, vn), unit, len, k }
    }

    /// The interval along the ray through `o` (its coordinate along the rays 0) that the tool
    /// with its tip moving from `from` sweeps, or `None`.
    #[inline]
    pub fn extent(&self, tool: &ToolSolid, o: &Point3<f64>, from: &Point3<f64>) -> Option<(f64, f64)> {
        let r = o - from;
        let rho = tool.radius_at(r.dot(&self.u))?;
        // The ray is the line at `r·n` across, its points at `t − from[k]` along: the chord of
        // the capsule from the origin along `v`.
        let (lo, hi) = super::super::removal::capsule_x(
            (0.0, 0.0),
            self.v,
            self.unit,
            self.len,
            r.dot(&self.n),
            rho,
            rho * rho,
        )?;
        Some((lo + from[self.k], hi + from[self.k]))
    }
}

/// Candidate points `(t, s)` (at most 23 for five lines: kept on the stack).
type Candidates = smallvec::SmallVec<[(f64, f64); 32]>;

/// The quadratic `F(t, s) = |M|² − L²` as `att·t² + 2·ats·t·s + ass·s² + 2·bt·t + 2·bs·s + cc`.
#[derive(Debug, Clone, Copy)]
struct Conic {
    att: f64,
    ats: f64,
    ass: f64,
    bt: f64,
    bs: f64,
    cc: f64,
}

impl Conic {
    fn new(m: &[Aff], l: Aff) -> Conic {
        let mut q = Conic {
            att: -l.t * l.t,
            ats: -l.t * l.s,
            ass: -l.s * l.s,
            bt: -l.c * l.t,
            bs: -l.c * l.s,
            cc: -l.c * l.c,
        };
        for a in m {
            q.att += a.t * a.t;
            q.ats += a.t * a.s;
            q.ass += a.s * a.s;
            q.bt += a.c * a.t;
            q.bs += a.c * a.s;
            q.cc += a.c * a.c;
        }
        q
    }

    /// Points of `F = 0` on the line `lin = 0`.
    fn on_line(&self, lin: &Aff, out: &mut Candidates) {
        if lin.is_constant() {
            return;
        }
        if lin.s.abs() >= lin.t.abs() {
            // s = p + q·t
            let (p, q) = (-lin.c / lin.s, -lin.t / lin.s);
            let a = self.att + 2.0 * self.ats * q + self.ass * q * q;
            let b = 2.0 * (self.ats * p + self.ass * p * q + self.bt + self.bs * q);
            let c = self.ass * p * p + 2.0 * self.bs * p + self.cc;
            for t in roots(a, b, c).into_iter().filter(|x| x.is_finite()) {
                out.push((t, p + q * t));
            }
        } else {
            // t = p + q·s
            let (p, q) = (-lin.c / lin.t, -lin.s / lin.t);
            let a = self.att * q * q + 2.0 * self.ats * q + self.ass;
            let b = 2.0 * (self.att * p * q + self.ats * p + self.bt * q + self.bs);
            let c = self.att * p * p + 2.0 * self.bt * p + self.cc;
            for s in roots(a, b, c).into_iter().filter(|x| x.is_finite()) {
                out.push((p + q * s, s));
            }
        }
    }

    /// `∂F/∂s / 2` and `∂F/∂t / 2` as lines.
    fn ds(&self) -> Aff {
        Aff { c: self.bs, t: self.ats, s: self.ass }
    }

    fn dt(&self) -> Aff {
        Aff { c: self.bt, t: self.att, s: self.ats }
    }
}

/// Real roots of `a·x² + b·x + c` (a linear equation when `a` is negligible).
/// Missing roots are NaN.
fn roots(a: f64, b: f64, c: f64) -> [f64; 2] {
    let scale = a.abs().max(b.abs()).max(c.abs());
    let mut out = [f64::NAN; 2];
    if scale == 0.0 || !scale.is_finite() {
        return out;
    }
    if a.abs() <= 1e-13 * scale {
        if b.abs() > 1e-13 * scale {
            out[0] = -c / b;
        }
    } else {
        let disc = b * b - 4.0 * a * c;
        if disc >= -1e-12 * b * b {
            let sq = disc.max(0.0).sqrt();
            // The stable pair: q = −(b + sign(b)·√disc)/2, roots q/a and c/q.
            let qq = -0.5 * (b + b.signum() * sq);
            out[0] = qq / a;
            out[1] = if qq != 0.0 { c / qq } else { -b / (2.0 * a) };
        }
    }
    out
}

/// The crossing of two lines, or `None` when they are parallel.
fn cross(a: &Aff, b: &Aff) -> Option<(f64, f64)> {
    let det = a.t * b.s - a.s * b.t;
    let scale = (a.t.abs() + a.s.abs()) * (b.t.abs() + b.s.abs());
    if det.abs() <= 1e-12 * scale || scale == 0.0 {
        return None;
    }
    let t = (-a.c * b.s + a.s * b.c) / det;
    let s = (-a.t * b.c + a.c * b.t) / det;
    Some((t, s))
}

/// The `t` extent of `{ |M(t, s)| <= L(t, s), lin_i(t, s) >= 0 }` (see the module docs).
fn extent(m: &[Aff], l: Aff, lins: &[Aff]) -> Option<(f64, f64)> {
    let q = Conic::new(m, l);
    let mut cand = Candidates::new();
    for (i, a) in lins.iter().enumerate() {
        for b in &lins[i + 1..] {
            if let Some(p) = cross(a, b) {
                cand.push(p);
            }
        }
        q.on_line(a, &mut cand);
    }
    let (ds, dt) = (q.ds(), q.dt());
    q.on_line(&ds, &mut cand);
    if let Some(p) = cross(&ds, &dt) {
        cand.push(p);
    }
    let feasible = |&(t, s): &(f64, f64)| {
        if !(t.is_finite() && s.is_finite()) {
            return false;
        }
        if lins.iter().any(|a| a.at(t, s) < -FEAS_TOL_MM) {
            return false;
        }
        let r2: f64 = m.iter().map(|a| a.at(t, s).powi(2)).sum();
        r2.sqrt() <= l.at(t, s) + FEAS_TOL_MM
    };
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for p in cand.iter().filter(|p| feasible(p)) {
        lo = lo.min(p.0);
        hi = hi.max(p.0);
    }
    (lo <= hi).then_some((lo, hi))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    /// Whether `x` lies in the piece swept along the move, by dense sampling of `s` (the
    /// reference), within `tol`.
    fn in_swept(
        piece: &Piece,
        x: &Point3<f64>,
        p0: &Point3<f64>,
        v: &Vector3<f64>,
        f: &AxisFrame,
        tol: f64,
    ) -> bool {
        let n = 1500;
        (0..=n).any(|i| {
            let y = x - (p0 + v * (i as f64 / n as f64));
            let w = y.dot(&f.u);
            let rho = (y - f.u * w).norm();
            piece.contains(rho, w, tol)
        })
    }

    fn random_piece(rng: &mut StdRng) -> Piece {
        match rng.random_range(0..3) {
            0 => Piece::Sphere { c: rng.random_range(0.5..3.0), r: rng.random_range(0.3..3.0) },
            1 => {
                let h0 = rng.random_range(0.0..2.0);
                let r = rng.random_range(0.3..3.0);
                Piece::Frustum { h0, h1: h0 + rng.random_range(0.2..5.0), r0: r, r1: r }
            }
            _ => {
                let h0 = rng.random_range(0.0..2.0);
                Piece::Frustum {
                    h0,
                    h1: h0 + rng.random_range(0.2..4.0),
                    r0: rng.random_range(0.0..2.0),
                    r1: rng.random_range(0.5..3.0),
                }
            }
        }
    }

    fn random_unit(rng: &mut StdRng) -> Vector3<f64> {
        loop {
            let v = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            if v.norm() > 0.2 && v.norm() <= 1.0 {
                return v.normalize();
            }
        }
    }

    #[test]
    fn the_closed_form_extent_matches_dense_sampling_of_the_move() {
        let mut rng = StdRng::seed_from_u64(7);
        let mut hits = 0;
        for case in 0..150 {
            let piece = random_piece(&mut rng);
            // Axis-aligned rays half the time, as the dexel grids use; the axis sometimes
            // parallel to the ray or to the move.
            let axis = match case % 5 {
                0 => Vector3::z(),
                1 => Vector3::x(),
                _ => random_unit(&mut rng),
            };
            let f = AxisFrame::new(&Unit::new_normalize(axis));
            let d = match case % 4 {
                0 => Vector3::z(),
                1 => Vector3::x(),
                2 => Vector3::y(),
                _ => random_unit(&mut rng),
            };
            let v = match case % 7 {
                0 => Vector3::zeros(),
                1 => axis * rng.random_range(-4.0..4.0),
                _ => random_unit(&mut rng) * rng.random_range(0.0..6.0),
            };
            let p0 = Point3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(-2.0..2.0),
            );
            let o = Point3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
            );
            let rm = RayMove::new(&o, &d, &p0, &v, &f);
            let got = rm.extent(&piece);
            // Sample the ray: inside the interval (1e-3 in) must be in the swept piece, outside
            // (1e-3 out) must not.
            let tol = 2e-3 + v.norm() / 1500.0;
            for i in 0..=120 {
                let t = -12.0 + 24.0 * i as f64 / 120.0;
                let x = o + d * t;
                match got {
                    Some((lo, hi)) if t > lo + tol && t < hi - tol => {
                        assert!(
                            in_swept(&piece, &x, &p0, &v, &f, 1e-6),
                            "case {case}: t {t} in [{lo}, {hi}] not in {piece:?}"
                        );
                        hits += 1;
                    }
                    Some((lo, hi)) if t < lo - tol || t > hi + tol => {
                        assert!(
                            !in_swept(&piece, &x, &p0, &v, &f, -tol),
                            "case {case}: t {t} out of [{lo}, {hi}] is in {piece:?}"
                        );
                    }
                    None => assert!(
                        !in_swept(&piece, &x, &p0, &v, &f, -tol),
                        "case {case}: t {t} is in {piece:?}"
                    ),
                    _ => {}
                }
            }
        }
        assert!(hits > 500, "only {hits} samples inside");
    }

    #[test]
    fn a_ball_tool_is_a_sphere_and_a_shank() {
        let solid = ToolSolid::new(&ToolProfile::ball(6.0).expect("ball"), 40.0).expect("solid");
        assert_eq!(solid.pieces()[0], Piece::Sphere { c: 3.0, r: 3.0 });
        assert!(
            solid.contains(0.0, 0.0, 1e-9)
                && !solid.contains(2.9, 0.1, 0.0)
                && solid.contains(3.0, 39.0, 0.0)
        );
        let flat = ToolSolid::new(&ToolProfile::flat(6.0).expect("flat"), 30.0).expect("solid");
        assert!(flat.contains(2.99, 0.0, 0.0) && !flat.contains(3.01, 1.0, 0.0));
        assert!(ToolSolid::new(&ToolProfile::ball(6.0).expect("ball"), 2.0).is_err());
    }
}

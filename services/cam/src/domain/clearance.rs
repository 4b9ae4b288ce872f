//! Clearance of the tool, its shank and its holder from a part mesh at any tool orientation, and
//! the smallest tilt that clears a position where the upright tool collides (seed 001's holder
//! interference check and its avoidance by tilting, for milling from a mesh on a robot).
//!
//! # Model
//!
//! - **The tool as stacked cylinders** ([`ToolBody`]) along its axis from the tip: the cutting
//!   end as `CUTTING_SLICES` cylinders, each with the profile's radius at the slice's bottom (so
//!   inside the true solid: the cutting end may touch the part, and only entering it by more than
//!   the gouge tolerance counts; a ball's or bull's end is under-estimated by at most a sixteenth
//!   of its radius), the fluted length above the profile at the tool's radius less the tolerance,
//!   then the shank from the cutting length to the stick-out and the holder above it (the tool
//!   library's geometry), and optionally the spindle's body above the holder. The shank, holder
//!   and spindle must not touch the part at all.
//! - **The exact test** of a cylinder against a triangle: the triangle is clipped to the slab
//!   between the cylinder's end planes (a convex polygon) and projected along the axis; the
//!   cylinder meets it iff that convex polygon comes nearer the axis than the radius. No
//!   sampling: [`cylinder_distance`] is compared with a brute-force reference in the tests.
//! - **Candidates** come from a uniform grid over the mesh's triangle boxes ([`MeshIndex`]).
//! - **Tilting** ([`clear_path`]): at a position where the upright tool collides, the tool is
//!   turned about its tip, the axis leaning by `tilt` towards azimuth `φ`. Every
//!   [`TiltOptions::azimuths`] directions is tried from a small tilt up in [`TiltOptions::step_deg`]
//!   steps to [`TiltOptions::max_tilt_deg`]; the smallest clearing tilt wins (after a tilted
//!   position: the clearing axis nearest the previous one among tilts within two steps of the
//!   smallest, so the lean does not swap sides) and is refined by bisection to an eighth of a
//!   step. Then
//!   the lean (the axis's horizontal part) is ramped along the path so that it changes by at
//!   most [`TiltOptions::max_rate_deg_mm`] per millimetre of travel (the neighbours of a tilted
//!   stretch lean too, each checked), so the robot's wrist turns smoothly; a rapid breaks the
//!   chain. Only axes the machine carrying the tool accepts count ([`Accept`]: the robot planner
//!   refuses axes its arm cannot take there). Where the axis still turns by more than a step
//!   between neighbours, the poses on the way are checked too, and a turn that would sweep the
//!   tool into the part blocks the position it turns to. Positions that no tilt clears are
//!   reported with where they are and what hits, and left out of the cut: the program lifts over
//!   them ([`ClearedPath::lifted`]: out along the tool's axis, across, down along the next axis).

use depthmill_geometry::Mesh;
use nalgebra::{Point3, Unit, Vector3};
use rayon::prelude::*;

use super::tool::Tool;

/// Slices of the cutting end's profile in a [`ToolBody`].
pub const CUTTING_SLICES: usize = 16;

/// One cylinder of a [`ToolBody`], heights along the axis from the tip.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Section {
    pub from_mm: f64,
    pub to_mm: f64,
    pub radius_mm: f64,
    /// Which part of the tool: `"cutting"`, `"shank"`, `"holder"` or `"spindle"`.
    pub part: &'static str,
}

/// The tool in its holder as cylinders along its axis (see the module docs).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ToolBody {
    pub sections: Vec<Section>,
}

impl ToolBody {
    /// `tool`'s body with the cutting end shrunk by `gouge_tol_mm` (radially and at the tip) and
    /// a spindle body of `spindle` = (diameter, length) mm above the holder, if given.
    pub fn new(tool: &Tool, gouge_tol_mm: f64, spindle: Option<(f64, f64)>) -> Self {
        let tol = gouge_tol_mm.max(0.0);
        let r = tool.radius_mm();
        let top = tool.profile.max_height_mm();
        let mut sections = Vec::new();
        // The profile's radius at the bottom of each slice (radius steps of r/16); heights are
        // non-decreasing in the radius, so each cylinder lies inside the tool.
        let mut prev_h = tol;
        for k in 1..=CUTTING_SLICES {
            let rk = r * (k - 1) as f64 / CUTTING_SLICES as f64;
            let hk = tool.profile.height_at(r * k as f64 / CUTTING_SLICES as f64).unwrap_or(top).max(tol);
            if hk > prev_h + 1e-12 && rk - tol > 0.0 {
                sections.push(Section { from_mm: prev_h, to_mm: hk, radius_mm: rk - tol, part: "cutting" });
            }
            prev_h = prev_h.max(hk);
        }
        if tool.cutting_length_mm > prev_h && r - tol > 0.0 {
            sections.push(Section {
                from_mm: prev_h,
                to_mm: tool.cutting_length_mm,
                radius_mm: r - tol,
                part: "cutting",
            });
        }
        if tool.stickout_mm > tool.cutting_length_mm {
            sections.push(Section {
                from_mm: tool.cutting_length_mm,
                to_mm: tool.stickout_mm,
                radius_mm: tool.shank_diameter_mm / 2.0,
                part: "shank",
            });
        }
        let holder_top = tool.stickout_mm + tool.holder_length_mm;
        sections.push(Section {
            from_mm: tool.stickout_mm,
            to_mm: holder_top,
            radius_mm: tool.holder_diameter_mm / 2.0,
            part: "holder",
        });
        if let Some((d, l)) = spindle
            && d > 0.0
            && l > 0.0
        {
            sections.push(Section {
                from_mm: holder_top,
                to_mm: holder_top + l,
                radius_mm: d / 2.0,
                part: "spindle",
            });
        }
        ToolBody { sections }
    }

    /// Widest radius of any section.
    pub fn max_radius_mm(&self) -> f64 {
        self.sections.iter().map(|s| s.radius_mm).fold(0.0, f64::max)
    }

    /// Top of the body above the tip.
    pub fn length_mm(&self) -> f64 {
        self.sections.iter().map(|s| s.to_mm).fold(0.0, f64::max)
    }
}

/// A uniform grid over a mesh's triangles for box queries.
#[derive(Debug, Clone)]
pub struct MeshIndex {
    tris: Vec<[Vector3<f64>; 3]>,
    lo: Vector3<f64>,
    cell: f64,
    dims: [usize; 3],
    /// Cell `c`'s triangles are `items[starts[c]..starts[c + 1]]`.
    starts: Vec<u32>,
    items: Vec<u32>,
}

/// Largest grid of a [`MeshIndex`] (cells).
const MAX_INDEX_CELLS: usize = 1 << 21;

impl MeshIndex {
    /// Indexes `mesh`'s triangles (degenerate ones included: a sliver still blocks the holder).
    pub fn new(mesh: &Mesh) -> Self {
        let tris: Vec<[Vector3<f64>; 3]> = mesh
            .triangles
            .iter()
            .map(|t| t.map(|i| mesh.vertices.get(i as usize).map_or_else(Vector3::zeros, |p| p.coords)))
            .filter(|t| t.iter().all(|v| v.iter().all(|c| c.is_finite())))
            .collect();
        let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
        for v in tris.iter().flatten() {
            lo = lo.inf(v);
            hi = hi.sup(v);
        }
        if tris.is_empty() {
            lo = Vector3::zeros();
            hi = Vector3::zeros();
        }
        let size = hi - lo;
        // About as many cells as triangles, at most MAX_INDEX_CELLS.
        let volume = size.iter().map(|s| s.max(1e-3)).product::<f64>();
        let target = (tris.len().clamp(1, MAX_INDEX_CELLS)) as f64;
        let mut cell = (volume / target).cbrt().max(1e-3);
        let dims_for = |cell: f64| size.map(|s| ((s / cell).floor() as usize + 1).max(1));
        let mut dims = dims_for(cell);
        while dims.iter().product::<usize>() > MAX_INDEX_CELLS {
            cell *= 1.25;
            dims = dims_for(cell);
        }
        let dims = [dims.x, dims.y, dims.z];
        let mut index = MeshIndex { tris, lo, cell, dims, starts: Vec::new(), items: Vec::new() };
        let ranges: Vec<[[usize; 2]; 3]> = index
            .tris
            .iter()
            .map(|t| {
                let (a, b) = (t[0].inf(&t[1]).inf(&t[2]), t[0].sup(&t[1]).sup(&t[2]));
                index.cell_range(&a, &b)
            })
            .collect();
        let ncells = dims[0] * dims[1] * dims[2];
        let mut counts = vec![0u32; ncells + 1];
        for r in &ranges {
            index.for_cells(r, |c| counts[c + 1] += 1);
        }
        for c in 0..ncells {
            counts[c + 1] += counts[c];
        }
        let mut fill = counts.clone();
        let mut items = vec![0u32; counts[ncells] as usize];
        for (t, r) in ranges.iter().enumerate() {
            index.for_cells(r, |c| {
                items[fill[c] as usize] = t as u32;
                fill[c] += 1;
            });
        }
        index.starts = counts;
        index.items = items;
        index
    }

    /// The same triangles in one unbounded cell: every query that meets the mesh's box returns
    /// every triangle (the reference the tests and the benchmark hold the grid against).
    pub fn unindexed(mesh: &Mesh) -> Self {
        let mut index = MeshIndex::new(mesh);
        index.dims = [1, 1, 1];
        index.cell = f64::INFINITY;
        index.starts = vec![0, index.tris.len() as u32];
        index.items = (0..index.tris.len() as u32).collect();
        index
    }

    /// Triangles indexed.
    pub fn len(&self) -> usize {
        self.tris.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tris.is_empty()
    }

    fn cell_range(&self, a: &Vector3<f64>, b: &Vector3<f64>) -> [[usize; 2]; 3] {
        std::array::from_fn(|k| {
            let f = |v: f64| (((v - self.lo[k]) / self.cell).floor().max(0.0) as usize).min(self.dims[k] - 1);
            [f(a[k]), f(b[k])]
        })
    }

    fn for_cells(&self, r: &[[usize; 2]; 3], mut f: impl FnMut(usize)) {
        for z in r[2][0]..=r[2][1] {
            for y in r[1][0]..=r[1][1] {
                for x in r[0][0]..=r[0][1] {
                    f((z * self.dims[1] + y) * self.dims[0] + x);
                }
            }
        }
    }

    /// Indices of the triangles whose cells meet the box `a..b`, each once, into `scratch`.
    fn candidates(&self, a: &Vector3<f64>, b: &Vector3<f64>, scratch: &mut Scratch) {
        scratch.candidates.clear();
        if self.tris.is_empty() {
            return;
        }
        let hi = self.lo + Vector3::from(self.dims.map(|d| d as f64 * self.cell));
        if (0..3).any(|k| b[k] < self.lo[k] || a[k] > hi[k]) {
            return;
        }
        // A generation stamp per triangle instead of sorting out the repeats.
        if scratch.seen.len() != self.tris.len() || scratch.generation == u32::MAX {
            scratch.seen = vec![0; self.tris.len()];
            scratch.generation = 0;
        }
        scratch.generation += 1;
        let g = scratch.generation;
        let r = self.cell_range(a, b);
        let (seen, out) = (&mut scratch.seen, &mut scratch.candidates);
        self.for_cells(&r, |c| {
            for &t in &self.items[self.starts[c] as usize..self.starts[c + 1] as usize] {
                if seen[t as usize] != g {
                    seen[t as usize] = g;
                    out.push(t);
                }
            }
        });
    }
}

/// An orthonormal pair perpendicular to the unit vector `a`.
fn perpendiculars(a: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if a.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let u = a.cross(&helper).normalize();
    (u, a.cross(&u))
}

/// Distance from the origin to the segment `p`-`q` (2-D).
fn origin_segment_distance(p: [f64; 2], q: [f64; 2]) -> f64 {
    let d = [q[0] - p[0], q[1] - p[1]];
    let l2 = d[0] * d[0] + d[1] * d[1];
    let t = if l2 > 0.0 { (-(p[0] * d[0] + p[1] * d[1]) / l2).clamp(0.0, 1.0) } else { 0.0 };
    (p[0] + t * d[0]).hypot(p[1] + t * d[1])
}

/// A cylinder's frame: `(x, y)` across its axis, `h` along it from its base.
struct CylinderFrame {
    base: Vector3<f64>,
    u: Vector3<f64>,
    v: Vector3<f64>,
    axis: Vector3<f64>,
    length: f64,
}

/// A section touching the part within this distance does not collide (rounding of a shank as
/// wide as the tool running along the wall the tool finishes), mm.
pub const CONTACT_MM: f64 = 1e-6;

/// Most vertices of a triangle clipped by two parallel planes.
const MAX_CLIPPED: usize = 5;

impl CylinderFrame {
    fn new(base: &Vector3<f64>, axis: &Unit<Vector3<f64>>, length: f64) -> Self {
        let (u, v) = perpendiculars(axis);
        CylinderFrame { base: *base, u, v, axis: axis.into_inner(), length }
    }

    fn local(&self, tri: &[Vector3<f64>; 3]) -> [[f64; 3]; 3] {
        tri.map(|p| {
            let d = p - self.base;
            [d.dot(&self.u), d.dot(&self.v), d.dot(&self.axis)]
        })
    }

    /// Whether the cylinder of `radius` meets `tri` (quick rejections first).
    fn meets(&self, tri: &[Vector3<f64>; 3], radius: f64) -> Option<f64> {
        let l = self.local(tri);
        let all = |f: &dyn Fn(&[f64; 3]) -> bool| l.iter().all(f);
        if all(&|p| p[2] < 0.0)
            || all(&|p| p[2] > self.length)
            || all(&|p| p[0] >= radius)
            || all(&|p| p[0] <= -radius)
            || all(&|p| p[1] >= radius)
            || all(&|p| p[1] <= -radius)
        {
            return None;
        }
        clipped_distance(&l, self.length).filter(|&d| d < radius - CONTACT_MM)
    }
}

/// [`cylinder_distance`] on a triangle already in the cylinder's frame.
fn clipped_distance(tri: &[[f64; 3]; 3], length: f64) -> Option<f64> {
    let mut poly = [[0.0; 3]; MAX_CLIPPED];
    poly[..3].copy_from_slice(tri);
    let mut n = 3;
    for (keep_above, plane) in [(true, 0.0), (false, length)] {
        let inside = |p: &[f64; 3]| if keep_above { p[2] >= plane } else { p[2] <= plane };
        let mut out = [[0.0; 3]; MAX_CLIPPED];
        let mut m = 0;
        for i in 0..n {
            let (p, q) = (poly[i], poly[(i + 1) % n]);
            if inside(&p) && m < MAX_CLIPPED {
                out[m] = p;
                m += 1;
            }
            if inside(&p) != inside(&q) && m < MAX_CLIPPED {
                let t = (plane - p[2]) / (q[2] - p[2]);
                out[m] = [p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]), plane];
                m += 1;
            }
        }
        poly = out;
        n = m;
        if n == 0 {
            return None;
        }
    }
    // The projection along the axis is convex: the origin is inside iff it is on one side of
    // every edge (a polygon of no area falls back to its edges' distance).
    let (mut pos, mut neg) = (false, false);
    let mut best = f64::INFINITY;
    let mut area2 = 0.0;
    for i in 0..n {
        let (p, q) = (poly[i], poly[(i + 1) % n]);
        let cross = p[0] * q[1] - p[1] * q[0];
        area2 += cross;
        pos |= cross > 0.0;
        neg |= cross < 0.0;
        best = best.min(origin_segment_distance([p[0], p[1]], [q[0], q[1]]));
    }
    if area2.abs() > 1e-18 && !(pos && neg) {
        return Some(0.0);
    }
    Some(best)
}

/// The smallest distance from the axis of a cylinder (through `base`, direction `axis`, heights
/// `0..=length` along it) to the part of triangle `tri` between the cylinder's end planes, or
/// `None` when the triangle has no point there. The cylinder of radius `R` meets the triangle iff
/// the distance is below `R`.
pub fn cylinder_distance(
    tri: &[Vector3<f64>; 3],
    base: &Vector3<f64>,
    axis: &Unit<Vector3<f64>>,
    length: f64,
) -> Option<f64> {
    let f = CylinderFrame::new(base, axis, length);
    clipped_distance(&f.local(tri), length)
}

/// Where a tool body meets the part.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Hit {
    /// The section's part (`"cutting"`, `"shank"`, `"holder"`, `"spindle"`; `"arm"` where the
    /// machine carrying the tool cannot take the pose).
    pub part: &'static str,
    /// The triangle's index in the indexed list.
    pub triangle: u32,
    /// How far into the section's cylinder the triangle reaches, mm.
    pub depth_mm: f64,
}

/// Reused buffers of the collision queries.
#[derive(Debug, Default)]
pub struct Scratch {
    candidates: Vec<u32>,
    /// Per triangle, the query that last listed it.
    seen: Vec<u32>,
    generation: u32,
}

/// The first section of `body` (tip upwards) that meets the part with its tip at `tip` and its
/// axis along `axis` (from the tip towards the holder), or `None` when the whole body is clear.
pub fn collision(
    index: &MeshIndex,
    body: &ToolBody,
    tip: &Point3<f64>,
    axis: &Unit<Vector3<f64>>,
    scratch: &mut Scratch,
) -> Option<Hit> {
    first_hit(index, body, tip, axis, scratch, false)
}

/// Whether the body at `tip` along `axis` meets the part (stops at the first triangle).
pub fn collides(
    index: &MeshIndex,
    body: &ToolBody,
    tip: &Point3<f64>,
    axis: &Unit<Vector3<f64>>,
    scratch: &mut Scratch,
) -> bool {
    first_hit(index, body, tip, axis, scratch, true).is_some()
}

fn first_hit(
    index: &MeshIndex,
    body: &ToolBody,
    tip: &Point3<f64>,
    axis: &Unit<Vector3<f64>>,
    scratch: &mut Scratch,
    any: bool,
) -> Option<Hit> {
    for s in &body.sections {
        let base = tip.coords + axis.as_ref() * s.from_mm;
        let top = tip.coords + axis.as_ref() * s.to_mm;
        let pad = Vector3::repeat(s.radius_mm);
        index.candidates(&(base.inf(&top) - pad), &(base.sup(&top) + pad), scratch);
        let frame = CylinderFrame::new(&base, axis, s.to_mm - s.from_mm);
        let mut deepest: Option<Hit> = None;
        for &t in &scratch.candidates {
            if let Some(d) = frame.meets(&index.tris[t as usize], s.radius_mm)
                && deepest.is_none_or(|h| s.radius_mm - d > h.depth_mm)
            {
                deepest = Some(Hit { part: s.part, triangle: t, depth_mm: s.radius_mm - d });
                if any {
                    return deepest;
                }
            }
        }
        if deepest.is_some() {
            return deepest;
        }
    }
    None
}

/// Rapid moves are sampled this many times more sparsely than feed moves.
pub const RAPID_SAMPLES_APART: f64 = 5.0;

/// Settings of the tilt search (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TiltOptions {
    /// Largest tilt from the upright axis, degrees.
    pub max_tilt_deg: f64,
    /// Tilt step of the search, degrees (refined to an eighth of it).
    pub step_deg: f64,
    /// Directions of lean tried.
    pub azimuths: usize,
    /// Largest change of the tool axis per millimetre of travel, degrees.
    pub max_rate_deg_mm: f64,
    /// Positions checked along a move at least this often, mm.
    pub sample_mm: f64,
    /// How far the cutting end may enter the part, mm.
    pub gouge_tol_mm: f64,
}

impl Default for TiltOptions {
    fn default() -> Self {
        TiltOptions {
            max_tilt_deg: 40.0,
            step_deg: 2.0,
            azimuths: 24,
            max_rate_deg_mm: 2.0,
            sample_mm: 1.0,
            gouge_tol_mm: 0.01,
        }
    }
}

impl TiltOptions {
    /// Checks every setting is usable.
    pub fn validate(&self) -> Result<(), String> {
        let bad = |k: &str, v: f64, want: &str| Err(format!("{k} {v}: {want}"));
        if !(self.max_tilt_deg.is_finite() && (0.0..=80.0).contains(&self.max_tilt_deg)) {
            return bad("max_tilt_deg", self.max_tilt_deg, "must be from 0 to 80 degrees");
        }
        if !(self.step_deg.is_finite() && self.step_deg >= 0.1 && self.step_deg <= 10.0) {
            return bad("step_deg", self.step_deg, "must be from 0.1 to 10 degrees");
        }
        if !(4..=360).contains(&self.azimuths) {
            return bad("azimuths", self.azimuths as f64, "must be from 4 to 360 directions");
        }
        if !(self.max_rate_deg_mm.is_finite() && self.max_rate_deg_mm > 0.0) {
            return bad("max_rate_deg_mm", self.max_rate_deg_mm, "must be a positive rate");
        }
        if !(self.sample_mm.is_finite() && self.sample_mm >= 0.01) {
            return bad("sample_mm", self.sample_mm, "must be at least 0.01 mm");
        }
        if !(self.gouge_tol_mm.is_finite() && self.gouge_tol_mm >= 0.0) {
            return bad("gouge_tol_mm", self.gouge_tol_mm, "must be a non-negative distance");
        }
        Ok(())
    }
}

/// The axis leaning by `tilt` (radians) towards azimuth `phi` (radians, from +X about +Z).
pub fn leaning_axis(tilt: f64, phi: f64) -> Unit<Vector3<f64>> {
    Unit::new_normalize(Vector3::new(tilt.sin() * phi.cos(), tilt.sin() * phi.sin(), tilt.cos()))
}

fn axis_of_lean(l: [f64; 2]) -> Unit<Vector3<f64>> {
    let tilt = l[0].hypot(l[1]);
    if tilt < 1e-15 { Vector3::z_axis() } else { leaning_axis(tilt, l[1].atan2(l[0])) }
}

/// The lean of an axis: its tilt (radians) times the direction it leans to.
fn lean_of(axis: &[f64; 3]) -> [f64; 2] {
    let h = axis[0].hypot(axis[1]);
    if h < 1e-15 {
        return [0.0, 0.0];
    }
    let tilt = h.atan2(axis[2]);
    [tilt * axis[0] / h, tilt * axis[1] / h]
}

/// The axis a fraction `f` of the way from `a0` to `a1`, their leans interpolated linearly: how
/// the tool turns between two positions, in the check here and in the robot program alike.
pub fn axis_between(a0: &[f64; 3], a1: &[f64; 3], f: f64) -> [f64; 3] {
    let (l0, l1) = (lean_of(a0), lean_of(a1));
    let a = axis_of_lean([l0[0] + f * (l1[0] - l0[0]), l0[1] + f * (l1[1] - l0[1])]);
    [a.x, a.y, a.z]
}

/// One position of a checked path.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct OrientedPoint {
    pub tip: [f64; 3],
    /// Tool axis (unit, from the tip towards the holder).
    pub axis: [f64; 3],
    /// Reached by a rapid move (else a feed move).
    pub rapid: bool,
    /// No tilt clears this position: the program lifts over it.
    pub blocked: bool,
}

/// A position no tilt clears.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Blocked {
    pub at_mm: [f64; 3],
    /// What the upright tool hits there.
    pub part: &'static str,
    pub depth_mm: f64,
}

/// The checked path and what the check found.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize)]
pub struct ClearedPath {
    pub points: Vec<OrientedPoint>,
    /// Positions where the upright tool collides.
    pub colliding: usize,
    /// Positions that lean (to clear, or ramping to and from a clearing lean).
    pub tilted: usize,
    pub max_tilt_deg: f64,
    /// Largest change of the tool axis per millimetre between neighbouring feed positions.
    pub max_rate_deg_mm: f64,
    pub blocked: Vec<Blocked>,
}

/// Which tilted axes the machine carrying the tool can take at a tip (the robot planner refuses
/// axes near the arm's wrist singularity); [`any_axis`] takes every one.
pub type Accept<'a> = &'a (dyn Fn(&Point3<f64>, &Unit<Vector3<f64>>) -> bool + Sync);

/// Asked by [`clear_path`] every [`STOP_EVERY`] positions with the positions checked so far and
/// their number; `true` stops it with the error [`STOPPED`] (a cancelled job).
pub type Stop<'a> = &'a (dyn Fn(usize, usize) -> bool + Sync);

/// How often [`clear_path`] asks its [`Stop`], in positions.
pub const STOP_EVERY: usize = 256;

/// The error of a [`clear_path`] its [`Stop`] ended.
pub const STOPPED: &str = "stopped on request";

/// A [`Stop`] that never stops.
pub fn never(_: usize, _: usize) -> bool {
    false
}

/// Every axis is acceptable.
pub fn any_axis(_: &Point3<f64>, _: &Unit<Vector3<f64>>) -> bool {
    true
}

/// Azimuths whose smallest clearing tilt is within this many steps of the smallest of all
/// compete on how little the axis turns from the previous position's.
const AZIMUTH_SLACK_STEPS: usize = 2;

/// The leans that clear `tip`, as (tilt step, azimuth in radians): per azimuth (from 0, then
/// outwards both ways) its smallest clearing tilt step, for the azimuths within
/// [`AZIMUTH_SLACK_STEPS`] of the smallest of all. Empty when no tilt up to the limit clears.
/// Does not depend on the previous position, so positions are searched in parallel.
fn tilt_candidates(
    index: &MeshIndex,
    body: &ToolBody,
    tip: &Point3<f64>,
    o: &TiltOptions,
    accept: Accept<'_>,
    scratch: &mut Scratch,
) -> Vec<(usize, f64)> {
    let step = o.step_deg.to_radians();
    let steps = (o.max_tilt_deg.to_radians() / step).floor() as usize;
    let n = o.azimuths;
    let d = std::f64::consts::TAU / n as f64;
    let order = (0..n as i64).map(|i| {
        let off = if i % 2 == 1 { (i + 1) / 2 } else { -(i / 2) };
        off as f64 * d
    });
    let mut found: Vec<(usize, f64)> = Vec::new();
    let mut kmin = usize::MAX;
    for phi in order {
        // Once one azimuth clears, the others need not look past the slack above it.
        let limit = if kmin == usize::MAX { steps } else { (kmin + AZIMUTH_SLACK_STEPS).min(steps) };
        if let Some(k) = (1..=limit).find(|&k| {
            let axis = leaning_axis(k as f64 * step, phi);
            !collides(index, body, tip, &axis, scratch) && accept(tip, &axis)
        }) {
            kmin = kmin.min(k);
            found.push((k, phi));
        }
    }
    found.retain(|&(k, _)| k <= kmin.saturating_add(AZIMUTH_SLACK_STEPS));
    found
}

/// The tilt (radians) and azimuth clearing `tip` among its `candidates`
/// ([`tilt_candidates`]): the smallest tilt, or, after a tilted position, the clearing axis
/// nearest the previous one (`prev`), so the lean does not swap sides between neighbours; the
/// tilt then bisected between the last colliding and the first clearing step.
fn pick_tilt(
    (index, body, accept): (&MeshIndex, &ToolBody, Accept<'_>),
    tip: &Point3<f64>,
    o: &TiltOptions,
    prev: Option<&Unit<Vector3<f64>>>,
    candidates: &[(usize, f64)],
    scratch: &mut Scratch,
) -> Option<(f64, f64)> {
    let step = o.step_deg.to_radians();
    let turn = |k: usize, phi: f64| {
        prev.map_or(0.0, |a| a.dot(&leaning_axis(k as f64 * step, phi)).clamp(-1.0, 1.0).acos())
    };
    let &(k, phi) = candidates.iter().min_by(|a, b| {
        let key = |&(k, phi): &(usize, f64)| if prev.is_some() { (turn(k, phi), k) } else { (0.0, k) };
        let (ta, ka) = key(a);
        let (tb, kb) = key(b);
        ta.total_cmp(&tb).then(ka.cmp(&kb))
    })?;
    let (mut lo, mut hi) = ((k - 1) as f64 * step, k as f64 * step);
    for _ in 0..3 {
        let mid = 0.5 * (lo + hi);
        let axis = leaning_axis(mid, phi);
        if collides(index, body, tip, &axis, scratch) || !accept(tip, &axis) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some((hi, phi))
}

/// [`tilt_candidates`] then [`pick_tilt`]: the lean clearing `tip` after `prev`.
#[cfg(test)]
fn search_tilt(
    index: &MeshIndex,
    body: &ToolBody,
    tip: &Point3<f64>,
    o: &TiltOptions,
    prev: Option<&Unit<Vector3<f64>>>,
    accept: Accept<'_>,
    scratch: &mut Scratch,
) -> Option<(f64, f64)> {
    let candidates = tilt_candidates(index, body, tip, o, accept, scratch);
    pick_tilt((index, body, accept), tip, o, prev, &candidates, scratch)
}

/// What [`first_leans`] found.
struct FirstLeans {
    leans: Vec<Option<[f64; 2]>>,
    colliding: usize,
    blocked: Vec<Blocked>,
}

/// Per position (tip, rapid) the lean `[tilt·cos φ, tilt·sin φ]` that clears it (zero where
/// the upright tool does, `None` where no tilt does), how many collide upright, and the
/// blocked ones. The upright checks and each colliding position's candidate leans are found in
/// parallel, [`STOP_EVERY`] positions at a time between the `stop` questions; the choice among
/// a position's candidates depends on the previous position's lean (none after a rapid), so it
/// is made in order.
fn first_leans(
    index: &MeshIndex,
    body: &ToolBody,
    pts: &[([f64; 3], bool)],
    o: &TiltOptions,
    accept: Accept<'_>,
    stop: Stop<'_>,
) -> Result<FirstLeans, String> {
    // Per position: what the upright tool hits and the leans that clear it.
    type Found = Option<(Hit, Vec<(usize, f64)>)>;
    let mut found: Vec<Found> = Vec::with_capacity(pts.len());
    for (c, chunk) in pts.chunks(STOP_EVERY).enumerate() {
        if stop(c * STOP_EVERY, pts.len()) {
            return Err(STOPPED.to_string());
        }
        found.par_extend(chunk.par_iter().map_init(Scratch::default, |scratch, &(p, _)| {
            let tip = Point3::from(p);
            collision(index, body, &tip, &Vector3::z_axis(), scratch)
                .map(|hit| (hit, tilt_candidates(index, body, &tip, o, accept, scratch)))
        }));
    }
    let mut scratch = Scratch::default();
    let (mut colliding, mut blocked) = (0, Vec::new());
    let mut leans: Vec<Option<[f64; 2]>> = Vec::with_capacity(pts.len());
    let mut prev_axis: Option<Unit<Vector3<f64>>> = None;
    for (&(p, rapid), f) in pts.iter().zip(&found) {
        let tip = Point3::from(p);
        match f {
            None => {
                leans.push(Some([0.0, 0.0]));
                prev_axis = None;
            }
            Some((hit, candidates)) => {
                colliding += 1;
                match pick_tilt((index, body, accept), &tip, o, prev_axis.as_ref(), candidates, &mut scratch)
                {
                    Some((tilt, phi)) => {
                        prev_axis = Some(leaning_axis(tilt, phi));
                        leans.push(Some([tilt * phi.cos(), tilt * phi.sin()]));
                    }
                    None => {
                        blocked.push(Blocked { at_mm: p, part: hit.part, depth_mm: hit.depth_mm });
                        leans.push(None);
                        prev_axis = None;
                    }
                }
            }
        }
        if rapid {
            prev_axis = None;
        }
    }
    Ok(FirstLeans { leans, colliding, blocked })
}

/// Checks every position of a path (moves to `points`, each a rapid or a feed; feed moves
/// sampled every [`TiltOptions::sample_mm`], rapids every [`RAPID_SAMPLES_APART`] times that, so
/// that a robot moving joint-interpolated between neighbours stays near the checked line) and
/// tilts the tool where the upright one collides, taking only axes `accept` takes (see the
/// module docs). `start` is where the path begins.
pub fn clear_path(
    index: &MeshIndex,
    body: &ToolBody,
    start: [f64; 3],
    moves: &[([f64; 3], bool)],
    o: &TiltOptions,
    accept: Accept<'_>,
    stop: Stop<'_>,
) -> Result<ClearedPath, String> {
    o.validate()?;
    // Positions: every move end, feed moves subdivided.
    let mut pts: Vec<([f64; 3], bool)> = vec![(start, true)];
    let mut prev = start;
    for &(to, rapid) in moves {
        if !to.iter().all(|v| v.is_finite()) {
            return Err(format!("move {} to {to:?}: not a finite position", pts.len()));
        }
        let len = (0..3).map(|k| (to[k] - prev[k]).powi(2)).sum::<f64>().sqrt();
        let spacing = if rapid { RAPID_SAMPLES_APART * o.sample_mm } else { o.sample_mm };
        let n = (len / spacing).ceil().max(1.0) as usize;
        for i in 1..n {
            let t = i as f64 / n as f64;
            pts.push((std::array::from_fn(|k| prev[k] + t * (to[k] - prev[k])), rapid));
        }
        pts.push((to, rapid));
        prev = to;
    }
    let FirstLeans { mut leans, colliding, blocked } = first_leans(index, body, &pts, o, accept, stop)?;
    let mut scratch = Scratch::default();
    let mut out = ClearedPath { colliding, blocked, ..ClearedPath::default() };
    // Ramp the lean along each chain of feed positions, both ways.
    let rate = o.max_rate_deg_mm.to_radians();
    let dist = |i: usize, j: usize| (0..3).map(|k| (pts[i].0[k] - pts[j].0[k]).powi(2)).sum::<f64>().sqrt();
    let ramp = |from: usize, to: usize, leans: &mut Vec<Option<[f64; 2]>>, scratch: &mut Scratch| {
        let (Some(l), Some(cur)) = (leans[from], leans[to]) else { return };
        let mag = l[0].hypot(l[1]);
        let allowed = mag - rate * dist(from, to);
        if allowed <= 0.0 || allowed <= cur[0].hypot(cur[1]) {
            return;
        }
        let cand = [l[0] * allowed / mag, l[1] * allowed / mag];
        let (tip, axis) = (Point3::from(pts[to].0), axis_of_lean(cand));
        if !collides(index, body, &tip, &axis, scratch) && accept(&tip, &axis) {
            leans[to] = Some(cand);
        }
    };
    let feeds: Vec<usize> = (1..pts.len()).filter(|&i| !pts[i].1).collect();
    for &i in &feeds {
        ramp(i - 1, i, &mut leans, &mut scratch);
    }
    for &i in feeds.iter().rev() {
        ramp(i, i - 1, &mut leans, &mut scratch);
    }
    // Where the axis turns by more than a step between neighbours, the poses on the way are
    // checked too (tip and lean interpolated): a turn that sweeps the tool into the part blocks
    // the position it turns to, so the path lifts out along the old axis and comes back down
    // along the new one instead.
    let step = o.step_deg.to_radians();
    for i in 1..pts.len() {
        let (Some(l0), Some(l1)) = (leans[i - 1], leans[i]) else { continue };
        let turn = (l1[0] - l0[0]).hypot(l1[1] - l0[1]);
        if turn <= step {
            continue;
        }
        let m = (turn / step).ceil() as usize;
        let (a, b) = (pts[i - 1].0, pts[i].0);
        let hit = (1..m).find_map(|k| {
            let f = k as f64 / m as f64;
            let tip = Point3::from(std::array::from_fn::<f64, 3, _>(|c| a[c] + f * (b[c] - a[c])));
            let axis = axis_of_lean([l0[0] + f * (l1[0] - l0[0]), l0[1] + f * (l1[1] - l0[1])]);
            collision(index, body, &tip, &axis, &mut scratch)
                .or_else(|| (!accept(&tip, &axis)).then_some(Hit { part: "arm", triangle: 0, depth_mm: 0.0 }))
        });
        if let Some(h) = hit {
            out.blocked.push(Blocked { at_mm: b, part: h.part, depth_mm: h.depth_mm });
            leans[i] = None;
        }
    }
    let mut last_axis: Option<(usize, Unit<Vector3<f64>>)> = None;
    for (i, (&(p, rapid), lean)) in pts.iter().zip(&leans).enumerate() {
        let axis = lean.map_or(Vector3::z_axis(), axis_of_lean);
        let tilt = axis.z.clamp(-1.0, 1.0).acos().to_degrees();
        if lean.is_some_and(|l| l[0].hypot(l[1]) > 0.0) {
            out.tilted += 1;
            out.max_tilt_deg = out.max_tilt_deg.max(tilt);
        }
        if let Some((j, a)) = last_axis
            && j + 1 == i
            && !rapid
            && lean.is_some()
        {
            let d = dist(j, i);
            if d > 1e-9 {
                let turn = a.dot(&axis).clamp(-1.0, 1.0).acos().to_degrees();
                out.max_rate_deg_mm = out.max_rate_deg_mm.max(turn / d);
            }
        }
        last_axis = lean.map(|_| (i, axis));
        out.points.push(OrientedPoint {
            tip: p,
            axis: [axis.x, axis.y, axis.z],
            rapid,
            blocked: lean.is_none(),
        });
    }
    Ok(out)
}

impl ClearedPath {
    /// The path with every stretch of blocked positions replaced by a lift over it: from the
    /// last clear position out along its axis up to `clear_z` (at feed: stock may stand above
    /// it; sampled and checked), across to where the next clear
    /// position's axis meets that height, and down along the axis to it at feed (sampled and
    /// checked like the rest; upright where `accept` refuses that axis or it collides and upright does not; a
    /// descent that still collides is added to [`ClearedPath::blocked`]).
    pub fn lifted(
        &self,
        index: &MeshIndex,
        body: &ToolBody,
        clear_z: f64,
        o: &TiltOptions,
        accept: Accept<'_>,
    ) -> ClearedPath {
        let mut out = ClearedPath { points: Vec::with_capacity(self.points.len()), ..self.clone() };
        let mut scratch = Scratch::default();
        // The axis `p` has, or upright where the machine cannot take it there (or it collides
        // and upright does not).
        let settle = |tip: [f64; 3], p: &OrientedPoint, scratch: &mut Scratch| -> OrientedPoint {
            let at = Point3::from(tip);
            let axis = Unit::new_normalize(Vector3::from(p.axis));
            let fits =
                |a: &Unit<Vector3<f64>>, s: &mut Scratch| !collides(index, body, &at, a, s) && accept(&at, a);
            let axis = if !fits(&axis, scratch) && fits(&Vector3::z_axis(), scratch) {
                Vector3::z_axis()
            } else {
                axis
            };
            OrientedPoint { tip, axis: [axis.x, axis.y, axis.z], ..*p }
        };
        // `p` at `tip` turned upright when the upright tool fits there (else as it is).
        let upright = |tip: [f64; 3], p: &OrientedPoint, scratch: &mut Scratch| -> OrientedPoint {
            let at = Point3::from(tip);
            let z = Vector3::z_axis();
            if !collides(index, body, &at, &z, scratch) && accept(&at, &z) {
                OrientedPoint { tip, axis: [0.0, 0.0, 1.0], ..*p }
            } else {
                OrientedPoint { tip, ..*p }
            }
        };
        let mut i = 0;
        while i < self.points.len() {
            let p = self.points[i];
            if !p.blocked {
                out.points.push(p);
                i += 1;
                continue;
            }
            let end = (i..self.points.len()).find(|&j| !self.points[j].blocked);
            let Some(j) = end else { break };
            let next = self.points[j];
            if let Some(last) = out.points.last().copied() {
                // Out along the last position's axis (a tilted tool moved straight up would
                // sweep its body into what it leans away from), at feed: stock may stand above.
                let a = last.axis;
                let reach = if a[2] > 1e-6 { (clear_z - last.tip[2]).max(0.0) / a[2] } else { 0.0 };
                let n = (reach / o.sample_mm).ceil().max(1.0) as usize;
                for k in 1..=n {
                    let t = reach * k as f64 / n as f64;
                    let tip = [last.tip[0] + a[0] * t, last.tip[1] + a[1] * t, last.tip[2] + a[2] * t];
                    let q = settle(tip, &OrientedPoint { rapid: false, ..last }, &mut scratch);
                    let axis = Unit::new_normalize(Vector3::from(q.axis));
                    if let Some(hit) = collision(index, body, &Point3::from(tip), &axis, &mut scratch) {
                        out.blocked.push(Blocked { at_mm: tip, part: hit.part, depth_mm: hit.depth_mm });
                    }
                    out.points.push(q);
                }
                // Upright at the clearance height before going across: the way across then
                // keeps one axis the machine takes at both ends, instead of turning from one
                // lean to the next on the way (through axes nobody checked).
                if let Some(top) = out.points.last().copied() {
                    let up = upright(top.tip, &top, &mut scratch);
                    if up.axis != top.axis {
                        out.points.push(up);
                    }
                }
            }
            // Down along the next position's axis (the body slides along its own line, clear
            // of what it clears there), from where that line meets the clearance height.
            let a = next.axis;
            let reach = if a[2] > 1e-6 { (clear_z - next.tip[2]).max(0.0) / a[2] } else { 0.0 };
            let along = |t: f64| [next.tip[0] + a[0] * t, next.tip[1] + a[1] * t, next.tip[2] + a[2] * t];
            let over = OrientedPoint { rapid: true, ..next };
            let above = settle(along(reach), &over, &mut scratch);
            // Across upright, then the turn to the next position's axis in place.
            let across = upright(above.tip, &above, &mut scratch);
            if across.axis != above.axis {
                out.points.push(across);
                out.points.push(OrientedPoint { rapid: false, ..above });
            } else {
                out.points.push(above);
            }
            let n = (reach / o.sample_mm).ceil().max(1.0) as usize;
            for k in 1..n {
                let tip = along(reach * (n - k) as f64 / n as f64);
                let q = settle(tip, &OrientedPoint { rapid: false, ..next }, &mut scratch);
                let axis = Unit::new_normalize(Vector3::from(q.axis));
                if let Some(hit) = collision(index, body, &Point3::from(tip), &axis, &mut scratch) {
                    out.blocked.push(Blocked { at_mm: tip, part: hit.part, depth_mm: hit.depth_mm });
                }
                out.points.push(q);
            }
            i = j;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;
    use crate::domain::tool::Tool;

    /// Reference: the distance from the axis over a fine barycentric sampling of the triangle,
    /// restricted to the slab (`None` when no sample is in it).
    fn sampled_distance(
        tri: &[Vector3<f64>; 3],
        base: &Vector3<f64>,
        axis: &Unit<Vector3<f64>>,
        length: f64,
        n: usize,
    ) -> Option<f64> {
        let mut best: Option<f64> = None;
        for i in 0..=n {
            for j in 0..=n - i {
                let (a, b) = (i as f64 / n as f64, j as f64 / n as f64);
                let p = tri[0] * (1.0 - a - b) + tri[1] * a + tri[2] * b - base;
                let h = p.dot(axis);
                if (0.0..=length).contains(&h) {
                    let d = (p - axis.as_ref() * h).norm();
                    best = Some(best.map_or(d, |x: f64| x.min(d)));
                }
            }
        }
        best
    }

    fn v3() -> impl Strategy<Value = Vector3<f64>> {
        (-5.0f64..5.0, -5.0f64..5.0, -5.0f64..5.0).prop_map(|(x, y, z)| Vector3::new(x, y, z))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]

        /// The exact distance is never above any sampled one and within the sampling's spacing
        /// of the smallest; when the slab holds a sample the exact test finds the triangle there.
        #[test]
        fn cylinder_distance_matches_sampling(a in v3(), b in v3(), c in v3(), base in v3(), dir in v3(), len in 0.5f64..6.0) {
            prop_assume!(dir.norm() > 0.1);
            let axis = Unit::new_normalize(dir);
            let tri = [a, b, c];
            let n = 200;
            let exact = cylinder_distance(&tri, &base, &axis, len);
            let sampled = sampled_distance(&tri, &base, &axis, len, n);
            let spacing = [a - b, b - c, c - a].iter().map(|e| e.norm()).fold(0.0, f64::max) / n as f64;
            match (exact, sampled) {
                (Some(e), Some(s)) => {
                    prop_assert!(e <= s + 1e-9, "exact {e} above sampled {s}");
                    prop_assert!(s <= e + 2.0 * spacing + 1e-9, "exact {e} far below sampled {s}");
                }
                (None, Some(s)) => prop_assert!(false, "exact found nothing, sampled {s}"),
                // The slab may hold a sliver between samples.
                (_, None) => {}
            }
        }
    }

    fn tool() -> Tool {
        Tool::from_spec(&"flat-6".parse().expect("spec")).expect("tool")
    }

    /// A closed box mesh.
    fn block(lo: [f64; 3], hi: [f64; 3]) -> Mesh {
        let v: Vec<Point3<f64>> = (0..8)
            .map(|i| {
                Point3::new(
                    if i & 1 == 0 { lo[0] } else { hi[0] },
                    if i & 2 == 0 { lo[1] } else { hi[1] },
                    if i & 4 == 0 { lo[2] } else { hi[2] },
                )
            })
            .collect();
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        let tris = quads.iter().flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]).collect();
        Mesh::new(v, tris).expect("mesh")
    }

    /// Two meshes as one.
    fn both(mut a: Mesh, b: Mesh) -> Mesh {
        let n = a.vertices.len() as u32;
        a.vertices.extend(b.vertices);
        a.triangles.extend(b.triangles.iter().map(|t| t.map(|i| i + n)));
        a
    }

    #[test]
    fn the_body_stacks_the_tool_library_geometry() {
        let t = tool();
        let b = ToolBody::new(&t, 0.01, Some((60.0, 100.0)));
        let parts: Vec<&str> = b.sections.iter().map(|s| s.part).collect();
        assert_eq!(parts, ["cutting", "shank", "holder", "spindle"]);
        assert!((b.sections[0].radius_mm - 2.99).abs() < 1e-12);
        assert_eq!(b.sections[2].radius_mm, 16.0);
        assert!((b.length_mm() - (t.stickout_mm + t.holder_length_mm + 100.0)).abs() < 1e-9);
        // A ball's cutting end: slices inside the sphere.
        let ball = Tool::from_spec(&"ball-6".parse().expect("spec")).expect("tool");
        let bb = ToolBody::new(&ball, 0.0, None);
        for s in bb.sections.iter().filter(|s| s.part == "cutting" && s.from_mm < 3.0) {
            let h = s.from_mm;
            let true_r = (3.0f64 * 3.0 - (3.0 - h) * (3.0 - h)).max(0.0).sqrt();
            assert!(s.radius_mm <= true_r + 1e-9, "{s:?} outside the ball ({true_r})");
            assert!(true_r - s.radius_mm <= 3.0 / CUTTING_SLICES as f64 + 1e-9);
        }
    }

    #[test]
    fn collisions_name_the_part_that_hits() {
        // A wall 60 mm tall, its face at x = 0; the tool beside it at z = 10.
        let mesh = block([-20.0, -50.0, 0.0], [0.0, 50.0, 60.0]);
        let index = MeshIndex::new(&mesh);
        let body = ToolBody::new(&tool(), 0.01, None);
        let mut s = Scratch::default();
        let up = Vector3::z_axis();
        // Tool edge touching the wall: clear of the cutting end within the tolerance, but the
        // holder (radius 16) reaches into the wall.
        let hit = collision(&index, &body, &Point3::new(3.0, 0.0, 10.0), &up, &mut s).expect("hit");
        assert_eq!(hit.part, "holder");
        assert!((hit.depth_mm - 13.0).abs() < 1e-9, "{hit:?}");
        // Into the wall by 0.5 mm: the cutting end gouges.
        let hit = collision(&index, &body, &Point3::new(2.5, 0.0, 10.0), &up, &mut s).expect("hit");
        assert_eq!(hit.part, "cutting");
        // Far enough: clear. Above the wall: clear.
        assert!(collision(&index, &body, &Point3::new(16.5, 0.0, 10.0), &up, &mut s).is_none());
        assert!(collision(&index, &body, &Point3::new(3.0, 0.0, 60.5), &up, &mut s).is_none());
    }

    #[test]
    fn a_wall_is_cleared_by_leaning_away_with_a_smooth_ramp() {
        let mesh = block([-20.0, -50.0, 0.0], [0.0, 50.0, 60.0]);
        let index = MeshIndex::new(&mesh);
        let body = ToolBody::new(&tool(), 0.01, None);
        let o = TiltOptions::default();
        // Along the wall at 3 mm, coming in from 40 mm away.
        let moves = [([40.0, -20.0, 10.0], true), ([3.0, -20.0, 10.0], false), ([3.0, 20.0, 10.0], false)];
        let path =
            clear_path(&index, &body, [40.0, -20.0, 70.0], &moves, &o, &any_axis, &never).expect("path");
        assert!(path.blocked.is_empty(), "{:?}", path.blocked);
        assert!(path.colliding > 0);
        let mut s = Scratch::default();
        for p in &path.points {
            let axis = Unit::new_normalize(Vector3::from(p.axis));
            assert!(collision(&index, &body, &Point3::from(p.tip), &axis, &mut s).is_none(), "{p:?}");
            // Leans away from the wall (+X), never towards it.
            assert!(p.axis[0] >= -1e-12, "{p:?}");
        }
        // The holder must move 13 mm out over a 34 mm stick-out, plus its own tilt: about 20°.
        assert!((18.0..=30.0).contains(&path.max_tilt_deg), "{}", path.max_tilt_deg);
        // The smallest clearing tilt: a degree less collides.
        let along = path.points.iter().find(|p| p.tip[0] == 3.0 && p.tip[1] == 0.0).expect("point");
        let tilt = along.axis[2].acos();
        assert!(
            collision(
                &index,
                &body,
                &Point3::from(along.tip),
                &leaning_axis(tilt - 1f64.to_radians(), 0.0),
                &mut s
            )
            .is_some()
        );
        // The ramp keeps the axis turning within the rate on the way in.
        assert!(path.max_rate_deg_mm <= o.max_rate_deg_mm + 1e-6, "{}", path.max_rate_deg_mm);
    }

    #[test]
    fn a_pocket_too_narrow_for_the_holder_is_reported() {
        // A slot 8 mm wide, 50 mm deep between two walls: no tilt within 40° clears the holder
        // at its bottom.
        let left = block([-40.0, -50.0, 0.0], [-4.0, 50.0, 50.0]);
        let right = block([4.0, -50.0, 0.0], [40.0, 50.0, 50.0]);
        let mesh = both(left, right);
        let index = MeshIndex::new(&mesh);
        let body = ToolBody::new(&tool(), 0.01, None);
        let moves = [([0.0, -10.0, 5.0], false), ([0.0, 10.0, 5.0], false)];
        let path =
            clear_path(&index, &body, [0.0, -10.0, 5.0], &moves, &TiltOptions::default(), &any_axis, &never)
                .expect("path");
        assert!(!path.blocked.is_empty());
        assert!(path.points.iter().all(|p| p.blocked));
        assert_eq!(path.blocked[0].part, "holder");
        assert_eq!(path.blocked[0].at_mm, [0.0, -10.0, 5.0]);
    }

    /// Reference of [`first_leans`]: every position in order, upright check then the whole tilt
    /// search after the previous position's lean.
    fn first_leans_in_order(
        index: &MeshIndex,
        body: &ToolBody,
        pts: &[([f64; 3], bool)],
        o: &TiltOptions,
    ) -> Vec<Option<[f64; 2]>> {
        let mut s = Scratch::default();
        let mut prev: Option<Unit<Vector3<f64>>> = None;
        let mut out = Vec::new();
        for &(p, rapid) in pts {
            let tip = Point3::from(p);
            let lean = if collision(index, body, &tip, &Vector3::z_axis(), &mut s).is_none() {
                prev = None;
                Some([0.0, 0.0])
            } else {
                match search_tilt(index, body, &tip, o, prev.as_ref(), &any_axis, &mut s) {
                    Some((tilt, phi)) => {
                        prev = Some(leaning_axis(tilt, phi));
                        Some([tilt * phi.cos(), tilt * phi.sin()])
                    }
                    None => {
                        prev = None;
                        None
                    }
                }
            };
            if rapid {
                prev = None;
            }
            out.push(lean);
        }
        out
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(16))]

        /// The parallel search finds the leans the one-position-at-a-time search finds, along
        /// random paths around random posts.
        #[test]
        fn leans_found_in_parallel_are_those_found_in_order(
            posts in proptest::collection::vec((-30.0f64..30.0, -30.0f64..30.0, 10.0f64..60.0), 1..4),
            path in proptest::collection::vec((-40.0f64..40.0, -40.0f64..40.0, 0.0f64..20.0, proptest::bool::weighted(0.1)), 2..40),
        ) {
            let mut mesh = block([posts[0].0, posts[0].1, 0.0], [posts[0].0 + 6.0, posts[0].1 + 6.0, posts[0].2]);
            for p in &posts[1..] {
                mesh = both(mesh, block([p.0, p.1, 0.0], [p.0 + 6.0, p.1 + 6.0, p.2]));
            }
            let index = MeshIndex::new(&mesh);
            let body = ToolBody::new(&tool(), 0.01, None);
            let o = TiltOptions::default();
            let pts: Vec<([f64; 3], bool)> = path.iter().map(|&(x, y, z, r)| ([x, y, z], r)).collect();
            let FirstLeans { leans: fast, colliding, blocked } =
                first_leans(&index, &body, &pts, &o, &any_axis, &never).expect("leans");
            let slow = first_leans_in_order(&index, &body, &pts, &o);
            prop_assert_eq!(fast.len(), slow.len());
            for (i, (f, s)) in fast.iter().zip(&slow).enumerate() {
                match (f, s) {
                    (Some(f), Some(s)) => prop_assert!((f[0] - s[0]).abs() < 1e-9 && (f[1] - s[1]).abs() < 1e-9, "position {}: {:?} vs {:?}", i, f, s),
                    _ => prop_assert_eq!(f.is_none(), s.is_none(), "position {}", i),
                }
            }
            prop_assert_eq!(blocked.len(), slow.iter().filter(|l| l.is_none()).count());
            prop_assert!(colliding >= blocked.len());
        }
    }

    #[test]
    fn blocked_stretches_are_lifted_over() {
        // Through a slot 8 mm wide and 50 mm long between walls 50 mm tall: the holder cannot
        // reach its middle at any tilt; near its ends it leans out of the way.
        let left = block([-40.0, -25.0, 0.0], [-4.0, 25.0, 50.0]);
        let right = block([4.0, -25.0, 0.0], [40.0, 25.0, 50.0]);
        let mesh = both(left, right);
        let index = MeshIndex::new(&mesh);
        let body = ToolBody::new(&tool(), 0.01, None);
        let o = TiltOptions::default();
        let moves = [([0.0, -60.0, 5.0], false), ([0.0, 60.0, 5.0], false)];
        let path = clear_path(&index, &body, [0.0, -60.0, 5.0], &moves, &o, &any_axis, &never).expect("path");
        assert!(path.points.iter().any(|p| p.blocked));
        let lifted = path.lifted(&index, &body, 70.0, &o, &any_axis);
        assert!(lifted.points.iter().all(|p| !p.blocked));
        // Up at feed, across upright at rapid (the turns from and back to the leans made in place
        // at the clearance height), one crossing per lift (a turn too sharp to make in the slot
        // lifts too).
        let high = |p: &OrientedPoint| (p.tip[2] - 70.0).abs() < 1e-9;
        let across: Vec<usize> = (1..lifted.points.len()).filter(|&i| lifted.points[i].rapid).collect();
        assert!(!across.is_empty());
        for &i in &across {
            let (from, to) = (&lifted.points[i - 1], &lifted.points[i]);
            assert!(high(from) && high(to) && !from.rapid, "{from:?} -> {to:?}");
            assert_eq!((from.axis, to.axis), ([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]), "{from:?} -> {to:?}");
            let (before, after) = (&lifted.points[i - 2], &lifted.points[i + 1]);
            assert_eq!((before.tip, after.tip), (from.tip, to.tip), "the turns are made in place");
            assert!(!after.rapid);
        }
        // Everything kept is clear, the descent included.
        let mut s = Scratch::default();
        for p in &lifted.points {
            let axis = Unit::new_normalize(Vector3::from(p.axis));
            assert!(collision(&index, &body, &Point3::from(p.tip), &axis, &mut s).is_none(), "{p:?}");
        }
        assert_eq!(lifted.blocked.len(), path.blocked.len());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// The grid's candidates miss nothing: on a soup of random triangles, the body at random
        /// tips and axes hits exactly what it hits when every triangle is tested.
        #[test]
        fn the_grid_finds_what_testing_every_triangle_finds(seed in 0u64..1000) {
            use rand::{Rng, SeedableRng};
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            let mut v = Vec::new();
            let mut t = Vec::new();
            for i in 0..200u32 {
                let c = Vector3::new(rng.random_range(-60.0..60.0), rng.random_range(-60.0..60.0), rng.random_range(0.0..60.0));
                for _ in 0..3 {
                    v.push(Point3::from(c + Vector3::new(rng.random_range(-8.0..8.0), rng.random_range(-8.0..8.0), rng.random_range(-8.0..8.0))));
                }
                t.push([3 * i, 3 * i + 1, 3 * i + 2]);
            }
            let mesh = Mesh::new(v, t).expect("mesh");
            let (grid, all) = (MeshIndex::new(&mesh), MeshIndex::unindexed(&mesh));
            let body = ToolBody::new(&tool(), 0.01, Some((60.0, 100.0)));
            let mut s = Scratch::default();
            for _ in 0..50 {
                let tip = Point3::new(rng.random_range(-70.0..70.0), rng.random_range(-70.0..70.0), rng.random_range(-10.0..70.0));
                let axis = leaning_axis(rng.random_range(0.0..0.8), rng.random_range(0.0..std::f64::consts::TAU));
                let a = collision(&grid, &body, &tip, &axis, &mut s);
                let b = collision(&all, &body, &tip, &axis, &mut s);
                prop_assert_eq!(a.map(|h| (h.part, h.depth_mm)), b.map(|h| (h.part, h.depth_mm)));
                prop_assert_eq!(collides(&grid, &body, &tip, &axis, &mut s), a.is_some());
            }
        }
    }

    #[test]
    fn bad_options_and_positions_are_refused() {
        let index = MeshIndex::new(&block([0.0; 3], [1.0; 3]));
        let body = ToolBody::new(&tool(), 0.01, None);
        let o = TiltOptions { max_tilt_deg: 95.0, ..TiltOptions::default() };
        let e = clear_path(&index, &body, [0.0; 3], &[], &o, &any_axis, &never).expect_err("tilt");
        assert!(e.contains("max_tilt_deg 95"), "{e}");
        let e = clear_path(
            &index,
            &body,
            [0.0; 3],
            &[([f64::NAN, 0.0, 0.0], false)],
            &TiltOptions::default(),
            &any_axis,
            &never,
        )
        .expect_err("nan");
        assert!(e.contains("move 1"), "{e}");
        // A stop asked for ends the check at the next question.
        let moves: Vec<([f64; 3], bool)> = (1..=600).map(|i| ([i as f64, 0.0, 5.0], false)).collect();
        let asked = std::sync::atomic::AtomicUsize::new(0);
        let stop = |done: usize, total: usize| {
            assert!(done < total);
            asked.fetch_add(1, std::sync::atomic::Ordering::Relaxed) == 1
        };
        let e = clear_path(&index, &body, [0.0, 0.0, 5.0], &moves, &TiltOptions::default(), &any_axis, &stop)
            .expect_err("stopped");
        assert_eq!(e, STOPPED);
        assert_eq!(asked.load(std::sync::atomic::Ordering::Relaxed), 2);
    }
}

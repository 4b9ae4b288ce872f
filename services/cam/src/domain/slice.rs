//! Slicing a triangle mesh into planar layers: the part's cross-sections at given heights, as
//! closed contours with their holes and nested islands (seed 001's first step: the layers a
//! robot mills pass by pass).
//!
//! # The plane convention (exact vertex and edge handling)
//! A vertex at exactly the slicing height `h` counts as above the plane (`z >= h`): the section
//! is the limit of the sections just below `h`. No vertex is then on the plane, every triangle
//! that crosses it has exactly one vertex alone on its side, and its section is one segment
//! between two crossed edges. A triangle lying in the plane is above it (it adds nothing); an
//! edge in the plane is the segment of the triangle below it. A crossing is computed from the
//! edge's two vertices in index order, so the two triangles sharing an edge compute the same
//! point bit for bit, and a crossing at a vertex is that vertex exactly.
//!
//! # Chaining and orientation
//! A segment runs from the crossing of its triangle's edge that goes from above to below (in the
//! triangle's counter-clockwise order, seen from outside) to the crossing of the edge that goes
//! from below to above: the solid is then on the left, so outer boundaries run counter-clockwise
//! seen from above and holes clockwise. Segments chain through the crossed edges they share
//! (edge keys, not coordinates): on a closed, consistently oriented, 2-manifold mesh every
//! crossed edge ends one segment and starts one, and the chains are closed contours. An edge
//! that starts two segments of a layer (more than two triangles on it, or two neighbours facing
//! opposite ways) is reported as a [`Defect`]; a chain that cannot be continued (the mesh is open
//! there) is kept as an [`OpenChain`] naming the boundary edges it ends on.
//!
//! # Nesting
//! Each closed contour's depth is the number of other contours around it (even-odd test of a
//! point on it); its parent is the smallest one around it. On a well-formed mesh outer
//! boundaries (counter-clockwise) have even depth and holes (clockwise) odd depth; a contour
//! whose orientation disagrees with its depth is reported.
//!
//! # Speed
//! Each triangle finds the range of layers it crosses from its lowest and highest vertex (a
//! binary search in the sorted heights); the (layer, triangle) pairs are bucketed by layer with
//! a counting sort; layers are then cut and chained in parallel, each only over its own
//! triangles. [`slice_reference`] (every triangle against every layer) is the reference.

use depthmill_geometry::Mesh;
use rayon::prelude::*;

/// Most layers one call slices.
pub const MAX_LAYERS: usize = 100_000;

/// Why a mesh could not be sliced.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SliceError {
    #[error("slice levels: {0}")]
    Levels(String),
    #[error("mesh: vertex {index} has a non-finite coordinate ({x}, {y}, {z})")]
    NonFinite { index: usize, x: f64, y: f64, z: f64 },
    #[error("mesh: triangle {triangle} names vertex {index}, but the mesh has {vertices} vertices")]
    Index { triangle: usize, index: u32, vertices: usize },
}

/// An undirected mesh edge by its two vertex indices, smaller first.
pub type Edge = (u32, u32);

/// Whether a contour bounds material (counter-clockwise) or a hole in it (clockwise).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ContourKind {
    Outer,
    Hole,
}

/// A closed contour of a layer.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Contour {
    /// Points in order, the solid on the left; the last joins the first (not repeated).
    pub points: Vec<[f64; 2]>,
    /// Signed area (shoelace), mm²: positive counter-clockwise.
    pub area_mm2: f64,
    pub kind: ContourKind,
    /// Number of other contours around it.
    pub depth: u32,
    /// Index of the smallest contour around it in the layer's `contours`.
    pub parent: Option<usize>,
}

/// A chain of segments that does not close: the mesh is open along the edges it ends on.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct OpenChain {
    pub points: Vec<[f64; 2]>,
    /// The edge the chain starts on (no segment of the layer ends there) and the one it ends on.
    pub start_edge: Edge,
    pub end_edge: Edge,
}

/// What is wrong with the mesh where a layer crosses it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Defect {
    /// The layer's height.
    pub z_mm: f64,
    /// The mesh edge (vertex indices) where the chaining found it, and where the layer is.
    pub edge: Option<Edge>,
    pub at: [f64; 2],
    pub message: String,
}

/// One layer's section.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Layer {
    pub z_mm: f64,
    pub contours: Vec<Contour>,
    pub open: Vec<OpenChain>,
    pub defects: Vec<Defect>,
}

impl Layer {
    /// Net area of the section (outer areas minus holes), mm².
    pub fn area_mm2(&self) -> f64 {
        self.contours.iter().map(|c| c.area_mm2).sum()
    }
}

/// `n` heights from `z0` in steps of `step` (`z0 + i·step`).
pub fn levels(z0: f64, step: f64, n: usize) -> Result<Vec<f64>, SliceError> {
    if !(z0.is_finite() && step.is_finite() && step > 0.0) {
        return Err(SliceError::Levels(format!("start {z0} and step {step}: need finite values, step > 0")));
    }
    if n == 0 || n > MAX_LAYERS {
        return Err(SliceError::Levels(format!("{n} layers: need 1 to {MAX_LAYERS}")));
    }
    Ok((0..n).map(|i| z0 + i as f64 * step).collect())
}

fn check(mesh: &Mesh, levels: &[f64]) -> Result<(), SliceError> {
    if levels.is_empty() || levels.len() > MAX_LAYERS {
        return Err(SliceError::Levels(format!("{} layers: need 1 to {MAX_LAYERS}", levels.len())));
    }
    if let Some((i, z)) = levels.iter().enumerate().find(|(_, z)| !z.is_finite()) {
        return Err(SliceError::Levels(format!("level {i} is {z}: heights must be finite")));
    }
    if let Some(i) = levels.windows(2).position(|w| w[1] <= w[0]) {
        return Err(SliceError::Levels(format!(
            "level {} ({}) is not above level {i} ({}): heights must increase",
            i + 1,
            levels[i + 1],
            levels[i]
        )));
    }
    if let Some((index, p)) =
        mesh.vertices.iter().enumerate().find(|(_, p)| !p.coords.iter().all(|c| c.is_finite()))
    {
        return Err(SliceError::NonFinite { index, x: p.x, y: p.y, z: p.z });
    }
    let n = mesh.vertices.len();
    if let Some((triangle, &index)) = mesh
        .triangles
        .iter()
        .enumerate()
        .find_map(|(t, tri)| tri.iter().find(|&&i| i as usize >= n).map(|i| (t, i)))
    {
        return Err(SliceError::Index { triangle, index, vertices: n });
    }
    Ok(())
}

/// Slices `mesh` at each of `levels` (strictly increasing, finite). See the module docs.
///
/// Errors: bad levels, a non-finite vertex, a triangle naming a missing vertex.
pub fn slice(mesh: &Mesh, levels: &[f64]) -> Result<Vec<Layer>, SliceError> {
    check(mesh, levels)?;
    let v = &mesh.vertices;
    // The layers each triangle crosses: zmin < h <= zmax.
    let ranges: Vec<(u32, u32)> = mesh
        .triangles
        .par_iter()
        .map(|t| {
            let z = [v[t[0] as usize].z, v[t[1] as usize].z, v[t[2] as usize].z];
            let (lo, hi) = (z[0].min(z[1]).min(z[2]), z[0].max(z[1]).max(z[2]));
            let first = levels.partition_point(|&l| l <= lo);
            let end = levels.partition_point(|&l| l <= hi);
            (first as u32, end.max(first) as u32)
        })
        .collect();
    let mut start = vec![0usize; levels.len() + 1];
    for &(a, b) in &ranges {
        for l in a..b {
            start[l as usize + 1] += 1;
        }
    }
    for i in 0..levels.len() {
        start[i + 1] += start[i];
    }
    let mut fill = start.clone();
    let mut tris = vec![0u32; start[levels.len()]];
    for (t, &(a, b)) in ranges.iter().enumerate() {
        for l in a..b {
            tris[fill[l as usize]] = t as u32;
            fill[l as usize] += 1;
        }
    }
    Ok(levels
        .par_iter()
        .enumerate()
        .map(|(l, &h)| {
            let segments: Vec<Segment> = tris[start[l]..start[l + 1]]
                .iter()
                .filter_map(|&t| segment(mesh, mesh.triangles[t as usize], h))
                .collect();
            chain(h, segments)
        })
        .collect())
}

/// The reference: every triangle against every layer, then the same chaining.
pub fn slice_reference(mesh: &Mesh, levels: &[f64]) -> Result<Vec<Layer>, SliceError> {
    check(mesh, levels)?;
    Ok(levels
        .iter()
        .map(|&h| {
            let segments: Vec<Segment> = mesh.triangles.iter().filter_map(|&t| segment(mesh, t, h)).collect();
            chain(h, segments)
        })
        .collect())
}

/// One triangle's section: from the crossing on `from` to the crossing on `to`.
#[derive(Debug, Clone, Copy)]
struct Segment {
    from: Edge,
    to: Edge,
    a: [f64; 2],
    b: [f64; 2],
}

fn key(e: Edge) -> u64 {
    (u64::from(e.0) << 32) | u64::from(e.1)
}

/// Where the plane `z = h` crosses the edge `u`-`v` (one vertex below, one at or above),
/// computed in index order so both triangles on the edge get the same point; a vertex at `h`
/// is returned exactly.
fn crossing(mesh: &Mesh, u: u32, v: u32, h: f64) -> (Edge, [f64; 2]) {
    let (i, j) = if u < v { (u, v) } else { (v, u) };
    let (p, q) = (&mesh.vertices[i as usize], &mesh.vertices[j as usize]);
    let at = if p.z == h {
        [p.x, p.y]
    } else if q.z == h {
        [q.x, q.y]
    } else {
        let t = (h - p.z) / (q.z - p.z);
        [p.x + t * (q.x - p.x), p.y + t * (q.y - p.y)]
    };
    ((i, j), at)
}

fn segment(mesh: &Mesh, t: [u32; 3], h: f64) -> Option<Segment> {
    let above = t.map(|i| mesh.vertices[i as usize].z >= h);
    let (mut from, mut to) = (None, None);
    for k in 0..3 {
        let (u, w) = (t[k], t[(k + 1) % 3]);
        match (above[k], above[(k + 1) % 3]) {
            (true, false) => from = Some(crossing(mesh, u, w, h)),
            (false, true) => to = Some(crossing(mesh, u, w, h)),
            _ => {}
        }
    }
    let ((fe, a), (te, b)) = (from?, to?);
    Some(Segment { from: fe, to: te, a, b })
}

/// Chains one layer's segments into contours and open chains, and nests the contours.
fn chain(h: f64, segs: Vec<Segment>) -> Layer {
    let mut defects = Vec::new();
    // Segments by the edge they start on.
    let mut by_start: Vec<(u64, u32)> =
        segs.iter().enumerate().map(|(i, s)| (key(s.from), i as u32)).collect();
    by_start.sort_unstable();
    for w in by_start.windows(2) {
        if w[0].0 == w[1].0 {
            let s = &segs[w[1].1 as usize];
            defects.push(Defect {
                z_mm: h,
                edge: Some(s.from),
                at: s.a,
                message: "the edge starts two sections: more than two triangles share it, or two \
                          neighbours on it face opposite ways"
                    .into(),
            });
        }
    }
    let next_of = |s: &Segment| -> Option<u32> {
        let k = key(s.to);
        let i = by_start.partition_point(|&(x, _)| x < k);
        by_start.get(i).filter(|&&(x, _)| x == k).map(|&(_, j)| j)
    };
    let mut has_pred = vec![false; segs.len()];
    let next: Vec<Option<u32>> = segs.iter().map(next_of).collect();
    for n in next.iter().flatten() {
        has_pred[*n as usize] = true;
    }
    let mut used = vec![false; segs.len()];
    let push = |pts: &mut Vec<[f64; 2]>, p: [f64; 2]| {
        if pts.last() != Some(&p) {
            pts.push(p);
        }
    };
    let mut open = Vec::new();
    let mut closed: Vec<Vec<[f64; 2]>> = Vec::new();
    // Open chains first, from the segments nothing leads into; then the cycles.
    let starts: Vec<usize> = (0..segs.len()).filter(|&i| !has_pred[i]).chain(0..segs.len()).collect();
    for s0 in starts {
        if used[s0] {
            continue;
        }
        let mut pts = Vec::new();
        let mut cur = s0;
        let is_cycle = has_pred[s0];
        loop {
            used[cur] = true;
            push(&mut pts, segs[cur].a);
            match next[cur] {
                Some(n) if n as usize == s0 && is_cycle => break,
                Some(n) if !used[n as usize] => cur = n as usize,
                _ => {
                    // No way on: open (or led into a chain already taken, a defect above).
                    push(&mut pts, segs[cur].b);
                    open.push(OpenChain { points: pts, start_edge: segs[s0].from, end_edge: segs[cur].to });
                    pts = Vec::new();
                    break;
                }
            }
        }
        if !pts.is_empty() {
            let pts = without_spikes(pts);
            if pts.len() >= 3 && signed_area(&pts) != 0.0 {
                closed.push(pts);
            }
        }
    }
    let open = join_open(h, open, &mut closed, &mut defects);
    cancel_opposite_pairs(&mut closed);
    let contours = nest(h, closed, &mut defects);
    Layer { z_mm: h, contours, open, defects }
}

/// Joins open chains whose ends meet at the same point (to 1e-9 mm and 1e-12 relative): the
/// mark of a mesh whose reader dropped a zero-area triangle (its three collinear edges are then
/// used once each) or that has a crack of no width. A chain that closes becomes a contour, with a
/// [`Defect`] naming the edges it was closed across; chains whose ends meet nothing stay open.
fn join_open(
    h: f64,
    mut chains: Vec<OpenChain>,
    closed: &mut Vec<Vec<[f64; 2]>>,
    defects: &mut Vec<Defect>,
) -> Vec<OpenChain> {
    let near = |p: [f64; 2], q: [f64; 2]| {
        (p[0] - q[0]).hypot(p[1] - q[1]) <= 1e-9 + 1e-12 * p[0].abs().max(p[1].abs())
    };
    let first = |c: &OpenChain| c.points.first().copied().unwrap_or([f64::NAN; 2]);
    let last = |c: &OpenChain| c.points.last().copied().unwrap_or([f64::NAN; 2]);
    loop {
        if let Some(i) = chains.iter().position(|c| c.points.len() >= 3 && near(last(c), first(c))) {
            let c = chains.swap_remove(i);
            let gap = (last(&c)[0] - first(&c)[0]).hypot(last(&c)[1] - first(&c)[1]);
            defects.push(Defect {
                z_mm: h,
                edge: Some(c.end_edge),
                at: first(&c),
                message: format!(
                    "closed across a gap of {gap:.1e} mm between edges {:?} and {:?}: a degenerate or missing triangle",
                    c.end_edge, c.start_edge
                ),
            });
            let mut pts = c.points;
            pts.pop();
            closed.push(without_spikes(pts));
            continue;
        }
        let pair = (0..chains.len()).find_map(|i| {
            (0..chains.len()).find(|&j| j != i && near(last(&chains[i]), first(&chains[j]))).map(|j| (i, j))
        });
        let Some((i, j)) = pair else { break };
        let tail = chains[j].clone();
        let head = &mut chains[i];
        head.points.extend(tail.points.iter().skip(1).copied());
        head.end_edge = tail.end_edge;
        chains.remove(j);
    }
    chains
}

/// A closed contour without the back-and-forth steps a layer through a ridge or a knife edge
/// at exactly its height leaves (`a, b, a`: the zero-width limit of the section just below).
fn without_spikes(pts: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    let mut out: Vec<[f64; 2]> = Vec::with_capacity(pts.len());
    for p in pts {
        if out.len() >= 2 && out[out.len() - 2] == p {
            out.pop();
        } else if out.last() != Some(&p) {
            out.push(p);
        }
    }
    // Across the seam: the last point equal to the first, or a spike at either end.
    loop {
        let n = out.len();
        // The last point repeats the first, or is a spike's tip between the one before it and
        // the first.
        if (n >= 2 && out[0] == out[n - 1]) || (n >= 3 && out[n - 2] == out[0]) {
            out.pop();
        } else if n >= 3 && out[1] == out[n - 1] {
            out.remove(0);
            out.pop();
        } else {
            break;
        }
    }
    out
}

/// Drops pairs of contours that run through the same points in opposite directions (a ring of
/// zero width: a closed ridge exactly at the layer's height).
fn cancel_opposite_pairs(closed: &mut Vec<Vec<[f64; 2]>>) {
    let canon = |p: &[[f64; 2]], reverse: bool| -> Vec<[u64; 2]> {
        let mut q: Vec<[u64; 2]> = p.iter().map(|a| [a[0].to_bits(), a[1].to_bits()]).collect();
        if reverse {
            q.reverse();
        }
        let first = (0..q.len()).min_by_key(|&i| q[i]).unwrap_or(0);
        q.rotate_left(first);
        q
    };
    let keys: Vec<(Vec<[u64; 2]>, bool)> = closed
        .iter()
        .map(|p| {
            let ccw = signed_area(p) > 0.0;
            (canon(p, !ccw), ccw)
        })
        .collect();
    let mut drop = vec![false; closed.len()];
    for i in 0..closed.len() {
        if drop[i] {
            continue;
        }
        if let Some(j) =
            (i + 1..closed.len()).find(|&j| !drop[j] && keys[j].1 != keys[i].1 && keys[j].0 == keys[i].0)
        {
            drop[i] = true;
            drop[j] = true;
        }
    }
    let mut k = 0;
    closed.retain(|_| {
        k += 1;
        !drop[k - 1]
    });
}

/// Signed area of the closed polygon `p` (shoelace), positive counter-clockwise.
pub(crate) fn signed_area(p: &[[f64; 2]]) -> f64 {
    let n = p.len();
    0.5 * (0..n)
        .map(|i| {
            let (a, b) = (p[i], p[(i + 1) % n]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum::<f64>()
}

/// Even-odd test of `q` against the closed polygon `p`.
pub(crate) fn contains(p: &[[f64; 2]], q: [f64; 2]) -> bool {
    let mut inside = false;
    let n = p.len();
    let Some(mut j) = n.checked_sub(1) else { return false };
    for i in 0..n {
        let (a, b) = (p[i], p[j]);
        if (a[1] > q[1]) != (b[1] > q[1]) {
            let x = a[0] + (q[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
            if q[0] < x {
                inside = !inside;
            }
        }
        j = i;
    }
    inside
}

/// The box of the points `p`: `[x_min, y_min, x_max, y_max]` (infinite the wrong way round when
/// `p` is empty).
pub(crate) fn bounds(p: &[[f64; 2]]) -> [f64; 4] {
    p.iter().fold([f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY], |b, q| {
        [b[0].min(q[0]), b[1].min(q[1]), b[2].max(q[0]), b[3].max(q[1])]
    })
}

fn nest(h: f64, closed: Vec<Vec<[f64; 2]>>, defects: &mut Vec<Defect>) -> Vec<Contour> {
    let areas: Vec<f64> = closed.iter().map(|p| signed_area(p)).collect();
    let boxes: Vec<[f64; 4]> = closed.iter().map(|p| bounds(p)).collect();
    // A point just inside each contour's own region: a millionth of its longest edge off the
    // edge's middle, towards the side the contour encloses (left of a counter-clockwise one).
    // Not a vertex another contour may touch, nor a point on an edge another contour shares.
    let probes: Vec<[f64; 2]> = closed
        .iter()
        .zip(&areas)
        .map(|(p, &area)| {
            let n = p.len();
            let len = |k: usize| {
                let (a, b) = (p[k], p[(k + 1) % n]);
                (b[0] - a[0]).hypot(b[1] - a[1])
            };
            let i = (0..n).max_by(|&i, &j| len(i).total_cmp(&len(j))).unwrap_or(0);
            let (a, b) = (p[i], p[(i + 1) % n]);
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let side = if area >= 0.0 { 1e-6 } else { -1e-6 };
            [0.5 * (a[0] + b[0]) - side * dy, 0.5 * (a[1] + b[1]) + side * dx]
        })
        .collect();
    let mut out: Vec<Contour> = Vec::with_capacity(closed.len());
    for (i, pts) in closed.iter().enumerate() {
        let q = probes[i];
        let mut depth = 0u32;
        let mut parent: Option<usize> = None;
        for (j, other) in closed.iter().enumerate() {
            let b = boxes[j];
            if j == i || q[0] < b[0] || q[0] > b[2] || q[1] < b[1] || q[1] > b[3] {
                continue;
            }
            if areas[j].abs() > areas[i].abs() * (1.0 - 1e-12) && contains(other, q) {
                depth += 1;
                if parent.is_none_or(|p| areas[j].abs() < areas[p].abs()) {
                    parent = Some(j);
                }
            }
        }
        let kind = if areas[i] >= 0.0 { ContourKind::Outer } else { ContourKind::Hole };
        if (kind == ContourKind::Outer) != depth.is_multiple_of(2) {
            defects.push(Defect {
                z_mm: h,
                edge: None,
                at: q,
                message: format!(
                    "a {} contour inside {depth} other(s): the mesh's faces are not consistently oriented outward there",
                    if kind == ContourKind::Outer { "counter-clockwise (outer)" } else { "clockwise (hole)" }
                ),
            });
        }
        out.push(Contour { points: pts.clone(), area_mm2: areas[i], kind, depth, parent });
    }
    out
}

/// Edges of a mesh that a closed, consistently oriented 2-manifold would not have.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Topology {
    /// Edges used by one triangle only (the mesh is open there).
    pub boundary: Vec<Edge>,
    /// Edges used by more than two triangles.
    pub non_manifold: Vec<Edge>,
    /// Edges whose two triangles run them the same way (neighbours facing opposite ways).
    pub misoriented: Vec<Edge>,
}

impl Topology {
    pub fn is_closed_manifold(&self) -> bool {
        self.boundary.is_empty() && self.non_manifold.is_empty() && self.misoriented.is_empty()
    }
}

/// Checks every edge of `mesh` (by vertex index: weld coincident vertices first, as the STL
/// reader does).
pub fn topology(mesh: &Mesh) -> Topology {
    // (edge key, +1 when run from the smaller index to the larger, -1 otherwise).
    let mut half: Vec<(u64, i8)> = mesh
        .triangles
        .par_iter()
        .flat_map_iter(|t| {
            (0..3).map(move |k| {
                let (u, v) = (t[k], t[(k + 1) % 3]);
                if u < v { (key((u, v)), 1i8) } else { (key((v, u)), -1i8) }
            })
        })
        .collect();
    half.par_sort_unstable();
    let mut out = Topology::default();
    let mut i = 0;
    while i < half.len() {
        let k = half[i].0;
        let mut j = i;
        let mut sum = 0i32;
        while j < half.len() && half[j].0 == k {
            sum += i32::from(half[j].1);
            j += 1;
        }
        let edge = ((k >> 32) as u32, k as u32);
        match j - i {
            1 => out.boundary.push(edge),
            2 if sum != 0 => out.misoriented.push(edge),
            2 => {}
            _ => out.non_manifold.push(edge),
        }
        i = j;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use depthmill_geometry::nalgebra::Point3;
    use proptest::prelude::*;

    /// A closed block whose top is the height field `z[j][i]` over a unit grid (`nx` x `ny`
    /// cells) and whose bottom is at 0: top and bottom grids, four walls, faces outward.
    fn terrain(nx: usize, ny: usize, z: &[f64]) -> Mesh {
        let mut v = Vec::new();
        let top = |i: usize, j: usize| (j * (nx + 1) + i) as u32;
        let nt = (nx + 1) * (ny + 1);
        let bot = |i: usize, j: usize| (nt + j * (nx + 1) + i) as u32;
        for j in 0..=ny {
            for i in 0..=nx {
                v.push(Point3::new(i as f64, j as f64, z[j * (nx + 1) + i]));
            }
        }
        for j in 0..=ny {
            for i in 0..=nx {
                v.push(Point3::new(i as f64, j as f64, 0.0));
            }
        }
        let mut t = Vec::new();
        for j in 0..ny {
            for i in 0..nx {
                t.push([top(i, j), top(i + 1, j), top(i + 1, j + 1)]);
                t.push([top(i, j), top(i + 1, j + 1), top(i, j + 1)]);
                t.push([bot(i, j), bot(i + 1, j + 1), bot(i + 1, j)]);
                t.push([bot(i, j), bot(i, j + 1), bot(i + 1, j + 1)]);
            }
        }
        // The boundary counter-clockwise seen from above.
        let mut ring = Vec::new();
        ring.extend((0..nx).map(|i| (i, 0)));
        ring.extend((0..ny).map(|j| (nx, j)));
        ring.extend((1..=nx).rev().map(|i| (i, ny)));
        ring.extend((1..=ny).rev().map(|j| (0, j)));
        for k in 0..ring.len() {
            let (a, b) = (ring[k], ring[(k + 1) % ring.len()]);
            t.push([bot(a.0, a.1), bot(b.0, b.1), top(b.0, b.1)]);
            t.push([bot(a.0, a.1), top(b.0, b.1), top(a.0, a.1)]);
        }
        Mesh { vertices: v, triangles: t }
    }

    /// The height of the terrain's top at `(x, y)` (the same triangulation).
    fn terrain_top(nx: usize, z: &[f64], x: f64, y: f64) -> f64 {
        let (i, j) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = (x - i as f64, y - j as f64);
        let h = |i: usize, j: usize| z[j * (nx + 1) + i];
        if fx >= fy {
            // Triangle (0,0) (1,0) (1,1).
            h(i, j) + fx * (h(i + 1, j) - h(i, j)) + fy * (h(i + 1, j + 1) - h(i + 1, j))
        } else {
            // Triangle (0,0) (1,1) (0,1).
            h(i, j) + fy * (h(i, j + 1) - h(i, j)) + fx * (h(i + 1, j + 1) - h(i, j + 1))
        }
    }

    /// An axis-aligned box, faces outward (or inward: a cavity).
    fn cuboid(mesh: &mut Mesh, lo: [f64; 3], hi: [f64; 3], inward: bool) {
        let o = mesh.vertices.len() as u32;
        for k in 0..8 {
            mesh.vertices.push(Point3::new(
                if k & 1 == 0 { lo[0] } else { hi[0] },
                if k & 2 == 0 { lo[1] } else { hi[1] },
                if k & 4 == 0 { lo[2] } else { hi[2] },
            ));
        }
        let faces = [
            [0, 2, 3, 1], // bottom (-z)
            [4, 5, 7, 6], // top (+z)
            [0, 1, 5, 4], // -y
            [2, 6, 7, 3], // +y
            [0, 4, 6, 2], // -x
            [1, 3, 7, 5], // +x
        ];
        for f in faces {
            let (a, b, c, d) = (o + f[0], o + f[1], o + f[2], o + f[3]);
            for tri in [[a, b, c], [a, c, d]] {
                mesh.triangles.push(if inward { [tri[0], tri[2], tri[1]] } else { tri });
            }
        }
    }

    fn torus(nu: usize, nv: usize, big: f64, small: f64) -> Mesh {
        use std::f64::consts::TAU;
        let mut v = Vec::new();
        for i in 0..nu {
            for j in 0..nv {
                let (u, w) = (TAU * i as f64 / nu as f64, TAU * j as f64 / nv as f64);
                let r = big + small * w.cos();
                v.push(Point3::new(r * u.cos(), r * u.sin(), small * w.sin()));
            }
        }
        let id = |i: usize, j: usize| ((i % nu) * nv + (j % nv)) as u32;
        let mut t = Vec::new();
        for i in 0..nu {
            for j in 0..nv {
                t.push([id(i, j), id(i + 1, j), id(i + 1, j + 1)]);
                t.push([id(i, j), id(i + 1, j + 1), id(i, j + 1)]);
            }
        }
        Mesh { vertices: v, triangles: t }
    }

    fn inside(layer: &Layer, q: [f64; 2]) -> bool {
        layer.contours.iter().filter(|c| contains(&c.points, q)).count() % 2 == 1
    }

    #[test]
    fn a_box_with_a_cavity_and_an_island_nests_three_contours() {
        let mut m = Mesh { vertices: Vec::new(), triangles: Vec::new() };
        cuboid(&mut m, [0.0; 3], [10.0; 3], false);
        cuboid(&mut m, [2.0; 3], [8.0; 3], true);
        cuboid(&mut m, [4.0, 4.0, 3.0], [6.0, 6.0, 7.0], false);
        assert!(topology(&m).is_closed_manifold());
        let layers = slice(&m, &[5.0]).expect("slices");
        let l = &layers[0];
        assert!(l.open.is_empty() && l.defects.is_empty(), "{l:?}");
        let mut c = l.contours.clone();
        c.sort_by(|a, b| b.area_mm2.abs().total_cmp(&a.area_mm2.abs()));
        assert_eq!(
            c.iter().map(|c| c.kind).collect::<Vec<_>>(),
            [ContourKind::Outer, ContourKind::Hole, ContourKind::Outer]
        );
        assert_eq!(c.iter().map(|c| c.depth).collect::<Vec<_>>(), [0, 1, 2]);
        assert!((c[0].area_mm2 - 100.0).abs() < 1e-12 && (c[1].area_mm2 + 36.0).abs() < 1e-12);
        assert!((c[2].area_mm2 - 4.0).abs() < 1e-12);
        assert!((l.area_mm2() - 68.0).abs() < 1e-12);
        // The island's parent is the hole, the hole's the outer boundary.
        let idx = |a: f64| l.contours.iter().position(|k| (k.area_mm2 - a).abs() < 1e-9);
        assert_eq!(l.contours[idx(4.0).expect("island")].parent, idx(-36.0));
        assert_eq!(l.contours[idx(-36.0).expect("hole")].parent, idx(100.0));
        // At a face's height the section is the one just below it: at z = 10 (the top) the full
        // square; at z = 8 (the cavity's roof) the square with the hole; at 0
        // (the bottom) nothing. (The island ends at 7.)
        let at = slice(&m, &[0.0, 8.0, 10.0]).expect("slices");
        assert!(at[0].contours.is_empty());
        assert!((at[1].area_mm2() - 64.0).abs() < 1e-12, "{:?}", at[1].area_mm2());
        assert!((at[2].area_mm2() - 100.0).abs() < 1e-12);
    }

    #[test]
    fn a_torus_gives_a_ring() {
        let m = torus(64, 32, 5.0, 2.0);
        assert!(topology(&m).is_closed_manifold());
        for z in [0.0, 1.0, -1.5] {
            let l = &slice(&m, &[z]).expect("slices")[0];
            assert!(l.open.is_empty() && l.defects.is_empty(), "z {z}: {l:?}");
            assert_eq!(l.contours.len(), 2, "z {z}");
            let outer = l.contours.iter().find(|c| c.kind == ContourKind::Outer).expect("outer");
            let hole = l.contours.iter().find(|c| c.kind == ContourKind::Hole).expect("hole");
            assert_eq!((outer.depth, hole.depth), (0, 1));
            // Radii of the section's circles: 5 ± sqrt(4 - z²), within the facets' sag.
            let w = (4.0 - z * z).sqrt();
            let area = std::f64::consts::PI * ((5.0 + w).powi(2) - (5.0 - w).powi(2));
            assert!((l.area_mm2() - area).abs() < 0.03 * area, "z {z}: {} vs {area}", l.area_mm2());
        }
    }

    #[test]
    fn open_non_manifold_and_misoriented_meshes_are_reported_with_their_edges() {
        let z: Vec<f64> = (0..16).map(|k| 1.0 + 0.25 * f64::from(k % 5)).collect();
        let whole = terrain(3, 3, &z);
        assert!(topology(&whole).is_closed_manifold());
        // A wall triangle removed: open along its three edges; a layer through it has an open
        // chain ending on two of them.
        let wall = whole.triangles.len() - 2;
        let mut open = whole.clone();
        let gone = open.triangles.remove(wall);
        let topo = topology(&open);
        assert_eq!(topo.boundary.len(), 3, "{topo:?}");
        let l = &slice(&open, &[0.5]).expect("slices")[0];
        assert_eq!(l.open.len(), 1, "{l:?}");
        let edges: Vec<Edge> =
            (0..3).map(|k| (gone[k].min(gone[(k + 1) % 3]), gone[k].max(gone[(k + 1) % 3]))).collect();
        assert!(edges.contains(&l.open[0].start_edge) && edges.contains(&l.open[0].end_edge), "{l:?}");
        // A triangle twice: three triangles on each of its edges.
        let mut doubled = whole.clone();
        doubled.triangles.push(whole.triangles[wall]);
        assert_eq!(topology(&doubled).non_manifold.len(), 3);
        assert!(!slice(&doubled, &[0.5]).expect("slices")[0].defects.is_empty());
        // A wall triangle flipped: its edges run the same way as its neighbours'.
        let mut flipped = whole.clone();
        let t = &mut flipped.triangles[wall];
        t.swap(1, 2);
        assert_eq!(topology(&flipped).misoriented.len(), 3);
        let l = &slice(&flipped, &[0.5]).expect("slices")[0];
        assert!(!l.defects.is_empty() || !l.open.is_empty(), "{l:?}");
    }

    #[test]
    fn a_crack_of_no_width_is_closed_and_reported() {
        // A cube whose edge (0,0,0)-(0,0,10) is split at (0,0,5) on one face only: what a
        // reader leaves after dropping the zero-area triangle that closed the seam.
        let mut m = Mesh { vertices: Vec::new(), triangles: Vec::new() };
        cuboid(&mut m, [0.0; 3], [10.0; 3], false);
        m.vertices.push(Point3::new(0.0, 0.0, 5.0));
        let k = m.triangles.iter().position(|t| *t == [0, 4, 6]).expect("the -x face's triangle");
        m.triangles[k] = [0, 8, 6];
        m.triangles.push([8, 4, 6]);
        let topo = topology(&m);
        assert_eq!(topo.boundary, vec![(0, 4), (0, 8), (4, 8)]);
        for z in [3.0, 7.0] {
            let l = &slice(&m, &[z]).expect("slices")[0];
            assert!(l.open.is_empty(), "{l:?}");
            assert_eq!(l.contours.len(), 1);
            assert!((l.area_mm2() - 100.0).abs() < 1e-9);
            assert_eq!(l.defects.len(), 1);
            assert!(l.defects[0].message.starts_with("closed across a gap of 0.0e0 mm"), "{:?}", l.defects);
        }
    }

    #[test]
    fn bad_levels_and_vertices_are_refused_with_what_is_wrong() {
        let m = torus(8, 8, 5.0, 2.0);
        assert!(matches!(slice(&m, &[]), Err(SliceError::Levels(_))));
        let e = slice(&m, &[0.0, 1.0, 1.0]).expect_err("not increasing");
        assert!(e.to_string().contains("level 2 (1) is not above level 1 (1)"), "{e}");
        assert!(slice(&m, &[f64::NAN]).expect_err("nan").to_string().contains("level 0 is NaN"));
        assert!(levels(0.0, 0.0, 3).is_err() && levels(0.0, 1.0, 0).is_err());
        assert!(levels(0.0, 1.0, MAX_LAYERS + 1).is_err());
        let mut bad = m.clone();
        bad.vertices[5].z = f64::INFINITY;
        assert!(matches!(slice(&bad, &[0.0]), Err(SliceError::NonFinite { index: 5, .. })));
        let mut bad = m;
        bad.triangles[3][1] = 10_000;
        assert!(matches!(slice(&bad, &[0.0]), Err(SliceError::Index { triangle: 3, index: 10_000, .. })));
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

        /// Random closed blocks with heights on the 0.25 mm grid (vertices, edges and flats at
        /// the layers' heights): the bucketed slicer equals the every-triangle reference; every
        /// contour closes; and a point is inside the section exactly when the block's top is
        /// above the layer there (the block's own definition).
        #[test]
        fn sections_of_random_blocks_match_the_height_field(
            nx in 1usize..7,
            ny in 1usize..7,
            steps in proptest::collection::vec(1u8..12, 64),
            probes in proptest::collection::vec((0.001f64..0.999, 0.001f64..0.999), 40),
        ) {
            let z: Vec<f64> = (0..(nx + 1) * (ny + 1)).map(|k| 0.25 * f64::from(steps[k % steps.len()])).collect();
            let m = terrain(nx, ny, &z);
            prop_assert!(topology(&m).is_closed_manifold());
            let lv = levels(0.125, 0.125, 24).expect("levels");
            let fast = slice(&m, &lv).expect("slices");
            let slow = slice_reference(&m, &lv).expect("slices");
            prop_assert_eq!(&fast, &slow);
            for l in &fast {
                prop_assert!(l.open.is_empty() && l.defects.is_empty(), "{:?}", l);
                for &(fx, fy) in &probes {
                    let (x, y) = (fx * nx as f64, fy * ny as f64);
                    let top = terrain_top(nx, &z, x, y);
                    if (top - l.z_mm).abs() < 1e-6 {
                        continue;
                    }
                    prop_assert_eq!(inside(l, [x, y]), top > l.z_mm, "z {} at ({}, {}): top {}", l.z_mm, x, y, top);
                }
            }
        }
    }
}

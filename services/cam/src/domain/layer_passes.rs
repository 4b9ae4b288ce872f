//! Passes of one layer of a sliced part (seed 001): the tool-centre rings that take the layer's
//! material off from the stock boundary in to the part, pass by pass at a radial depth.
//!
//! The part's section `P` (a [`Layer`]'s contours: outer boundaries counter-clockwise, holes
//! clockwise) is offset outward by `d_k = r + k·a_e` for `k = K, …, 1, 0` (`r` the tool radius,
//! `a_e` the radial depth of cut): ring `k` is where the tool centre runs to take material from
//! `d_k − r` to `d_k + r` off the part; ring 0 is the finishing contour, the tool touching the
//! part. `K` is the smallest count whose outermost ring reaches the stock's farthest corner
//! (`d_K + r >= D`, `D` the largest distance from the part to a stock corner). Each ring is kept
//! only where it passes over stock (within `r` of the stock rectangle): the parts in the air are
//! cut out, leaving open pieces.
//!
//! Offsetting is i_overlay's (round joins, the arc tolerance given): against clipper2-rust, the
//! other pure-Rust offsetter considered, it is 12-15x faster on many contours in one call, exact
//! to 1e-9 mm inward where clipper2-rust's port rounds to its 1e-6 grid, and scales linearly where
//! the port took 38 s for 10 000 contours (`cargo bench -p depthmill-cam --bench offset`).
//!
//! Holes of the part the tool cannot enter (narrower than its diameter, so ring 0 has no hole
//! inside them) are reported with where they are, not silently skipped.

use i_overlay::mesh::float::outline::offset::OutlineOffset;
use i_overlay::mesh::float::style::{LineJoin, OutlineStyle};

use depthmill_geometry::Mesh;

use super::slice::{
    ContourKind, Layer, MAX_LAYERS, SliceError, bounds, contains, levels, signed_area as area, slice,
};

/// A 2-D polyline (or closed loop), mm.
pub type Polyline2 = Vec<[f64; 2]>;

/// Most rings of one layer.
pub const MAX_RINGS: usize = 10_000;

/// Why a layer's passes could not be planned.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PassError {
    #[error("{field} {value}: {reason}")]
    Invalid { field: &'static str, value: f64, reason: String },
    #[error(transparent)]
    Slice(#[from] SliceError),
}

/// What a layer is cut with, and from.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PassOptions {
    pub tool_radius_mm: f64,
    /// Radial depth of cut between rings, at most the tool's diameter.
    pub radial_depth_mm: f64,
    /// Largest chord error of the rings' round corners.
    pub arc_tolerance_mm: f64,
    /// The stock's rectangle in the layer's plane: `[x_min, y_min, x_max, y_max]`.
    pub stock: [f64; 4],
}

/// One ring: where the tool centre runs at `offset_mm` from the part.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Ring {
    pub offset_mm: f64,
    /// Closed loops (the last point joins the first) where the whole ring passes over stock.
    pub loops: Vec<Vec<[f64; 2]>>,
    /// Open pieces where the ring was cut to the stock.
    pub pieces: Vec<Vec<[f64; 2]>>,
}

/// A hole of the part the tool does not enter.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Unreached {
    /// A point inside the hole and the hole's area.
    pub at: [f64; 2],
    pub area_mm2: f64,
}

/// A layer's rings, outermost first (the last is the finishing contour).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LayerPasses {
    pub z_mm: f64,
    pub rings: Vec<Ring>,
    pub unreached: Vec<Unreached>,
}

fn invalid(field: &'static str, value: f64, reason: impl Into<String>) -> PassError {
    PassError::Invalid { field, value, reason: reason.into() }
}

/// The part's section offset outward by `d` (round joins within `tol`): oriented contours,
/// outer boundaries counter-clockwise.
pub fn offset(contours: &[Vec<[f64; 2]>], d: f64, tol: f64) -> Vec<Vec<[f64; 2]>> {
    if contours.is_empty() {
        return Vec::new();
    }
    if d <= 0.0 {
        return contours.to_vec();
    }
    // A hole whose box is at most 2d across on its narrow side has an inscribed circle of
    // radius at most d: the offset fills it (every point of it is within d of its rim, and every
    // point outside it is nearer its rim than its inside), so it is left out exactly, sparing
    // the offsetter the loops it would turn inside out.
    let kept: Vec<Vec<[f64; 2]>> = contours
        .iter()
        .filter(|c| {
            area(c) > 0.0 || {
                let b = bounds(c);
                0.5 * (b[2] - b[0]).min(b[3] - b[1]) > d
            }
        })
        .cloned()
        .collect();
    // The chord angle whose sagitta is `tol` on an arc of radius `d`.
    let angle = 2.0 * (1.0 - (tol / d).min(1.0)).acos();
    let style = OutlineStyle::new(d).line_join(LineJoin::Round(angle.max(1e-3)));
    kept.outline_as::<i64>(&style).into_iter().flatten().collect()
}

/// Distance from `q` to the nearest edge of any of `contours`.
pub fn distance_to(contours: &[Vec<[f64; 2]>], q: [f64; 2]) -> f64 {
    contours
        .iter()
        .flat_map(|c| (0..c.len()).map(move |i| (c[i], c[(i + 1) % c.len()])))
        .map(|(a, b)| {
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let l2 = dx * dx + dy * dy;
            let t =
                if l2 > 0.0 { (((q[0] - a[0]) * dx + (q[1] - a[1]) * dy) / l2).clamp(0.0, 1.0) } else { 0.0 };
            (q[0] - a[0] - t * dx).hypot(q[1] - a[1] - t * dy)
        })
        .fold(f64::INFINITY, f64::min)
}

/// Whether `q` lies on the border of the rectangle `[x0, y0, x1, y1]` (to 1e-9 mm).
fn on_rect_border(q: &[f64; 2], b: [f64; 4]) -> bool {
    let near = |a: f64, c: f64| (a - c).abs() <= 1e-9;
    near(q[0], b[0]) || near(q[0], b[2]) || near(q[1], b[1]) || near(q[1], b[3])
}

/// The pieces of the closed loop `ring` inside the rectangle `[x0, y0, x1, y1]`: the loop itself
/// when it stays inside, else its open runs inside (segments clipped at the border).
fn clip_loop(ring: &[[f64; 2]], b: [f64; 4]) -> (Option<Polyline2>, Vec<Polyline2>) {
    let inside = |p: [f64; 2]| p[0] >= b[0] && p[0] <= b[2] && p[1] >= b[1] && p[1] <= b[3];
    if ring.iter().all(|&p| inside(p)) {
        return (Some(ring.to_vec()), Vec::new());
    }
    // Liang–Barsky on each edge, starting at a vertex outside so runs do not wrap.
    let n = ring.len();
    let start = (0..n).find(|&i| !inside(ring[i])).unwrap_or(0);
    let mut pieces: Vec<Vec<[f64; 2]>> = Vec::new();
    let mut cur: Vec<[f64; 2]> = Vec::new();
    for k in 0..n {
        let (a, c) = (ring[(start + k) % n], ring[(start + k + 1) % n]);
        let (dx, dy) = (c[0] - a[0], c[1] - a[1]);
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        let mut keep = true;
        for (p, q) in [(-dx, a[0] - b[0]), (dx, b[2] - a[0]), (-dy, a[1] - b[1]), (dy, b[3] - a[1])] {
            if p == 0.0 {
                if q < 0.0 {
                    keep = false;
                }
            } else {
                let t = q / p;
                if p < 0.0 {
                    t0 = t0.max(t);
                } else {
                    t1 = t1.min(t);
                }
            }
        }
        if !keep || t0 > t1 {
            if cur.len() >= 2 {
                pieces.push(std::mem::take(&mut cur));
            }
            cur.clear();
            continue;
        }
        let p0 = [a[0] + t0 * dx, a[1] + t0 * dy];
        let p1 = [a[0] + t1 * dx, a[1] + t1 * dy];
        if cur.last() != Some(&p0) {
            if cur.len() >= 2 {
                pieces.push(std::mem::take(&mut cur));
            }
            cur.clear();
            cur.push(p0);
        }
        cur.push(p1);
        if t1 < 1.0 {
            pieces.push(std::mem::take(&mut cur));
        }
    }
    if cur.len() >= 2 {
        pieces.push(cur);
    }
    (None, pieces)
}

/// The rings of `layer`. See the module docs.
///
/// Errors: a tool radius, radial depth (at most the diameter) or tolerance that is not a
/// positive finite number, a stock rectangle that is empty or not finite, more than
/// [`MAX_RINGS`] rings.
pub fn layer_passes(layer: &Layer, o: &PassOptions) -> Result<LayerPasses, PassError> {
    let r = o.tool_radius_mm;
    if !(r.is_finite() && r > 0.0) {
        return Err(invalid("tool_radius_mm", r, "must be a positive number of millimetres"));
    }
    let ae = o.radial_depth_mm;
    if !(ae.is_finite() && ae > 0.0 && ae <= 2.0 * r) {
        return Err(invalid(
            "radial_depth_mm",
            ae,
            format!("must be in (0, {}] (the tool's diameter)", 2.0 * r),
        ));
    }
    let tol = o.arc_tolerance_mm;
    if !(tol.is_finite() && tol > 0.0 && tol < r) {
        return Err(invalid("arc_tolerance_mm", tol, format!("must be in (0, {r}) mm")));
    }
    let s = o.stock;
    if !(s.iter().all(|v| v.is_finite()) && s[0] < s[2] && s[1] < s[3]) {
        return Err(invalid("stock", s[0], format!("{s:?}: need x_min < x_max and y_min < y_max, finite")));
    }
    let part: Vec<Vec<[f64; 2]>> = layer.contours.iter().map(|c| c.points.clone()).collect();
    // The fewest rings whose outermost one reaches all the stock: the region within `d_K + r`
    // of the part must hold the whole rectangle (its corners inside, and none of its boundary
    // inside the rectangle; the corners alone are not enough when the part is concave or has
    // wide holes, whose middles may be farther than any corner).
    let rect = [s[0], s[1], s[2], s[3]];
    let covered = |reach: f64| -> bool {
        let region = offset(&part, reach, tol);
        let corners = [[s[0], s[1]], [s[2], s[1]], [s[2], s[3]], [s[0], s[3]]];
        corners.iter().all(|&c| region.iter().filter(|k| contains(k, c)).count() % 2 == 1)
            && region.iter().all(|k| {
                let (whole, pieces) = clip_loop(k, rect);
                whole.is_none() && pieces.iter().all(|p| p.iter().all(|q| on_rect_border(q, rect)))
            })
    };
    // No point of the stock is farther from the part than its diagonal (when the part meets
    // the stock at all): more rings than that needs are refused before offsetting anything.
    let diagonal = (s[2] - s[0]).hypot(s[3] - s[1]);
    if !part.is_empty() && (diagonal - 2.0 * r) / ae >= MAX_RINGS as f64 {
        return Err(invalid(
            "radial_depth_mm",
            ae,
            format!(
                "up to {:.0} rings across the stock's {diagonal:.3} mm diagonal: more than {MAX_RINGS}",
                (diagonal - 2.0 * r) / ae
            ),
        ));
    }
    // Coverage grows with the reach: the smallest count by bisection.
    let mut count = 0usize;
    if !part.is_empty() && !covered(2.0 * r) {
        let (mut lo, mut hi) = (0usize, ((diagonal - 2.0 * r) / ae).ceil().max(1.0) as usize);
        if !covered(2.0 * r + hi as f64 * ae) {
            return Err(invalid(
                "stock",
                s[0],
                format!("{s:?}: the part's section at z {} does not meet the stock", layer.z_mm),
            ));
        }
        // covered(lo) is false, covered(hi) true.
        while hi - lo > 1 {
            let mid = lo + (hi - lo) / 2;
            if covered(2.0 * r + mid as f64 * ae) {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        count = hi;
    }
    let grown = [s[0] - r, s[1] - r, s[2] + r, s[3] + r];
    let mut rings = Vec::new();
    for k in (0..=count).rev() {
        if part.is_empty() {
            break;
        }
        let d = r + k as f64 * ae;
        let mut ring = Ring { offset_mm: d, loops: Vec::new(), pieces: Vec::new() };
        for lp in offset(&part, d, tol) {
            let (whole, pieces) = clip_loop(&lp, grown);
            ring.loops.extend(whole);
            ring.pieces.extend(pieces);
        }
        if !ring.loops.is_empty() || !ring.pieces.is_empty() {
            rings.push(ring);
        }
    }
    // Holes of the part with no hole of the finishing contour inside them.
    let finish = offset(&part, r, tol);
    let unreached = layer
        .contours
        .iter()
        .filter(|c| c.kind == ContourKind::Hole)
        .filter(|h| {
            !finish.iter().any(|f| area(f) < 0.0 && f.first().is_some_and(|&q| contains(&h.points, q)))
        })
        .map(|h| {
            let n = h.points.len() as f64;
            let c = h.points.iter().fold([0.0, 0.0], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n]);
            Unreached { at: c, area_mm2: h.area_mm2.abs() }
        })
        .collect();
    Ok(LayerPasses { z_mm: layer.z_mm, rings, unreached })
}

/// How a move of a layer program runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MoveKind {
    /// Cutting (a ring) or a link through cleared material or air at feed.
    Feed,
    /// Up to the clearance height and across above everything (a retract; the way back down
    /// is a feed move, as material may stand below).
    Rapid,
}

/// One straight move of a layer program, to `to` (mm).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PathMove {
    pub to: [f64; 3],
    pub kind: MoveKind,
}

/// A layer program and how its pieces were joined.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LayerProgram {
    pub moves: Vec<PathMove>,
    /// Links run at feed: within a layer clear of the part (a step in to the next ring cuts at
    /// most the radial depth, as the rings do), or across cleared material and down in the air
    /// beside the stock to the next layer.
    pub feed_links: usize,
    /// Links that retract to the clearance height and re-enter.
    pub retracts: usize,
}

/// Shortest distance between segments `a`-`b` and `c`-`d`.
fn segment_distance(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> f64 {
    let cross =
        |o: [f64; 2], p: [f64; 2], q: [f64; 2]| (p[0] - o[0]) * (q[1] - o[1]) - (p[1] - o[1]) * (q[0] - o[0]);
    let (d1, d2, d3, d4) = (cross(c, d, a), cross(c, d, b), cross(a, b, c), cross(a, b, d));
    if ((d1 > 0.0 && d2 < 0.0) || (d1 < 0.0 && d2 > 0.0))
        && ((d3 > 0.0 && d4 < 0.0) || (d3 < 0.0 && d4 > 0.0))
    {
        return 0.0;
    }
    let point_seg = |p: [f64; 2], s0: [f64; 2], s1: [f64; 2]| {
        let (dx, dy) = (s1[0] - s0[0], s1[1] - s0[1]);
        let l2 = dx * dx + dy * dy;
        let t =
            if l2 > 0.0 { (((p[0] - s0[0]) * dx + (p[1] - s0[1]) * dy) / l2).clamp(0.0, 1.0) } else { 0.0 };
        (p[0] - s0[0] - t * dx).hypot(p[1] - s0[1] - t * dy)
    };
    point_seg(a, c, d).min(point_seg(b, c, d)).min(point_seg(c, a, b)).min(point_seg(d, a, b))
}

/// Whether the tool centre can go straight from `a` to `b` in the layer without coming nearer
/// than `clear` to the part's section (so it never cuts the part).
fn clear_of(part: &[Vec<[f64; 2]>], a: [f64; 2], b: [f64; 2], clear: f64) -> bool {
    part.iter().all(|c| (0..c.len()).all(|i| segment_distance(a, b, c[i], c[(i + 1) % c.len()]) >= clear))
}

/// Joins the layers' rings into one program, top layer first, each layer from its outermost
/// ring in to its finishing ring. `parts[i]` is layer `i`'s section (its contours), `layers[i]`
/// its rings (heights decreasing). Between two cuts of a layer the tool goes straight at feed
/// when the link keeps at least `r - tol` from the part (outside the ring just cut everything is
/// cut away or air; a step in to the next ring cuts no more than the radial depth), and
/// otherwise retracts to `clear_z_mm` and re-enters (across at rapid, down at feed). Down to the next layer it moves across at the height it is at, then down
/// beside the next layer's first cut, when that start is off the stock (in the air) and the way
/// across keeps clear of this layer's part; else it retracts. A closed loop starts at its vertex
/// nearest the tool; an open piece from its nearer end.
///
/// Errors: layers and sections of different counts, heights not decreasing, a clearance height
/// not above every layer.
pub fn link_layers(
    parts: &[Vec<Vec<[f64; 2]>>],
    layers: &[LayerPasses],
    o: &PassOptions,
    clear_z_mm: f64,
) -> Result<LayerProgram, PassError> {
    if parts.len() != layers.len() {
        return Err(invalid("layers", layers.len() as f64, format!("{} sections given", parts.len())));
    }
    if let Some(w) = layers.windows(2).find(|w| w[1].z_mm >= w[0].z_mm) {
        return Err(invalid("z_mm", w[1].z_mm, format!("must be below the layer before it ({})", w[0].z_mm)));
    }
    if let Some(top) = layers.first()
        && !(clear_z_mm.is_finite() && clear_z_mm > top.z_mm)
    {
        return Err(invalid("clear_z_mm", clear_z_mm, format!("must be above the top layer ({})", top.z_mm)));
    }
    let r = o.tool_radius_mm;
    let clear = r - o.arc_tolerance_mm - 1e-9;
    let s = o.stock;
    let in_air = |p: [f64; 2]| p[0] < s[0] - r || p[0] > s[2] + r || p[1] < s[1] - r || p[1] > s[3] + r;
    let on_border = |p: [f64; 2]| {
        p[0] <= s[0] - r + 1e-9
            || p[0] >= s[2] + r - 1e-9
            || p[1] <= s[1] - r + 1e-9
            || p[1] >= s[3] + r - 1e-9
    };
    let mut prog = LayerProgram::default();
    let mut at: Option<[f64; 3]> = None;
    let retract = |prog: &mut LayerProgram, at: [f64; 3], to: [f64; 3]| {
        prog.moves.push(PathMove { to: [at[0], at[1], clear_z_mm], kind: MoveKind::Rapid });
        prog.moves.push(PathMove { to: [to[0], to[1], clear_z_mm], kind: MoveKind::Rapid });
        // Down at feed: below the clearance height there may be material not yet cut.
        prog.moves.push(PathMove { to, kind: MoveKind::Feed });
        prog.retracts += 1;
    };
    for (part, layer) in parts.iter().zip(layers) {
        let z = layer.z_mm;
        for ring in &layer.rings {
            // Every cut of the ring, the nearest next.
            let mut todo: Vec<(bool, &Vec<[f64; 2]>)> = ring
                .loops
                .iter()
                .map(|l| (true, l))
                .chain(ring.pieces.iter().map(|p| (false, p)))
                .filter(|(_, p)| !p.is_empty())
                .collect();
            while !todo.is_empty() {
                let here = at.map_or([0.0, 0.0], |p| [p[0], p[1]]);
                let d2 = |q: [f64; 2]| (q[0] - here[0]).powi(2) + (q[1] - here[1]).powi(2);
                let (k, start) = todo
                    .iter()
                    .enumerate()
                    .map(|(k, (closed, pts))| {
                        let best = if *closed {
                            (0..pts.len()).min_by(|&i, &j| d2(pts[i]).total_cmp(&d2(pts[j]))).unwrap_or(0)
                        } else if d2(pts[pts.len() - 1]) < d2(pts[0]) {
                            pts.len() - 1
                        } else {
                            0
                        };
                        (k, best, d2(pts[best]))
                    })
                    .min_by(|a, b| a.2.total_cmp(&b.2))
                    .map(|(k, best, _)| (k, best))
                    .unwrap_or((0, 0));
                let (closed, pts) = todo.swap_remove(k);
                let order: Vec<[f64; 2]> = if closed {
                    (0..=pts.len()).map(|i| pts[(start + i) % pts.len()]).collect()
                } else if start == 0 {
                    pts.clone()
                } else {
                    pts.iter().rev().copied().collect()
                };
                let first = [order[0][0], order[0][1], z];
                match at {
                    None => {
                        prog.moves
                            .push(PathMove { to: [first[0], first[1], clear_z_mm], kind: MoveKind::Rapid });
                        prog.moves.push(PathMove { to: first, kind: MoveKind::Feed });
                    }
                    Some(p) if (p[2] - z).abs() < 1e-12 => {
                        if clear_of(part, [p[0], p[1]], order[0], clear) {
                            prog.moves.push(PathMove { to: first, kind: MoveKind::Feed });
                            prog.feed_links += 1;
                        } else {
                            retract(&mut prog, p, first);
                        }
                    }
                    Some(p) => {
                        // Down a layer: across at the height above (cleared there), then down
                        // in the air beside the stock.
                        let prev_part = parts
                            .iter()
                            .zip(layers)
                            .find(|(_, l)| (l.z_mm - p[2]).abs() < 1e-12)
                            .map_or(part, |(pp, _)| pp);
                        let outside = in_air(order[0]) || on_border(order[0]);
                        if outside && clear_of(prev_part, [p[0], p[1]], order[0], clear) {
                            prog.moves
                                .push(PathMove { to: [first[0], first[1], p[2]], kind: MoveKind::Feed });
                            prog.moves.push(PathMove { to: first, kind: MoveKind::Feed });
                            prog.feed_links += 1;
                        } else {
                            retract(&mut prog, p, first);
                        }
                    }
                }
                for q in &order[1..] {
                    prog.moves.push(PathMove { to: [q[0], q[1], z], kind: MoveKind::Feed });
                }
                at = order.last().map(|q| [q[0], q[1], z]);
            }
        }
    }
    if let Some(p) = at {
        prog.moves.push(PathMove { to: [p[0], p[1], clear_z_mm], kind: MoveKind::Rapid });
    }
    Ok(prog)
}

/// How a mesh is cut layer by layer ([`mesh_program`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MeshProgramOptions {
    /// Distance between layers, mm.
    pub step_mm: f64,
    /// Height of the lowest layer (default: half a step above the mesh's lowest point).
    pub from_mm: Option<f64>,
    pub tool_radius_mm: f64,
    /// Radial depth of cut (default: the tool's radius).
    pub radial_depth_mm: Option<f64>,
    /// Stock around the part's box in X and Y, mm.
    pub stock_margin_mm: f64,
    /// Clearance height above the part's top for retracts, mm.
    pub clearance_mm: f64,
}

impl MeshProgramOptions {
    /// Layers every `step_mm` from the default first layer, for a tool of `tool_radius_mm`: radial
    /// depth the tool's radius, 5 mm of stock around the part, retracts 5 mm above it.
    pub fn new(step_mm: f64, tool_radius_mm: f64) -> Self {
        MeshProgramOptions {
            step_mm,
            from_mm: None,
            tool_radius_mm,
            radial_depth_mm: None,
            stock_margin_mm: 5.0,
            clearance_mm: 5.0,
        }
    }
}

/// A mesh's layers, their rings and the program joining them, top layer first.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshProgram {
    /// Layers bottom up, as sliced.
    pub layers: Vec<Layer>,
    /// Each layer's rings, bottom up.
    pub passes: Vec<LayerPasses>,
    pub options: PassOptions,
    pub program: LayerProgram,
    pub clear_z_mm: f64,
    /// The mesh's height range.
    pub z_range_mm: [f64; 2],
}

/// Slices `mesh` every `step_mm` from `from_mm` up to its top, plans each layer's rings with
/// a stock rectangle around the part's box, and joins them top layer first ([`link_layers`]).
///
/// Errors: a mesh with no triangles or a non-finite vertex, bad settings (named), more than
/// [`MAX_LAYERS`] layers, a first layer above the mesh.
pub fn mesh_program(mesh: &Mesh, o: &MeshProgramOptions) -> Result<MeshProgram, PassError> {
    if mesh.triangles.is_empty() {
        return Err(invalid("triangles", 0.0, "the mesh has none"));
    }
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in &mesh.vertices {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let step = o.step_mm;
    if !(step.is_finite() && step > 0.0) {
        return Err(invalid("step_mm", step, "must be a positive number of millimetres"));
    }
    let m = o.stock_margin_mm;
    if !(m.is_finite() && m >= 0.0) {
        return Err(invalid("stock_margin_mm", m, "must be a non-negative number of millimetres"));
    }
    if !(o.clearance_mm.is_finite() && o.clearance_mm > 0.0) {
        return Err(invalid("clearance_mm", o.clearance_mm, "must be a positive height"));
    }
    let from = o.from_mm.unwrap_or(lo[2] + 0.5 * step);
    if !from.is_finite() {
        return Err(invalid("from_mm", from, "must be finite"));
    }
    let count = ((hi[2] - from) / step).floor() + 1.0;
    if count < 1.0 {
        return Err(invalid(
            "from_mm",
            from,
            format!("above the mesh's highest point {:.4} mm: no layer cuts it", hi[2]),
        ));
    }
    if count > MAX_LAYERS as f64 {
        return Err(invalid(
            "step_mm",
            step,
            format!(
                "{count:.0} layers from {from} mm to {:.4} mm: more than {MAX_LAYERS}; take a larger step",
                hi[2]
            ),
        ));
    }
    let layers = slice(mesh, &levels(from, step, count as usize)?)?;
    let r = o.tool_radius_mm;
    let options = PassOptions {
        tool_radius_mm: r,
        radial_depth_mm: o.radial_depth_mm.unwrap_or(r),
        arc_tolerance_mm: (0.01f64).min(0.1 * r),
        stock: [lo[0] - m, lo[1] - m, hi[0] + m, hi[1] + m],
    };
    let passes = layers.iter().map(|l| layer_passes(l, &options)).collect::<Result<Vec<_>, _>>()?;
    // Top layer first.
    let parts: Vec<Vec<Polyline2>> =
        layers.iter().rev().map(|l| l.contours.iter().map(|c| c.points.clone()).collect()).collect();
    let top_down: Vec<LayerPasses> = passes.iter().rev().cloned().collect();
    let clear_z_mm = hi[2] + o.clearance_mm;
    let program = link_layers(&parts, &top_down, &options, clear_z_mm)?;
    Ok(MeshProgram { layers, passes, options, program, clear_z_mm, z_range_mm: [lo[2], hi[2]] })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::slice::Contour;
    use proptest::prelude::*;

    fn layer(contours: Vec<Vec<[f64; 2]>>) -> Layer {
        let contours = contours
            .into_iter()
            .map(|p| {
                let a = area(&p);
                Contour {
                    points: p,
                    area_mm2: a,
                    kind: if a > 0.0 { ContourKind::Outer } else { ContourKind::Hole },
                    depth: u32::from(a < 0.0),
                    parent: None,
                }
            })
            .collect();
        Layer { z_mm: 1.0, contours, open: Vec::new(), defects: Vec::new() }
    }

    fn square(x0: f64, y0: f64, w: f64, ccw: bool) -> Vec<[f64; 2]> {
        let mut p = vec![[x0, y0], [x0 + w, y0], [x0 + w, y0 + w], [x0, y0 + w]];
        if !ccw {
            p.reverse();
        }
        p
    }

    fn opts(r: f64, ae: f64, stock: [f64; 4]) -> PassOptions {
        PassOptions { tool_radius_mm: r, radial_depth_mm: ae, arc_tolerance_mm: 0.005, stock }
    }

    #[test]
    fn a_square_in_its_stock_gets_rings_out_to_the_corners() {
        let l = layer(vec![square(0.0, 0.0, 10.0, true)]);
        let p = layer_passes(&l, &opts(1.0, 1.5, [-10.0, -10.0, 20.0, 20.0])).expect("passes");
        // The farthest corner is 14.14 mm from the part: rings at 1 + 1.5 k, k = 9..0.
        assert_eq!(p.rings.len(), 10);
        assert!((p.rings[0].offset_mm - 14.5).abs() < 1e-12 && (p.rings[9].offset_mm - 1.0).abs() < 1e-12);
        // The finishing ring: the square grown by 1 with round corners.
        let fin = &p.rings[9];
        assert_eq!((fin.loops.len(), fin.pieces.len()), (1, 0));
        let a = area(&fin.loops[0]);
        let want = 12.0 * 12.0 - (4.0 - std::f64::consts::PI);
        // The corners' arcs are chords within 0.005 mm: at most 2π·r·0.005 less area.
        assert!(a <= want + 1e-9 && want - a <= std::f64::consts::TAU * 0.005, "{a} vs {want}");
        // Outer rings leave the stock (grown by the radius) and are cut into pieces.
        assert!(p.rings[0].loops.is_empty() && !p.rings[0].pieces.is_empty());
        for piece in &p.rings[0].pieces {
            assert!(piece.iter().all(|q| q[0] >= -11.0 - 1e-9 && q[0] <= 21.0 + 1e-9));
        }
        assert!(p.unreached.is_empty());
    }

    #[test]
    fn the_rings_reach_the_middle_of_a_wide_hole_farther_than_any_stock_corner() {
        // A 40 mm square frame with a 30 mm square hole: the stock's corners are 2.8 mm from
        // the part, the hole's middle 15 mm.
        let l = layer(vec![square(0.0, 0.0, 40.0, true), square(5.0, 5.0, 30.0, false)]);
        let p = layer_passes(&l, &opts(1.0, 1.5, [-2.0, -2.0, 42.0, 42.0])).expect("passes");
        let reach = p.rings.first().expect("rings").offset_mm + 1.0;
        assert!(reach >= 15.0, "the outermost ring reaches {reach} mm");
        assert!(reach < 15.0 + 1.5 + 1e-9, "one ring more than needed: {reach}");
        // Inside the hole the innermost ring of the middle is a small loop around the centre.
        assert!(
            p.rings[0]
                .loops
                .iter()
                .chain(&p.rings[0].pieces)
                .flatten()
                .all(|q| { (q[0] - 20.0).abs() <= 15.0 && (q[1] - 20.0).abs() <= 15.0 })
        );
    }

    #[test]
    fn a_hole_narrower_than_the_tool_is_reported_and_a_wide_one_is_cut() {
        let l = layer(vec![
            square(0.0, 0.0, 30.0, true),
            square(5.0, 5.0, 1.5, false), // 1.5 mm wide: a 2 mm tool cannot enter
            square(15.0, 15.0, 10.0, false), // 10 mm wide
        ]);
        let p = layer_passes(&l, &opts(1.0, 1.0, [-2.0, -2.0, 32.0, 32.0])).expect("passes");
        assert_eq!(p.unreached.len(), 1, "{:?}", p.unreached);
        assert!((p.unreached[0].at[0] - 5.75).abs() < 1e-9 && (p.unreached[0].area_mm2 - 2.25).abs() < 1e-9);
        let fin = p.rings.last().expect("finishing ring");
        // The outer loop and the wide hole's loop (8 x 8 inside it).
        assert_eq!(fin.loops.len(), 2);
        let hole = fin.loops.iter().find(|l| area(l) < 0.0).expect("hole loop");
        assert!((area(hole) + 64.0).abs() < 1e-6, "{}", area(hole));
    }

    #[test]
    fn bad_options_are_refused_with_the_field() {
        let l = layer(vec![square(0.0, 0.0, 10.0, true)]);
        let s = [-5.0, -5.0, 15.0, 15.0];
        let e = layer_passes(&l, &opts(0.0, 1.0, s)).expect_err("radius");
        assert!(e.to_string().starts_with("tool_radius_mm 0"), "{e}");
        let e = layer_passes(&l, &opts(1.0, 2.5, s)).expect_err("depth");
        assert!(e.to_string().contains("radial_depth_mm 2.5: must be in (0, 2]"), "{e}");
        assert!(layer_passes(&l, &opts(1.0, 1.0, [5.0, 0.0, 1.0, 10.0])).is_err());
        let e = layer_passes(&l, &opts(1.0, 1e-6, [-1e6, -1e6, 1e6, 1e6])).expect_err("rings");
        assert!(e.to_string().contains("more than 10000"), "{e}");
    }

    /// Every feed move of `prog` at a layer's height keeps `r - tol` from that layer's part.
    fn feeds_clear(parts: &[Vec<Vec<[f64; 2]>>], zs: &[f64], prog: &LayerProgram, clear: f64) -> bool {
        let mut from: Option<[f64; 3]> = None;
        for m in &prog.moves {
            if let (Some(a), MoveKind::Feed) = (from, m.kind)
                && (a[2] - m.to[2]).abs() < 1e-12
            {
                let k = zs.iter().position(|z| (z - a[2]).abs() < 1e-12).expect("a layer's height");
                if !clear_of(&parts[k], [a[0], a[1]], [m.to[0], m.to[1]], clear) {
                    return false;
                }
            }
            from = Some(m.to);
        }
        true
    }

    #[test]
    fn layers_link_through_cleared_material_and_retract_where_the_part_is_in_the_way() {
        // A square post: every layer starts in the air at the stock's border, so each layer
        // links down beside the stock without retracting.
        let post = vec![square(0.0, 0.0, 10.0, true)];
        let o = opts(1.0, 1.5, [-6.0, -6.0, 16.0, 16.0]);
        let zs = [9.0, 6.0, 3.0];
        let layers: Vec<LayerPasses> = zs
            .iter()
            .map(|&z| layer_passes(&Layer { z_mm: z, ..layer(post.clone()) }, &o).expect("passes"))
            .collect();
        let parts = vec![post.clone(); 3];
        let prog = link_layers(&parts, &layers, &o, 20.0).expect("program");
        assert_eq!(prog.retracts, 0, "{prog:?}");
        assert!(prog.feed_links > 0);
        assert!(feeds_clear(&parts, &zs, &prog, 1.0 - 0.005 - 1e-9));
        // The program ends up at the clearance height and visits every layer.
        assert_eq!(prog.moves.last().map(|m| m.to[2]), Some(20.0));
        for z in zs {
            assert!(prog.moves.iter().any(|m| m.to[2] == z));
        }

        // Two posts side by side a little more than a tool apart: the rings wrap both, some
        // links between them would cross a post and retract instead.
        let two = vec![square(0.0, 0.0, 10.0, true), square(12.5, 0.0, 10.0, true)];
        let o = opts(1.0, 1.0, [-3.0, -3.0, 25.5, 13.0]);
        let l = layer_passes(&Layer { z_mm: 5.0, ..layer(two.clone()) }, &o).expect("passes");
        let prog =
            link_layers(std::slice::from_ref(&two), std::slice::from_ref(&l), &o, 20.0).expect("program");
        assert!(feeds_clear(std::slice::from_ref(&two), &[5.0], &prog, 1.0 - 0.005 - 1e-9));
        assert!(prog.retracts > 0, "{} links, {} retracts", prog.feed_links, prog.retracts);

        // Bad calls.
        assert!(link_layers(&parts[..2], &layers, &o, 20.0).is_err());
        assert!(
            link_layers(&parts, &layers, &o, 5.0)
                .expect_err("clearance")
                .to_string()
                .contains("clear_z_mm 5")
        );
        let mut up = layers.clone();
        up.reverse();
        assert!(link_layers(&parts, &up, &o, 20.0).is_err());
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]

        /// Leaving out the holes an offset fills changes nothing: the same region as offsetting
        /// every contour (random plates with random rectangular holes).
        #[test]
        fn holes_left_out_of_an_offset_change_nothing(
            holes in proptest::collection::vec((1.0f64..30.0, 1.0f64..30.0, 0.5f64..8.0, 0.5f64..8.0), 1..6),
            d in 0.2f64..6.0,
        ) {
            let mut part = vec![square(0.0, 0.0, 40.0, true)];
            for (x, y, w, h) in holes {
                let (w, h) = (w.min(39.0 - x), h.min(39.0 - y));
                let rect = vec![[x, y], [x, y + h], [x + w, y + h], [x + w, y]]; // clockwise
                if part.iter().skip(1).all(|p: &Vec<[f64; 2]>| {
                    let b = bounds(p);
                    x + w < b[0] - 0.1 || x > b[2] + 0.1 || y + h < b[1] - 0.1 || y > b[3] + 0.1
                }) {
                    part.push(rect);
                }
            }
            let angle = 2.0 * (1.0 - (0.005 / d).min(1.0)).acos();
            let style = OutlineStyle::new(d).line_join(LineJoin::Round(angle.max(1e-3)));
            let all: Vec<Vec<[f64; 2]>> = part.clone().outline_as::<i64>(&style).into_iter().flatten().collect();
            let kept = offset(&part, d, 0.005);
            let (a, b): (f64, f64) = (all.iter().map(|c| area(c)).sum(), kept.iter().map(|c| area(c)).sum());
            prop_assert!((a - b).abs() < 1e-6 * a.abs(), "all contours {} vs holes left out {}", a, b);
            prop_assert_eq!(all.iter().filter(|c| area(c) < 0.0).count(), kept.iter().filter(|c| area(c) < 0.0).count());
        }


        /// Random star-shaped parts: every vertex of every ring is at the ring's offset from the
        /// part (within the arc tolerance, by brute force over the part's edges), outside it.
        #[test]
        fn ring_vertices_lie_at_their_offset_from_the_part(
            radii in proptest::collection::vec(2.0f64..6.0, 5..24),
            r in 0.5f64..2.0,
            ae_frac in 0.3f64..1.0,
        ) {
            let n = radii.len();
            let star: Vec<[f64; 2]> = radii
                .iter()
                .enumerate()
                .map(|(i, &rho)| {
                    let a = std::f64::consts::TAU * i as f64 / n as f64;
                    [rho * a.cos(), rho * a.sin()]
                })
                .collect();
            let part = vec![star.clone()];
            let l = layer(part.clone());
            let o = PassOptions { tool_radius_mm: r, radial_depth_mm: 2.0 * r * ae_frac, arc_tolerance_mm: 0.005, stock: [-8.0, -8.0, 8.0, 8.0] };
            let p = layer_passes(&l, &o).expect("passes");
            prop_assert!(!p.rings.is_empty());
            prop_assert!((p.rings.last().expect("ring").offset_mm - r).abs() < 1e-12);
            for ring in &p.rings {
                for q in ring.loops.iter().chain(&ring.pieces).flatten() {
                    let border = q[0].abs() >= 8.0 + r - 1e-9 || q[1].abs() >= 8.0 + r - 1e-9;
                    let d = distance_to(&part, *q);
                    // Clipped ends on the stock's border lie on the ring too.
                    prop_assert!((d - ring.offset_mm).abs() < 0.005 + 1e-6 || border && d >= ring.offset_mm - 0.006,
                        "offset {} vertex {:?} at {}", ring.offset_mm, q, d);
                    prop_assert!(!contains(&star, *q));
                }
            }
        }
    }
}

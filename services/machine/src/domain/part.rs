//! The simulated part measured against the original part, not against a depth map.
//!
//! The reference is a set of points on the original part's surface (the merged scan cloud, or
//! points of the input mesh), in the part frame (the frame of the A = 0 face's map and of the one
//! dexel stock). Each point is measured on the stock ([`DexelStock::deviation_at`]): the distance
//! to the simulated part's surface, positive where material is left over the point, negative
//! where the cut went into the part (a gouge).
//!
//! Only the points a face looks at count: a point belongs to the face whose target map, at the
//! point's position seen from that face, lies within [`SEEN_TOLERANCE_PIXELS`] pixels (at least
//! [`SEEN_TOLERANCE_MM`]) of the point's height; the others (the clamped bottom, the ends no face
//! turns up, walls steeper than the maps resolve) are counted as unseen and left out, since no
//! program cut there.
//!
//! Against the part opened by the tools: the opening of each face's target map by the program's
//! smallest tool (dilated by the tool into the surface its tip follows, then eroded back by the
//! tool: the surface the tool leaves where it cannot reach into a concave corner;
//! [`depthmill_geometry::compensate`], the CAM service's kernel, does both). A point's leftover there is what exceeds the
//! material the opening itself leaves above it; gouges are the same as against the part.

use depthmill_geometry::compensate::opened;
use depthmill_geometry::{HeightMap, ToolProfile};
use nalgebra::Point3;
use rayon::prelude::*;
use serde::Serialize;

use super::dexel::DexelStock;
use super::sim::part_from_work;

/// A point belongs to a face when its height is within this many of the face map's pixels of
/// the map's height there.
pub const SEEN_TOLERANCE_PIXELS: f64 = 2.0;
/// ... and at least this much, mm.
pub const SEEN_TOLERANCE_MM: f64 = 0.25;
/// Distances are searched up to this far, mm; a farther surface counts as this.
pub const MAX_DEVIATION_MM: f64 = 10.0;

/// Deviation figures over a set of points (positive = material left).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Figures {
    pub points: usize,
    pub max_gouge_mm: f64,
    pub max_leftover_mm: f64,
    pub mean_leftover_mm: f64,
    pub rms_deviation_mm: f64,
}

impl Figures {
    fn of(devs: impl Iterator<Item = f64>) -> Self {
        let mut f = Figures::default();
        let (mut sum_left, mut sum_sq) = (0.0, 0.0);
        for d in devs {
            f.points += 1;
            f.max_gouge_mm = f.max_gouge_mm.max(-d);
            f.max_leftover_mm = f.max_leftover_mm.max(d);
            sum_left += d.max(0.0);
            sum_sq += d * d;
        }
        let n = f.points.max(1) as f64;
        f.mean_leftover_mm = sum_left / n;
        f.rms_deviation_mm = (sum_sq / n).sqrt();
        f
    }
}

/// One face's share of the measurement.
#[derive(Debug, Clone, Serialize)]
pub struct FacePart {
    pub a_deg: f64,
    pub against_part: Figures,
    pub against_opened: Option<Figures>,
}

/// The simulated part against the original part.
#[derive(Debug, Clone, Serialize)]
pub struct PartDeviation {
    /// What the reference points are (e.g. `point_cloud`, `mesh`).
    pub source: String,
    /// Reference points given, and how many no face looks at.
    pub points: usize,
    pub unseen: usize,
    pub against_part: Figures,
    /// Against the part opened by `opened_by` (the program's smallest tool), when there is one.
    pub against_opened: Option<Figures>,
    pub opened_by: Option<String>,
    pub faces: Vec<FacePart>,
    pub max_search_mm: f64,
    /// Each reference point's deviation against the part (NaN where unseen), in input order.
    #[serde(skip)]
    pub per_point: Vec<f32>,
}

/// A face to measure on: its A angle and target map.
#[derive(Debug, Clone, Copy)]
pub struct MeasureFace<'a> {
    pub a_deg: f64,
    pub map: &'a HeightMap,
}

/// Measures `stock` against `reference` (see the module docs); `opening` names the tool the part
/// is opened with.
pub fn measure(
    stock: &DexelStock,
    source: &str,
    reference: &[Point3<f64>],
    faces: &[MeasureFace<'_>],
    opening: Option<(&str, &ToolProfile)>,
) -> PartDeviation {
    let frames: Vec<_> = faces.iter().map(|f| part_from_work(f.a_deg).inverse()).collect();
    let openings: Vec<Option<HeightMap>> =
        faces.iter().map(|f| opening.and_then(|(_, tool)| opened(f.map, tool))).collect();
    // Per point: (face, deviation against the part, against the opened part).
    let measured: Vec<Option<(usize, f64, Option<f64>)>> = reference
        .par_iter()
        .map(|p| {
            let mut best: Option<(usize, f64, [u32; 2])> = None;
            for (i, f) in faces.iter().enumerate() {
                let v = frames[i] * p;
                let Some((c, r)) = f.map.cell_of(v.x, v.y) else { continue };
                let Some(h) = f.map.get(c, r).filter(|h| h.is_finite()) else { continue };
                let err = (v.z - f64::from(h)).abs();
                let tol = (SEEN_TOLERANCE_PIXELS * f.map.pixel_mm()).max(SEEN_TOLERANCE_MM);
                if err <= tol && best.is_none_or(|(_, e, _)| err < e) {
                    best = Some((i, err, [c, r]));
                }
            }
            let (i, _, [c, r]) = best?;
            let d = stock.deviation_at(p, MAX_DEVIATION_MM);
            let against_opened = openings[i].as_ref().and_then(|o| o.get(c, r)).map(|o| {
                let allowance = (f64::from(o) - (frames[i] * p).z).max(0.0);
                if d < 0.0 { d } else { (d - allowance).max(0.0) }
            });
            Some((i, d, against_opened))
        })
        .collect();
    let seen = || measured.iter().flatten();
    let per_face = faces
        .iter()
        .enumerate()
        .map(|(i, f)| FacePart {
            a_deg: f.a_deg,
            against_part: Figures::of(seen().filter(|m| m.0 == i).map(|m| m.1)),
            against_opened: openings[i]
                .as_ref()
                .map(|_| Figures::of(seen().filter(|m| m.0 == i).filter_map(|m| m.2))),
        })
        .collect();
    let any_opening = openings.iter().any(Option::is_some);
    PartDeviation {
        source: source.to_string(),
        points: reference.len(),
        unseen: measured.iter().filter(|m| m.is_none()).count(),
        against_part: Figures::of(seen().map(|m| m.1)),
        against_opened: any_opening.then(|| Figures::of(seen().filter_map(|m| m.2))),
        opened_by: opening.filter(|_| any_opening).map(|(name, _)| name.to_string()),
        faces: per_face,
        max_search_mm: MAX_DEVIATION_MM,
        per_point: measured.iter().map(|m| m.map_or(f32::NAN, |m| m.1 as f32)).collect(),
    }
}

/// Most reference points measured: a larger cloud is thinned evenly, a mesh sampled this densely.
pub const MAX_REFERENCE_POINTS: usize = 400_000;

/// Points spread over `mesh`'s surface, about `max_points` of them: each triangle split into
/// `k × k` similar sub-triangles (`k` from its longest edge against an even spacing over the
/// whole area), one point at each sub-triangle's centroid, plus every vertex.
pub fn mesh_samples(mesh: &depthmill_geometry::Mesh, max_points: usize) -> Vec<Point3<f64>> {
    let area: f64 = (0..mesh.triangles.len())
        .map(|t| {
            let [a, b, c] = mesh.triangle(t);
            0.5 * (b - a).cross(&(c - a)).norm()
        })
        .sum();
    let budget = max_points.saturating_sub(mesh.vertices.len()).max(1) as f64;
    // A k × k split of a triangle with its longest edge e covers about e² / 2 per... point: pick
    // the spacing so the total is about the budget, then never more than it.
    let mut spacing = (2.0 * area / budget).sqrt().max(1e-6);
    let count = |spacing: f64| -> usize {
        (0..mesh.triangles.len())
            .map(|t| {
                let [a, b, c] = mesh.triangle(t);
                let e = (b - a).norm().max((c - b).norm()).max((a - c).norm());
                let k = (e / spacing).ceil().clamp(1.0, 1e4) as usize;
                k * k
            })
            .sum()
    };
    while count(spacing) > budget as usize && spacing.is_finite() {
        spacing *= 1.2;
    }
    let mut out: Vec<Point3<f64>> = mesh.vertices.iter().copied().take(max_points).collect();
    for t in 0..mesh.triangles.len() {
        let [a, b, c] = mesh.triangle(t);
        let e = (b - a).norm().max((c - b).norm()).max((a - c).norm());
        let k = (e / spacing).ceil().clamp(1.0, 1e4) as usize;
        let (u, v) = ((b - a) / k as f64, (c - a) / k as f64);
        for i in 0..k {
            for j in 0..k - i {
                // The upright sub-triangle at (i, j) and, where there is one, the inverted one.
                let base = a + u * i as f64 + v * j as f64;
                out.push(base + (u + v) / 3.0);
                if i + j + 1 < k {
                    out.push(base + (u + v) * (2.0 / 3.0));
                }
            }
        }
    }
    out
}

/// Each vertex's value: the deviation of the nearest measured reference point within
/// `radius_mm` (NaN when there is none): the colours of the simulated part in the report.
pub fn vertex_deviation(
    vertices: &[Point3<f64>],
    reference: &[Point3<f64>],
    per_point: &[f32],
    radius_mm: f64,
) -> Vec<f32> {
    let key = |p: &Point3<f64>| [0, 1, 2].map(|k| (p[k] / radius_mm).floor() as i64);
    let mut bins: std::collections::HashMap<[i64; 3], Vec<u32>> = std::collections::HashMap::new();
    for (i, (p, d)) in reference.iter().zip(per_point).enumerate() {
        if d.is_finite() && p.iter().all(|v| v.is_finite()) {
            bins.entry(key(p)).or_default().push(i as u32);
        }
    }
    vertices
        .par_iter()
        .map(|v| {
            let k = key(v);
            let mut best = (radius_mm * radius_mm, f32::NAN);
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let Some(list) = bins.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) else { continue };
                        for &i in list {
                            let d2 = (reference[i as usize] - v).norm_squared();
                            if d2 <= best.0 {
                                best = (d2, per_point[i as usize]);
                            }
                        }
                    }
                }
            }
            best.1
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use depthmill_geometry::HeightMapMeta;
    use nalgebra::Vector3;

    use super::*;
    use crate::domain::dexel::{Blank, DexelCells, OrientedBox, ToolSolid};

    #[test]
    fn mesh_samples_lie_on_the_surface_and_cover_every_face() {
        let mesh = depthmill_geometry::Mesh::cuboid(10.0, 20.0, 5.0);
        let pts = mesh_samples(&mesh, 5000);
        assert!(pts.len() <= 5000 && pts.len() > 2000, "{}", pts.len());
        let on = |p: &Point3<f64>, k: usize, v: f64| (p[k] - v).abs() < 1e-9;
        for p in &pts {
            let on_face = on(p, 0, 0.0)
                || on(p, 0, 10.0)
                || on(p, 1, 0.0)
                || on(p, 1, 20.0)
                || on(p, 2, 0.0)
                || on(p, 2, 5.0);
            assert!(on_face, "{p:?} is off the box");
        }
        for (k, v) in [(0, 0.0), (0, 10.0), (1, 0.0), (1, 20.0), (2, 0.0), (2, 5.0)] {
            let n = pts.iter().filter(|p| on(p, k, v)).count();
            assert!(n > 50, "face {k}={v} has {n} points");
        }
    }

    /// A 20 × 20 × 10 block with a 4 mm wide, 2 mm deep flat slot along X at Y 10, cut 0.05 mm
    /// too deep; the target is the slot as drawn (2 mm deep) with a sharp inner corner.
    #[test]
    fn a_slot_cut_too_deep_shows_its_gouge_and_the_opened_part_forgives_the_corners() {
        let blank =
            Blank { boxes: vec![OrientedBox::aligned(Point3::origin(), Point3::new(20.0, 20.0, 10.0))] };
        let mut stock = DexelStock::new(&blank, &DexelCells::tri(0.1)).expect("stock");
        let flat = ToolProfile::flat(4.0).expect("flat");
        let solid = ToolSolid::new(&flat, 30.0).expect("solid");
        stock
            .cut_line(
                &solid,
                &Point3::new(-3.0, 10.0, 7.95),
                &Point3::new(23.0, 10.0, 7.95),
                &Vector3::z_axis(),
            )
            .expect("cut");
        let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 10.0, ..HeightMapMeta::new(100, 100, 0.2) };
        let target = HeightMap::from_fn(meta, |c, r| {
            let (_, y) = meta.cell_center(c, r);
            if (y - 10.0).abs() < 2.0 { 8.0 } else { 10.0 }
        })
        .expect("map");
        // Points on the target's top and slot floor, inside the block.
        let pts: Vec<Point3<f64>> = (0..40)
            .flat_map(|i| (0..40).map(move |j| (0.25 + 0.5 * f64::from(i), 0.25 + 0.5 * f64::from(j))))
            .map(|(x, y)| Point3::new(x, y, if (y - 10.0).abs() < 2.0 { 8.0 } else { 10.0 }))
            .chain(std::iter::once(Point3::new(10.0, 10.0, -5.0)))
            .collect();
        let faces = [MeasureFace { a_deg: 0.0, map: &target }];
        let m = measure(&stock, "test", &pts, &faces, Some(("flat-4", &flat)));
        assert_eq!((m.points, m.unseen), (pts.len(), 1), "the point below the block is not seen");
        let f = m.against_part;
        assert!((f.max_gouge_mm - 0.05).abs() < 1e-3, "{f:?}");
        assert!(f.max_leftover_mm < 1e-3, "nothing is left on the top or the floor: {f:?}");
        assert_eq!(m.per_point.len(), pts.len());
        assert!(m.per_point[pts.len() - 1].is_nan());
        let o = m.against_opened.expect("opened");
        assert!((o.max_gouge_mm - 0.05).abs() < 1e-3, "{o:?}");
        assert_eq!(m.faces.len(), 1);

        // A pocket 10 mm wide cut with a ball D6 at its floor's depth: its sharp inner corners
        // keep material against the part, and nothing the ball could have reached against the part
        // opened by it.
        let wide = HeightMap::from_fn(meta, |c, r| {
            let (_, y) = meta.cell_center(c, r);
            if (y - 10.0).abs() < 5.0 { 8.0 } else { 10.0 }
        })
        .expect("map");
        let pts: Vec<Point3<f64>> = (0..40)
            .flat_map(|i| (0..40).map(move |j| (0.25 + 0.5 * f64::from(i), 0.25 + 0.5 * f64::from(j))))
            .map(|(x, y)| Point3::new(x, y, if (y - 10.0).abs() < 5.0 { 8.0 } else { 10.0 }))
            .collect();
        let mut stock = DexelStock::new(&blank, &DexelCells::tri(0.1)).expect("stock");
        let ball = ToolProfile::ball(6.0).expect("ball");
        let solid = ToolSolid::new(&ball, 30.0).expect("solid");
        // Ball centres from Y 7.84 to 12.16: 3 mm from both corners (at Y 5 and 15, Z 10).
        for k in 0..=18 {
            let y = 7.84 + 0.24 * f64::from(k);
            stock
                .cut_line(&solid, &Point3::new(-4.0, y, 8.0), &Point3::new(24.0, y, 8.0), &Vector3::z_axis())
                .expect("cut");
        }
        let faces = [MeasureFace { a_deg: 0.0, map: &wide }];
        let m = measure(&stock, "test", &pts, &faces, Some(("ball-6", &ball)));
        let (part, open) = (m.against_part, m.against_opened.expect("opened"));
        assert!(part.max_leftover_mm > 0.5, "the corners keep material: {part:?}");
        assert!(open.max_leftover_mm < 0.1, "{open:?} against {part:?}");
        assert!(part.max_gouge_mm < 0.02 && open.max_gouge_mm < 0.02, "{part:?}");
    }
}

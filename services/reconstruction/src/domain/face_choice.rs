//! Automatic face choice: the fewest orientations of the part about the machine's A axis from
//! which the tools reach its surface, with the coverage each adds.
//!
//! The surface is sampled evenly (a cloud decimated to one point per `cell_mm` voxel, a mesh's
//! triangles sampled at `cell_mm`), so a sample stands for about `cell_mm²` of surface. For each
//! candidate orientation (every `step_deg` around the A axis) the samples are seen from above in
//! that orientation's view frame:
//!
//! 1. `H`: the highest sample per `cell_mm` cell (cells without any: the lowest height less 1 mm,
//!    air the tool can go down into);
//! 2. `M`: `H` closed by a flat disk of radius `reach_radius_mm` (dilation, then erosion): the
//!    surface a tool of that radius coming from above leaves; a pocket or slot narrower than the
//!    tool stays filled to its rim;
//! 3. a sample is **reached** from that orientation when it is no lower than the lowest `M` of its
//!    cell and the 8 around it, less `tolerance_mm`. The neighbourhood makes the side of a step (a
//!    wall, cut by the tool's side) reached from above, while anything under an overhang (an
//!    undercut) or at the bottom of a too-narrow pocket is not.
//!
//! A point cloud has no surface under what the scanner saw (the part stands on the table): a cap
//! under its footprint, at its lowest height, with the table a few cells thick under it, hides
//! the inside of the cloud from orientations that look up at it (and keeps a side view from
//! reaching the part's lowest layer by going down past it), and walls under the surface seen
//! from above, from each cell's highest point down to its lowest neighbour's, hide it from
//! orientations that look from the side (without them a pocket's floor or the far side of a top
//! surface would be seen through the hollow cloud and count as reached). A closed mesh hides its
//! own inside.
//!
//! The choice is exact where it can be: for `k = 1, 2, …` faces, every `k`-subset of the
//! candidates is tried while there are at most [`EXACT_SUBSETS`] of them (greedy beyond), and the
//! smallest `k` whose best subset leaves less than `min_gain_pct` of the surface for another face
//! to add is taken; subsets within `min_gain_pct` of that best count as equal, so the fewest
//! faces within that margin are taken, and of those the one that turns the part least (`+Z`
//! when it does about as well; never a face that adds nothing). A cloud's candidates stop
//! at |A| = 90°: beyond, a view looks up into what the scanner never saw. What no candidate
//! reaches is reported as regions (centre, extent, area).

use std::collections::HashMap;

use depthmill_geometry::raster::{Roi, grid_for_roi, raster_cell, try_rasterize_max};
use depthmill_geometry::{CloudPoint, Face, HeightMap, Mesh, PointCloud};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::domain::error::{ReconError, Result};
use crate::domain::filters::voxel_keep_mask;
use crate::domain::image_ops::{grey_dilate_disk, grey_erode_disk};

/// Default angle between candidate orientations, degrees.
pub const DEFAULT_STEP_DEG: f64 = 15.0;
/// Default most faces chosen.
pub const DEFAULT_MAX_FACES: u32 = 4;
/// Default least surface share a face must add to be worth another setup, percent.
pub const DEFAULT_MIN_GAIN_PCT: f64 = 1.0;
/// Default sampling cell, mm.
pub const DEFAULT_CELL_MM: f64 = 0.5;
/// Default reach radius: the default finishing tool's (ball-3) radius, mm.
pub const DEFAULT_REACH_RADIUS_MM: f64 = 1.5;
/// Default height tolerance of the reach test, mm.
pub const DEFAULT_TOLERANCE_MM: f64 = 0.2;
/// Most subsets tried exactly for one face count; beyond, faces are added greedily.
pub const EXACT_SUBSETS: u64 = 20_000;
/// Most surface samples; a finer cell that would give more is coarsened.
pub const MAX_SAMPLES: usize = 400_000;
/// Layers of occluders under a cloud's cap (the table it stood on), each a sampling cell apart:
/// enough that a sample on the part's lowest layer has solid under it in every view.
const TABLE_LAYERS: u32 = 2;
/// Unreached regions listed in the report, largest first.
const MAX_REGIONS: usize = 8;

/// The `reconstruct.face_choice` object of a job: how faces are chosen when the job names none.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaceChoiceOptions {
    #[serde(default)]
    pub step_deg: Option<f64>,
    #[serde(default)]
    pub max_faces: Option<u32>,
    #[serde(default)]
    pub min_gain_pct: Option<f64>,
    #[serde(default)]
    pub cell_mm: Option<f64>,
    #[serde(default)]
    pub reach_radius_mm: Option<f64>,
    #[serde(default)]
    pub tolerance_mm: Option<f64>,
}

/// [`FaceChoiceOptions`] after defaults and checks.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FaceChoiceSettings {
    pub step_deg: f64,
    pub max_faces: u32,
    pub min_gain_pct: f64,
    pub cell_mm: f64,
    pub reach_radius_mm: f64,
    pub tolerance_mm: f64,
}

impl Default for FaceChoiceSettings {
    fn default() -> Self {
        FaceChoiceSettings {
            step_deg: DEFAULT_STEP_DEG,
            max_faces: DEFAULT_MAX_FACES,
            min_gain_pct: DEFAULT_MIN_GAIN_PCT,
            cell_mm: DEFAULT_CELL_MM,
            reach_radius_mm: DEFAULT_REACH_RADIUS_MM,
            tolerance_mm: DEFAULT_TOLERANCE_MM,
        }
    }
}

impl FaceChoiceOptions {
    /// Applies defaults and checks every value, naming the job field at fault.
    pub fn resolve(&self) -> Result<FaceChoiceSettings> {
        let field = |f: &str| format!("reconstruct.face_choice.{f}");
        let step_deg = self.step_deg.unwrap_or(DEFAULT_STEP_DEG);
        if !(step_deg.is_finite() && (1.0..=180.0).contains(&step_deg)) {
            return Err(ReconError::param(field("step_deg"), step_deg, "must be in [1, 180] degrees"));
        }
        let max_faces = self.max_faces.unwrap_or(DEFAULT_MAX_FACES);
        if !(1..=8).contains(&max_faces) {
            return Err(ReconError::param(field("max_faces"), max_faces, "must be in 1..=8"));
        }
        let min_gain_pct = self.min_gain_pct.unwrap_or(DEFAULT_MIN_GAIN_PCT);
        if !(min_gain_pct.is_finite() && (0.0..=100.0).contains(&min_gain_pct)) {
            return Err(ReconError::param(
                field("min_gain_pct"),
                min_gain_pct,
                "must be in [0, 100] percent",
            ));
        }
        let cell_mm = self.cell_mm.unwrap_or(DEFAULT_CELL_MM);
        if !(cell_mm.is_finite() && (0.01..=50.0).contains(&cell_mm)) {
            return Err(ReconError::param(field("cell_mm"), cell_mm, "must be in [0.01, 50] mm"));
        }
        let reach_radius_mm = self.reach_radius_mm.unwrap_or(DEFAULT_REACH_RADIUS_MM);
        if !(reach_radius_mm.is_finite() && (0.0..=100.0).contains(&reach_radius_mm)) {
            return Err(ReconError::param(
                field("reach_radius_mm"),
                reach_radius_mm,
                "must be in [0, 100] mm",
            ));
        }
        let tolerance_mm = self.tolerance_mm.unwrap_or(DEFAULT_TOLERANCE_MM);
        if !(tolerance_mm.is_finite() && (0.0..=10.0).contains(&tolerance_mm)) {
            return Err(ReconError::param(field("tolerance_mm"), tolerance_mm, "must be in [0, 10] mm"));
        }
        Ok(FaceChoiceSettings { step_deg, max_faces, min_gain_pct, cell_mm, reach_radius_mm, tolerance_mm })
    }
}

/// The surface as even samples, plus occluders that hide but are not surface to reach.
#[derive(Debug, Clone, Default)]
pub struct SurfaceSamples {
    pub points: Vec<Point3<f64>>,
    /// Points that block the view but need no tool (the cap under a cloud).
    pub occluders: Vec<Point3<f64>>,
    /// Largest turn about A worth trying, degrees: 90 for a cloud (what lies beyond was never
    /// measured: a view from below would look into it through its open bottom), 180 for a mesh.
    pub max_turn_deg: f64,
    /// The sampling cell actually used, mm (coarsened from the requested one for huge parts).
    pub cell_mm: f64,
    /// A scan's body as the scanner saw it from above (the part solid under it, unseen regions
    /// lidded at the height around them), with the height it must stand over a sample's line of
    /// sight to hide it, mm: a turned view reaches only the samples it sees past that body
    /// ([`crate::domain::pipeline::visible_from`]), as that face's depth map will.
    pub body: Option<(HeightMap, f64)>,
}

/// A cell size no finer than `cell_mm` that keeps about `area_mm2` under [`MAX_SAMPLES`] samples.
fn sampling_cell(cell_mm: f64, area_mm2: f64) -> f64 {
    cell_mm.max((area_mm2 / MAX_SAMPLES as f64).sqrt())
}

impl SurfaceSamples {
    /// Samples of a point cloud: one point per `cell_mm` voxel; as occluders, a cap under the
    /// footprint seen from above (+Z) at the lowest height of the cloud with two more
    /// layers (the table) under it, and each footprint cell's wall down to its lowest 4-neighbour.
    pub fn from_cloud(cloud: &PointCloud, cell_mm: f64) -> Result<SurfaceSamples> {
        let finite: Vec<Point3<f32>> =
            cloud.points.iter().copied().filter(|p| p.coords.iter().all(|c| c.is_finite())).collect();
        let Some(roi) = Roi::around(&finite, cell_mm) else {
            return Err(ReconError::Empty("face choice: no finite points".into()));
        };
        // The +Z footprint's area bounds the surface from below; the sides add about as much.
        let cell = sampling_cell(cell_mm, 4.0 * roi.width_mm() * roi.height_mm());
        let keep = voxel_keep_mask(&finite, cell)?;
        let points: Vec<Point3<f64>> =
            finite.iter().zip(&keep).filter(|(_, k)| **k).map(|(p, _)| p.at()).collect();
        let z_min = points.iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
        let grid = grid_for_roi(&roi, cell)?;
        let (top, _) = try_rasterize_max(&points, &grid)?;
        let top_at = |col: i64, row: i64| -> f64 {
            if col < 0 || row < 0 {
                return z_min;
            }
            top.get(col as u32, row as u32).filter(|z| z.is_finite()).map_or(z_min, f64::from)
        };
        let mut occluders = Vec::new();
        for row in 0..top.height() {
            for col in 0..top.width() {
                let Some(t) = top.get(col, row).filter(|z| z.is_finite()).map(f64::from) else { continue };
                let (x, y) = grid.cell_center(col, row);
                // The cap, and the table under it: nothing reaches the part's underside by
                // going down past its lowest point.
                for k in 0..=TABLE_LAYERS {
                    occluders.push(Point3::new(x, y, z_min - f64::from(k) * cell));
                }
                // The wall down to the lowest 4-neighbour: the body under the surface seen from
                // above is solid to its outline, so a side view does not look through it.
                let (c, r) = (i64::from(col), i64::from(row));
                let lo = [(c - 1, r), (c + 1, r), (c, r - 1), (c, r + 1)]
                    .into_iter()
                    .map(|(cc, rr)| top_at(cc, rr))
                    .fold(t, f64::min)
                    .max(z_min);
                let mut z = t - cell;
                while z > lo {
                    occluders.push(Point3::new(x, y, z));
                    z -= cell;
                }
            }
        }
        Ok(SurfaceSamples { points, occluders, cell_mm: cell, max_turn_deg: 90.0, body: None })
    }

    /// Samples of a mesh: each triangle sampled on a barycentric lattice of about `cell_mm`, then
    /// one sample per `cell_mm` voxel.
    pub fn from_mesh(mesh: &Mesh, cell_mm: f64) -> Result<SurfaceSamples> {
        let area: f64 = (0..mesh.triangles.len())
            .map(|t| {
                let [a, b, c] = mesh.triangle(t);
                0.5 * (b - a).cross(&(c - a)).norm()
            })
            .filter(|a| a.is_finite())
            .sum();
        if area <= 0.0 {
            return Err(ReconError::Empty("face choice: the mesh has no triangle with an area".into()));
        }
        let cell = sampling_cell(cell_mm, area);
        let mut raw = Vec::new();
        for t in 0..mesh.triangles.len() {
            let [a, b, c] = mesh.triangle(t);
            let longest = (b - a).norm().max((c - b).norm()).max((a - c).norm());
            if !longest.is_finite() {
                continue;
            }
            let m = ((longest / cell).ceil() as usize).clamp(1, 4096);
            // Lattice points i/m, j/m with i + j <= m, shifted to the sub-triangles' centroids.
            for i in 0..m {
                for j in 0..(m - i) {
                    let u = (i as f64 + 1.0 / 3.0) / m as f64;
                    let v = (j as f64 + 1.0 / 3.0) / m as f64;
                    raw.push(a + (b - a) * u + (c - a) * v);
                }
            }
        }
        let keep = voxel_keep_mask(&raw, cell)?;
        let points = raw.iter().zip(&keep).filter(|(_, k)| **k).map(|(p, _)| *p).collect();
        Ok(SurfaceSamples { points, occluders: Vec::new(), cell_mm: cell, max_turn_deg: 180.0, body: None })
    }
}

/// The candidate orientations: A = 0, ±step, ±2·step, … up to 180 (each once), keeping those
/// with |A| <= `max_abs_deg`.
pub fn candidates(step_deg: f64, max_abs_deg: f64) -> Vec<Face> {
    let n = (360.0 / step_deg).floor().max(1.0) as i64;
    let mut out = Vec::new();
    for k in 0..n {
        let mut a = k as f64 * step_deg;
        if a > 180.0 + 1e-9 {
            a -= 360.0;
        }
        if a.abs() <= max_abs_deg + 1e-9 {
            out.push(if a == 0.0 { Face::PosZ } else { Face::A { angle_deg: a } });
        }
    }
    out
}

/// How far a face turns the part, degrees: what the choice keeps low among subsets that reach
/// about as much.
fn turn_of(f: Face) -> f64 {
    match f {
        Face::A { angle_deg } => angle_deg.abs(),
        _ => 0.0,
    }
}

/// Which samples the tools reach from above with the part turned to `face` (module docs).
pub fn reached(samples: &SurfaceSamples, face: Face, s: &FaceChoiceSettings) -> Result<Vec<bool>> {
    let rot = face.view_from_part();
    let view: Vec<Point3<f64>> = samples.points.iter().map(|p| rot * p).collect();
    let occ: Vec<Point3<f64>> = samples.occluders.iter().map(|p| rot * p).collect();
    if view.is_empty() {
        return Ok(Vec::new());
    }
    let all: Vec<Point3<f64>> = view.iter().chain(&occ).copied().collect();
    let margin = s.reach_radius_mm + 2.0 * samples.cell_mm;
    let roi = Roi::around(&all, margin)
        .ok_or_else(|| ReconError::Empty("face choice: no finite samples".into()))?;
    let grid = grid_for_roi(&roi, samples.cell_mm)?;
    let (mut h, _) = try_rasterize_max(&all, &grid)?;
    let floor = all.iter().map(|p| p.z).fold(f64::INFINITY, f64::min) as f32 - 1.0;
    for z in h.data_mut() {
        if !z.is_finite() {
            *z = floor;
        }
    }
    let m = closing_then_neighbourhood_min(&h, s.reach_radius_mm)?;
    let tol = s.tolerance_mm as f32;
    let mut out: Vec<bool> = view
        .iter()
        .map(|p| match raster_cell(&grid, p.x, p.y) {
            Some((c, r)) => m.get(c, r).is_none_or(|lo| p.z as f32 >= lo - tol),
            None => true,
        })
        .collect();
    if let Some((body, occlusion_tol)) = samples.body.as_ref().filter(|_| face != Face::PosZ) {
        let up = rot.inverse() * Vector3::z();
        let points: Vec<Point3<f32>> = samples.points.iter().map(depthmill_geometry::cloud::single).collect();
        let seen = crate::domain::pipeline::visible_from(&points, &up, body, *occlusion_tol);
        for (o, v) in out.iter_mut().zip(seen) {
            *o &= v;
        }
    }
    Ok(out)
}

/// `H` closed by a flat disk of `radius_mm`, then the min over each cell's 3 × 3 neighbourhood.
fn closing_then_neighbourhood_min(h: &HeightMap, radius_mm: f64) -> Result<HeightMap> {
    let closed = grey_erode_disk(&grey_dilate_disk(h, radius_mm)?, radius_mm)?;
    let (w, hh) = (closed.width() as i64, closed.height() as i64);
    let src = closed.data().to_vec();
    let mut out = closed;
    for (i, o) in out.data_mut().iter_mut().enumerate() {
        let (c, r) = (i as i64 % w, i as i64 / w);
        let mut lo = f32::INFINITY;
        for dr in -1..=1 {
            for dc in -1..=1 {
                let (cc, rr) = (c + dc, r + dr);
                if (0..w).contains(&cc) && (0..hh).contains(&rr) {
                    lo = lo.min(src[(rr * w + cc) as usize]);
                }
            }
        }
        *o = lo;
    }
    Ok(out)
}

/// An orientation left out of the choice.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ExcludedFace {
    /// The face as text (`A=-30`).
    pub face: String,
    /// Share of that face's depth map the scan measured when it was chosen, percent.
    pub measured_pct: f64,
}

/// One chosen face.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ChosenFace {
    /// The face as text (`+Z`, `A=90`).
    pub face: String,
    /// Surface share this face adds to the faces before it, percent.
    pub gain_pct: f64,
    /// Surface share reached by this face and the ones before it, percent.
    pub cumulative_pct: f64,
}

/// A candidate orientation on its own.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct CandidateReach {
    pub face: String,
    /// Surface share reached from this orientation alone, percent.
    pub reach_pct: f64,
}

/// Surface no candidate orientation reaches.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct UnreachedRegion {
    /// Centre, part frame, mm.
    pub center_mm: [f64; 3],
    /// Extent of its bounding box, mm.
    pub size_mm: [f64; 3],
    /// Surface area, mm² (samples times the cell's area).
    pub area_mm2: f64,
}

/// What the face choice decided and why (in the reconstruct report).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct FaceChoiceReport {
    pub settings: FaceChoiceSettings,
    /// The sampling cell used (the setting, coarsened for a very large part), mm.
    pub cell_mm: f64,
    pub samples: usize,
    pub candidates: Vec<CandidateReach>,
    /// The faces, in the order they are machined: each adds the most of what is left.
    pub chosen: Vec<ChosenFace>,
    /// Surface the chosen faces reach, percent.
    pub covered_pct: f64,
    /// Surface some candidate reaches that the chosen faces leave (each remaining candidate adds
    /// less than `min_gain_pct`, or `max_faces` was reached), percent.
    pub left_reachable_pct: f64,
    /// Surface no candidate orientation reaches (undercuts, pockets narrower than the reach
    /// radius, the surface along the A axis), percent.
    pub unreached_pct: f64,
    /// The largest unreached regions.
    pub unreached_regions: Vec<UnreachedRegion>,
    /// True when every face count was searched exhaustively (else greedily past some count).
    pub exact: bool,
    /// Orientations left out of the choice: chosen before, their depth maps were mostly assumed
    /// (the scan hardly saw the part from that side), so a program from them would cut blind.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub excluded: Vec<ExcludedFace>,
    pub seconds: f64,
}

/// A set of samples as bits.
#[derive(Debug, Clone, PartialEq)]
struct Bits(Vec<u64>);

impl Bits {
    fn from_bools(b: &[bool]) -> Bits {
        let mut v = vec![0u64; b.len().div_ceil(64)];
        for (i, &x) in b.iter().enumerate() {
            if x {
                v[i / 64] |= 1 << (i % 64);
            }
        }
        Bits(v)
    }
    fn count(&self) -> u64 {
        self.0.iter().map(|w| u64::from(w.count_ones())).sum()
    }
    fn union_count(sets: &[&Bits]) -> u64 {
        let n = sets.first().map_or(0, |s| s.0.len());
        (0..n).map(|i| u64::from(sets.iter().fold(0u64, |a, s| a | s.0[i]).count_ones())).sum()
    }
    fn or(&mut self, o: &Bits) {
        for (a, b) in self.0.iter_mut().zip(&o.0) {
            *a |= b;
        }
    }
    fn get(&self, i: usize) -> bool {
        self.0[i / 64] >> (i % 64) & 1 == 1
    }
}

fn binomial(n: u64, k: u64) -> u64 {
    let mut r: u64 = 1;
    for i in 0..k {
        r = r.saturating_mul(n - i) / (i + 1);
    }
    r
}

/// Calls `f` with every `k`-subset of `0..n` (as sorted indices).
fn for_each_subset(n: usize, k: usize, f: &mut dyn FnMut(&[usize])) {
    fn rec(start: usize, n: usize, k: usize, cur: &mut Vec<usize>, f: &mut dyn FnMut(&[usize])) {
        if cur.len() == k {
            f(cur);
            return;
        }
        for i in start..n {
            if n - i < k - cur.len() {
                break;
            }
            cur.push(i);
            rec(i + 1, n, k, cur, f);
            cur.pop();
        }
    }
    rec(0, n, k, &mut Vec::with_capacity(k), f);
}

/// A subset of the candidates, the samples it covers, and the most any subset of its size covers.
type Best = (Vec<usize>, u64, u64);

/// The best subset of `sets` of each size `1..=max_k` (most samples covered; ties: the earlier
/// subset in lexicographic order, so lower candidate indices, A nearer 0, win). Exhaustive while
/// a size has at most [`EXACT_SUBSETS`] subsets, then greedy from the best smaller one.
/// Returns, per size, the subset, its count and the most any subset of that size covers
/// ([`Best`]), and whether every size was exhaustive.
fn best_subsets(sets: &[Bits], max_k: usize, tol: u64, cost: &[f64]) -> (Vec<Best>, bool) {
    let n = sets.len();
    let mut out: Vec<Best> = Vec::new();
    let mut exact = true;
    for k in 1..=max_k.min(n) {
        if binomial(n as u64, k as u64) <= EXACT_SUBSETS {
            let mut most = 0;
            for_each_subset(n, k, &mut |s| {
                let refs: Vec<&Bits> = s.iter().map(|&i| &sets[i]).collect();
                most = most.max(Bits::union_count(&refs));
            });
            // Of the subsets within `tol` of the most, the one that turns the part least.
            let (s, c) = least_turning(sets, k, most.saturating_sub(tol), cost).unwrap_or_default();
            out.push((s, c, most));
        } else {
            exact = false;
            let Some((prev, ..)) = out.last().cloned() else { break };
            let mut acc = Bits(vec![0; sets[0].0.len()]);
            for &i in &prev {
                acc.or(&sets[i]);
            }
            let mut best: Option<(usize, u64)> = None;
            for (i, s) in sets.iter().enumerate() {
                if prev.contains(&i) {
                    continue;
                }
                let c = Bits::union_count(&[&acc, s]);
                if best.is_none_or(|(_, b)| c > b) {
                    best = Some((i, c));
                }
            }
            let Some((i, c)) = best else { break };
            let mut s = prev;
            s.push(i);
            out.push((s, c, c));
        }
    }
    (out, exact)
}

/// Of the `k`-subsets of `sets` covering at least `floor` samples, the one that turns the part
/// least (then the one that covers more, then the first in lexicographic order); exhaustive.
fn least_turning(sets: &[Bits], k: usize, floor: u64, cost: &[f64]) -> Option<(Vec<usize>, u64)> {
    let turn = |s: &[usize]| s.iter().map(|&i| cost.get(i).copied().unwrap_or(0.0)).sum::<f64>();
    let mut best: Option<(Vec<usize>, u64, f64)> = None;
    for_each_subset(sets.len(), k, &mut |s| {
        let refs: Vec<&Bits> = s.iter().map(|&i| &sets[i]).collect();
        let c = Bits::union_count(&refs);
        if c < floor {
            return;
        }
        let t = turn(s);
        let better = match &best {
            None => true,
            Some((_, bc, bt)) => match t.total_cmp(bt) {
                std::cmp::Ordering::Less => true,
                std::cmp::Ordering::Equal => c > *bc,
                std::cmp::Ordering::Greater => false,
            },
        };
        if better {
            best = Some((s.to_vec(), c, t));
        }
    });
    best.map(|(s, c, _)| (s, c))
}

/// The faces to take: the size [`enough`] finds, then the fewest faces (turning least) within
/// `tol` samples of that size's best: a smaller set about as good as the best needs no more.
fn pick_faces(
    sets: &[Bits],
    best: &[Best],
    any: u64,
    n: u64,
    min_gain_pct: f64,
    tol: u64,
    cost: &[f64],
) -> Vec<usize> {
    let Some((pick, _, most)) = enough(best, any, n, min_gain_pct) else { return Vec::new() };
    let floor = most.saturating_sub(tol);
    for (j, (_, _, most_j)) in best.iter().enumerate().take(pick.len().saturating_sub(1)) {
        let k = j + 1;
        if *most_j >= floor
            && binomial(sets.len() as u64, k as u64) <= EXACT_SUBSETS
            && let Some((s, _)) = least_turning(sets, k, floor, cost)
        {
            return s;
        }
    }
    pick.clone()
}

/// Of `best` (per size, [`best_subsets`]), the first whose best count leaves less than
/// `min_gain_pct` of `n` samples of the `any` some candidate reaches, else the last.
fn enough(best: &[Best], any: u64, n: u64, min_gain_pct: f64) -> Option<&Best> {
    let pct = |c: u64| 100.0 * c as f64 / n.max(1) as f64;
    best.iter().find(|(_, _, most)| pct(any - most) < min_gain_pct || *most == any).or(best.last())
}

/// Chooses the faces (module docs). `progress` gets a fraction in [0, 1].
pub fn choose_faces(
    samples: &SurfaceSamples,
    s: &FaceChoiceSettings,
    exclude: &[ExcludedFace],
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Result<(Vec<Face>, FaceChoiceReport)> {
    let started = std::time::Instant::now();
    let n = samples.points.len();
    if n == 0 {
        return Err(ReconError::Empty("face choice: no surface samples".into()));
    }
    let cands: Vec<Face> = candidates(s.step_deg, samples.max_turn_deg)
        .into_iter()
        .filter(|f| !exclude.iter().any(|e| e.face == f.to_string()))
        .collect();
    if cands.is_empty() {
        return Err(ReconError::Empty("face choice: every candidate orientation is excluded".into()));
    }
    let reach: Vec<Vec<bool>> = cands.par_iter().map(|&f| reached(samples, f, s)).collect::<Result<_>>()?;
    if cancelled() {
        return Err(ReconError::Cancelled);
    }
    let sets: Vec<Bits> = reach.iter().map(|r| Bits::from_bools(r)).collect();
    let pct = |c: u64| 100.0 * c as f64 / n as f64;
    let all_refs: Vec<&Bits> = sets.iter().collect();
    let any = Bits::union_count(&all_refs);
    // Subsets within `min_gain_pct` of the best count as equal (turning the part is worth what a
    // face must add); the least turning wins.
    let tol = (s.min_gain_pct / 100.0 * n as f64).floor() as u64;
    let costs: Vec<f64> = cands.iter().map(|&f| turn_of(f)).collect();
    let (best, exact) = best_subsets(&sets, s.max_faces as usize, tol, &costs);
    // The smallest k whose best subset leaves less than min_gain_pct of what some candidate
    // reaches (no further face can add as much), else the largest searched; then the fewest
    // faces, turning least, within min_gain_pct of that size's best (judged by the best's count,
    // so the tie-break never asks for one more face, and a face adding nothing is not taken).
    let pick = pick_faces(&sets, &best, any, n as u64, s.min_gain_pct, tol, &costs);
    // Order the chosen faces by what each adds: the largest first.
    let mut order: Vec<usize> = Vec::new();
    let mut acc = Bits(vec![0; sets[0].0.len()]);
    let mut chosen = Vec::new();
    let mut left: Vec<usize> = pick.clone();
    while !left.is_empty() {
        let (j, &i) = left
            .iter()
            .enumerate()
            .max_by(|(_, a), (_, b)| {
                Bits::union_count(&[&acc, &sets[**a]])
                    .cmp(&Bits::union_count(&[&acc, &sets[**b]]))
                    .then(b.cmp(a))
            })
            .ok_or_else(|| ReconError::Empty("face choice: no candidate".into()))?;
        let before = acc.count();
        acc.or(&sets[i]);
        let after = acc.count();
        chosen.push(ChosenFace {
            face: cands[i].to_string(),
            gain_pct: pct(after - before),
            cumulative_pct: pct(after),
        });
        order.push(i);
        left.remove(j);
    }
    let covered = acc.count();
    let mut union_all = Bits(vec![0; sets[0].0.len()]);
    for b in &sets {
        union_all.or(b);
    }
    let unreached: Vec<Point3<f64>> =
        (0..n).filter(|&i| !union_all.get(i)).map(|i| samples.points[i]).collect();
    let report = FaceChoiceReport {
        settings: *s,
        cell_mm: samples.cell_mm,
        samples: n,
        candidates: cands
            .iter()
            .zip(&sets)
            .map(|(f, b)| CandidateReach { face: f.to_string(), reach_pct: pct(b.count()) })
            .collect(),
        chosen,
        covered_pct: pct(covered),
        left_reachable_pct: pct(any - covered),
        unreached_pct: pct(n as u64 - any),
        unreached_regions: regions(
            &unreached,
            samples.cell_mm,
            (2.0 * s.reach_radius_mm).max(2.0 * samples.cell_mm),
        ),
        exact,
        excluded: exclude.to_vec(),
        seconds: started.elapsed().as_secs_f64(),
    };
    // A lone face straight up is the plain 3-axis job; several turn the part on the A axis.
    let faces = order.iter().map(|&i| cands[i]).collect();
    Ok((faces, report))
}

/// Connected groups of `points` (26-neighbour voxels of `link_mm`), largest first.
fn regions(points: &[Point3<f64>], cell_mm: f64, link_mm: f64) -> Vec<UnreachedRegion> {
    let key = |p: &Point3<f64>| -> [i64; 3] {
        [(p.x / link_mm).floor() as i64, (p.y / link_mm).floor() as i64, (p.z / link_mm).floor() as i64]
    };
    let mut voxels: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
    for (i, p) in points.iter().enumerate() {
        voxels.entry(key(p)).or_default().push(i);
    }
    let mut seen: HashMap<[i64; 3], bool> = voxels.keys().map(|k| (*k, false)).collect();
    let mut out = Vec::new();
    let keys: Vec<[i64; 3]> = {
        let mut k: Vec<[i64; 3]> = voxels.keys().copied().collect();
        k.sort_unstable();
        k
    };
    for start in keys {
        if seen.get(&start).copied().unwrap_or(true) {
            continue;
        }
        seen.insert(start, true);
        let mut stack = vec![start];
        let mut members: Vec<usize> = Vec::new();
        while let Some(v) = stack.pop() {
            members.extend(voxels.get(&v).into_iter().flatten());
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let w = [v[0] + dx, v[1] + dy, v[2] + dz];
                        if let Some(s) = seen.get_mut(&w)
                            && !*s
                        {
                            *s = true;
                            stack.push(w);
                        }
                    }
                }
            }
        }
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for &i in &members {
            lo = lo.inf(&points[i].coords);
            hi = hi.sup(&points[i].coords);
        }
        let c = (lo + hi) / 2.0;
        let e = hi - lo;
        out.push(UnreachedRegion {
            center_mm: [c.x, c.y, c.z],
            size_mm: [e.x, e.y, e.z],
            area_mm2: members.len() as f64 * cell_mm * cell_mm,
        });
    }
    out.sort_by(|a, b| b.area_mm2.total_cmp(&a.area_mm2));
    out.truncate(MAX_REGIONS);
    out
}

impl FaceChoiceReport {
    /// One line per unreached region, for the job's diagnostics (empty when all is reached).
    pub fn diagnostics(&self) -> Vec<String> {
        let mut out = Vec::new();
        for r in self.unreached_regions.iter().filter(|r| r.area_mm2 >= 1.0) {
            out.push(format!(
                "about {:.0} mm² of surface around ({:.1}, {:.1}, {:.1}) mm, {:.1} x {:.1} x {:.1} mm, is \
                 reached from no A-axis orientation (an undercut, a pocket narrower than {:.1} mm, or \
                 the surface facing along the A axis): it is left as it comes out of the faces' cuts",
                r.area_mm2,
                r.center_mm[0],
                r.center_mm[1],
                r.center_mm[2],
                r.size_mm[0],
                r.size_mm[1],
                r.size_mm[2],
                2.0 * self.settings.reach_radius_mm,
            ));
        }
        out
    }
}

#[cfg(test)]
pub(crate) mod tests;

//! How much of the part, seen from above, the scan measured: the part's top-view silhouette (the
//! cells where its mesh has a top surface) against the cells the cloud has a point in.
//!
//! The coverage of [`super::ScanSession::holes`] looks at the cloud alone, so a surface the
//! scanner never saw at the edge of what it did see (a steep flank of a cylinder lying on its
//! side, the far side of an overhang) reads as outside the part, and the stages after it treat it
//! as empty. The mesh the job started from says where the part is; the unseen part of its
//! silhouette is what the rescan aims at and what the report names, with where it is.

use depthmill_geometry::mesh_raster::rasterize_mesh;
use depthmill_geometry::raster::{COVERAGE_HOLE, Roi, grid_for_roi, try_rasterize_max};
use depthmill_geometry::{HeightMap, HeightMapMeta, Mesh};
use nalgebra::Point3;
use serde::Serialize;

use super::{HoleTarget, hole_components};

/// Unseen regions listed in the report, largest first.
const MAX_REGIONS: usize = 10;

/// The part's top-view silhouette on a grid (NaN where the mesh has no top surface).
#[derive(Debug, Clone)]
pub struct Silhouette {
    top: HeightMap,
    cells: usize,
}

/// The silhouette against a cloud.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SilhouetteCoverage {
    pub pixel_mm: f64,
    /// Cells where the part's mesh has a top surface.
    pub silhouette_cells: usize,
    /// Of those, cells with at least one point of the cloud.
    pub seen_cells: usize,
    /// `seen / silhouette · 100`.
    pub covered_pct: f64,
    /// Area of the silhouette with no point, mm².
    pub unseen_area_mm2: f64,
    /// The largest unseen regions (8-connected), largest first, at most ten.
    pub unseen_regions: Vec<HoleTarget>,
}

impl Silhouette {
    /// The mesh's top surface at cell centres on a `pixel_mm` grid over its X/Y extent. `None`
    /// for a mesh without a finite extent or a grid the rasteriser refuses (too many cells).
    pub fn of(mesh: &Mesh, pixel_mm: f64) -> Option<Self> {
        let b = mesh.bounds()?;
        let roi = Roi {
            x_min_mm: b.min.x - pixel_mm,
            y_min_mm: b.min.y - pixel_mm,
            x_max_mm: b.max.x + pixel_mm,
            y_max_mm: b.max.y + pixel_mm,
        };
        let grid: HeightMapMeta = grid_for_roi(&roi, pixel_mm).ok()?;
        let top = rasterize_mesh(mesh, &grid);
        let cells = top.data().iter().filter(|z| z.is_finite()).count();
        Some(Self { top, cells })
    }

    /// What of the silhouette `points` cover (part frame).
    pub fn coverage(&self, points: &[Point3<f64>]) -> SilhouetteCoverage {
        let meta = *self.top.meta();
        let p = meta.pixel_mm;
        let mask = self.unseen_mask(points);
        let unseen: Vec<f32> = mask.iter().map(|&u| if u { COVERAGE_HOLE } else { f32::NAN }).collect();
        let seen = self.cells - mask.iter().filter(|&&u| u).count();
        let mut regions = HeightMap::new(HeightMapMeta { z_min_mm: 0.0, z_max_mm: 1.0, ..meta }, unseen)
            .map(|m| hole_components(&m))
            .unwrap_or_default();
        regions.sort_by(|a, b| b.area_mm2.total_cmp(&a.area_mm2));
        regions.truncate(MAX_REGIONS);
        let unseen_cells = self.cells - seen;
        SilhouetteCoverage {
            pixel_mm: p,
            silhouette_cells: self.cells,
            seen_cells: seen,
            covered_pct: if self.cells > 0 { seen as f64 / self.cells as f64 * 100.0 } else { 0.0 },
            unseen_area_mm2: unseen_cells as f64 * p * p,
            unseen_regions: regions,
        }
    }

    /// Per cell of the grid: part of the silhouette with no point of `points` in it.
    fn unseen_mask(&self, points: &[Point3<f64>]) -> Vec<bool> {
        let seen = try_rasterize_max(points, self.top.meta()).ok().map(|(m, _)| m);
        self.top
            .data()
            .iter()
            .enumerate()
            .map(|(i, z)| z.is_finite() && !seen.as_ref().is_some_and(|m| m.data()[i].is_finite()))
            .collect()
    }

    /// Centres of the silhouette's cells with no point of `points` (part frame), mm.
    pub fn unseen_cells(&self, points: &[Point3<f64>]) -> Vec<[f64; 2]> {
        let meta = *self.top.meta();
        let w = meta.width as usize;
        let p = meta.pixel_mm;
        self.unseen_mask(points)
            .iter()
            .enumerate()
            .filter(|&(_, &u)| u)
            .map(|(i, _)| {
                [meta.origin_x_mm + ((i % w) as f64 + 0.5) * p, meta.origin_y_mm + ((i / w) as f64 + 0.5) * p]
            })
            .collect()
    }
}

impl SilhouetteCoverage {
    /// A line for the job's diagnostics when part of the silhouette went unseen.
    pub fn diagnostic(&self) -> Option<String> {
        let largest = self.unseen_regions.first()?;
        Some(format!(
            "the scan saw {:.2} % of the part's top-view silhouette: {:.1} mm² unseen in {}{} region(s), the largest {:.1} mm² around ({:.1}, {:.1}) mm (part frame); steep or hidden surface there has no data, and the maps treat it as empty",
            self.covered_pct,
            self.unseen_area_mm2,
            self.unseen_regions.len(),
            if self.unseen_regions.len() == MAX_REGIONS { "+" } else { "" },
            largest.area_mm2,
            largest.center_x_mm,
            largest.center_y_mm,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unseen_strip_is_counted_and_located() {
        let s = Silhouette::of(&Mesh::cuboid(20.0, 10.0, 5.0), 0.5).expect("silhouette");
        assert_eq!(s.cells, 40 * 20);
        // Points on the top everywhere but the strip 15 <= x < 20.
        let mut pts = Vec::new();
        for j in 0..20 {
            for i in 0..30 {
                pts.push(Point3::new(0.25 + 0.5 * f64::from(i), 0.25 + 0.5 * f64::from(j), 5.0));
            }
        }
        let c = s.coverage(&pts);
        assert_eq!((c.silhouette_cells, c.seen_cells), (800, 600));
        assert!((c.covered_pct - 75.0).abs() < 1e-9);
        assert!((c.unseen_area_mm2 - 50.0).abs() < 1e-9);
        assert_eq!(c.unseen_regions.len(), 1);
        let r = c.unseen_regions[0];
        assert!((r.center_x_mm - 17.5).abs() < 1e-9 && (r.center_y_mm - 5.0).abs() < 1e-9, "{r:?}");
        assert!(c.diagnostic().is_some_and(|d| d.contains("75.00 %") && d.contains("(17.5, 5.0)")));
        // Everything seen: no diagnostic.
        let all: Vec<Point3<f64>> = (0..40)
            .flat_map(|i| {
                (0..20).map(move |j| Point3::new(0.25 + 0.5 * f64::from(i), 0.25 + 0.5 * f64::from(j), 5.0))
            })
            .collect();
        let c = s.coverage(&all);
        assert_eq!((c.covered_pct, c.diagnostic()), (100.0, None));
    }
}

//! Obstacles of the cell (DESIGN §6: up to a few boxes, cylinders or spheres with a safety
//! distance: the table, the part, a conveyor, the CNC) and the arm's clearance from them.
//!
//! The arm is checked as its skeleton: the chain of DH frame origins from the base to the flange
//! and on to the scanner's optical origin, sampled every [`SAMPLE_MM`], plus the scanner's body as
//! a sphere of [`SCANNER_RADIUS_MM`] around its optical origin. Distances are signed (negative
//! inside an obstacle).

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use super::{CellLayout, PartPlacement, ScanError};
use depthmill_geometry::arm::ArmModel;

/// Spacing of the samples along each link of the skeleton, mm.
pub const SAMPLE_MM: f64 = 10.0;
/// Radius of the scanner's body around its optical origin, mm (an SLP-400 class head is about
/// 60 mm across).
pub const SCANNER_RADIUS_MM: f64 = 30.0;

/// An obstacle in the world (robot base) frame, mm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case", deny_unknown_fields)]
pub enum Obstacle {
    /// An axis-aligned box.
    Box { name: String, min_mm: [f64; 3], max_mm: [f64; 3] },
    /// A cylinder with a vertical axis through `center_mm` (x, y).
    Cylinder { name: String, center_mm: [f64; 2], radius_mm: f64, z_min_mm: f64, z_max_mm: f64 },
    /// A sphere.
    Sphere { name: String, center_mm: [f64; 3], radius_mm: f64 },
}

impl Obstacle {
    /// Its name.
    pub fn name(&self) -> &str {
        match self {
            Obstacle::Box { name, .. } | Obstacle::Cylinder { name, .. } | Obstacle::Sphere { name, .. } => {
                name
            }
        }
    }

    /// Signed distance from `p` to the obstacle (negative inside), mm.
    pub fn distance(&self, p: &Point3<f64>) -> f64 {
        match self {
            Obstacle::Box { min_mm, max_mm, .. } => {
                let d = Vector3::from_fn(|i, _| (min_mm[i] - p[i]).max(p[i] - max_mm[i]));
                let outside = d.map(|v| v.max(0.0)).norm();
                outside + d.max().min(0.0)
            }
            Obstacle::Cylinder { center_mm, radius_mm, z_min_mm, z_max_mm, .. } => {
                let dr = (p.x - center_mm[0]).hypot(p.y - center_mm[1]) - radius_mm;
                let dz = (z_min_mm - p.z).max(p.z - z_max_mm);
                dr.max(0.0).hypot(dz.max(0.0)) + dr.max(dz).min(0.0)
            }
            Obstacle::Sphere { center_mm, radius_mm, .. } => {
                (p - Point3::from(*center_mm)).norm() - radius_mm
            }
        }
    }

    /// Checks the numbers; `field` names it in errors (`scan.obstacles[i]`).
    pub fn validate(&self, field: &str) -> Result<(), ScanError> {
        let bad = |reason: &str| ScanError::InvalidOption {
            field: field.to_string(),
            value: format!("{self:?}"),
            reason: reason.to_string(),
        };
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        match self {
            Obstacle::Box { min_mm, max_mm, .. } => {
                if !finite(min_mm) || !finite(max_mm) || (0..3).any(|i| min_mm[i] >= max_mm[i]) {
                    return Err(bad("a box needs finite min_mm < max_mm on every axis"));
                }
            }
            Obstacle::Cylinder { center_mm, radius_mm, z_min_mm, z_max_mm, .. } => {
                let ok =
                    finite(center_mm) && radius_mm.is_finite() && *radius_mm > 0.0 && z_min_mm < z_max_mm;
                if !ok {
                    return Err(bad("a cylinder needs a finite centre, radius > 0 and z_min_mm < z_max_mm"));
                }
            }
            Obstacle::Sphere { center_mm, radius_mm, .. } => {
                let ok = finite(center_mm) && radius_mm.is_finite() && *radius_mm > 0.0;
                if !ok {
                    return Err(bad("a sphere needs a finite centre and radius > 0"));
                }
            }
        }
        Ok(())
    }
}

/// The cell's own obstacles: the table disc (30 mm thick below its top) and the part (its
/// bounding cylinder about the table's axis, so it holds at every table angle).
pub fn cell_obstacles(layout: &CellLayout, placement: &PartPlacement) -> Vec<Obstacle> {
    let c = [layout.table_axis_x_mm, layout.table_axis_y_mm];
    let half = placement.reach_mm();
    vec![
        Obstacle::Cylinder {
            name: "table".into(),
            center_mm: c,
            radius_mm: layout.table_radius_mm,
            z_min_mm: layout.table_top_z_mm - 30.0,
            z_max_mm: layout.table_top_z_mm,
        },
        Obstacle::Cylinder {
            name: "part".into(),
            center_mm: c,
            radius_mm: half.max(1.0),
            z_min_mm: layout.table_top_z_mm,
            z_max_mm: layout.table_top_z_mm + placement.height_mm().max(1.0),
        },
    ]
}

/// The smallest clearance of the arm at joints `q_deg` from `obstacles`: (distance, obstacle,
/// which part of the arm). `None` without obstacles.
pub fn clearance(arm: &ArmModel, q_deg: &[f64; 6], obstacles: &[Obstacle]) -> Option<(f64, String, String)> {
    if obstacles.is_empty() {
        return None;
    }
    let frames = arm.fk_all(q_deg);
    let pts: Vec<Point3<f64>> = frames.iter().map(|f| Point3::from(f.translation.vector)).collect();
    let mut best: Option<(f64, String, String)> = None;
    let mut consider = |d: f64, o: &Obstacle, what: &dyn Fn() -> String| {
        if best.as_ref().is_none_or(|b| d < b.0) {
            best = Some((d, o.name().to_string(), what()));
        }
    };
    for o in obstacles {
        for k in 0..pts.len() - 1 {
            let (a, b) = (pts[k], pts[k + 1]);
            let n = ((b - a).norm() / SAMPLE_MM).ceil().max(1.0) as usize;
            for s in 0..=n {
                let p = a + (b - a) * (s as f64 / n as f64);
                let link = |k: usize| match k {
                    6 => "the scanner bracket".to_string(),
                    k => format!("the link from frame {k} to frame {}", k + 1),
                };
                consider(o.distance(&p), o, &|| link(k));
            }
        }
        consider(o.distance(&pts[7]) - SCANNER_RADIUS_MM, o, &|| "the scanner".to_string());
    }
    best
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// Distance by brute force: the nearest of many points sampled on the surface (outside), or
    /// minus the nearest face (inside), for a box.
    #[test]
    fn box_and_cylinder_distances_match_a_brute_force() {
        let mut rng = StdRng::seed_from_u64(5);
        let b = Obstacle::Box { name: "b".into(), min_mm: [-10.0, -5.0, 0.0], max_mm: [10.0, 5.0, 8.0] };
        let c = Obstacle::Cylinder {
            name: "c".into(),
            center_mm: [1.0, 2.0],
            radius_mm: 6.0,
            z_min_mm: -3.0,
            z_max_mm: 4.0,
        };
        // Surface samples of each.
        let mut box_pts = Vec::new();
        let mut cyl_pts = Vec::new();
        for _ in 0..60_000 {
            let (u, v) = (rng.random::<f64>(), rng.random::<f64>());
            let face = rng.random_range(0..6);
            let p = match face {
                0 => [-10.0, -5.0 + 10.0 * u, 8.0 * v],
                1 => [10.0, -5.0 + 10.0 * u, 8.0 * v],
                2 => [-10.0 + 20.0 * u, -5.0, 8.0 * v],
                3 => [-10.0 + 20.0 * u, 5.0, 8.0 * v],
                4 => [-10.0 + 20.0 * u, -5.0 + 10.0 * v, 0.0],
                _ => [-10.0 + 20.0 * u, -5.0 + 10.0 * v, 8.0],
            };
            box_pts.push(Point3::from(p));
            let t = std::f64::consts::TAU * u;
            let q = match face % 3 {
                0 => [1.0 + 6.0 * t.cos(), 2.0 + 6.0 * t.sin(), -3.0 + 7.0 * v],
                1 => [1.0 + 6.0 * v.sqrt() * t.cos(), 2.0 + 6.0 * v.sqrt() * t.sin(), -3.0],
                _ => [1.0 + 6.0 * v.sqrt() * t.cos(), 2.0 + 6.0 * v.sqrt() * t.sin(), 4.0],
            };
            cyl_pts.push(Point3::from(q));
        }
        for _ in 0..200 {
            let p = Point3::new(
                rng.random_range(-25.0..25.0),
                rng.random_range(-20.0..20.0),
                rng.random_range(-15.0..20.0),
            );
            for (o, pts) in [(&b, &box_pts), (&c, &cyl_pts)] {
                let d = o.distance(&p);
                let near = pts.iter().map(|q| (q - p).norm()).fold(f64::INFINITY, f64::min);
                // Outside the distance is the nearest surface point; inside, minus it.
                let expect = if d >= 0.0 { near } else { -near };
                assert!((d - expect).abs() < 0.35, "{} at {p:?}: {d} vs {expect}", o.name());
            }
        }
        let s = Obstacle::Sphere { name: "s".into(), center_mm: [0.0, 0.0, 0.0], radius_mm: 2.0 };
        assert!((s.distance(&Point3::new(3.0, 4.0, 0.0)) - 3.0).abs() < 1e-12);
    }

    #[test]
    fn the_arm_at_home_clears_the_cell_and_a_box_around_it_does_not() {
        let arm = ArmModel::viper_s650();
        let far =
            vec![Obstacle::Sphere { name: "far".into(), center_mm: [2000.0, 0.0, 0.0], radius_mm: 10.0 }];
        let (d, name, _) = clearance(&arm, &ArmModel::HOME_DEG, &far).unwrap();
        assert!(d > 1000.0 && name == "far");
        let around = vec![Obstacle::Box {
            name: "cage".into(),
            min_mm: [-50.0, -50.0, 100.0],
            max_mm: [50.0, 50.0, 200.0],
        }];
        let (d, name, what) = clearance(&arm, &ArmModel::HOME_DEG, &around).unwrap();
        assert!(d < 0.0, "the upper arm runs through the box: {d} ({what})");
        assert_eq!(name, "cage");
        assert!(clearance(&arm, &ArmModel::HOME_DEG, &[]).is_none());
    }
}

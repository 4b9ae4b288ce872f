//! The calibration routine: the reference sphere on the table, the scan plan that sees it and
//! the table top at every table angle and from several directions, and the session that runs it.

use depthmill_geometry::Mesh;
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use super::{CalibrationError, Cell, invalid};
use crate::domain::scan::{CellLayout, Pass, ScanMode, ScanOptions, ScanPlan, ScanSession, Station, plan};

/// Standoff of the calibration passes above what they look at, mm (the middle of the window).
const STANDOFF_MM: f64 = 150.0;
/// Extra standoffs of the straight-down sphere passes at the first angle, mm.
const EXTRA_STANDOFFS_MM: [f64; 2] = [100.0, 200.0];
/// Tilt of the turned sphere passes, degrees (inside the table top's 25° incidence limit is not
/// needed: these look at the sphere).
const VIEW_TILT_DEG: f64 = 20.0;
/// Length of the table-top pass across the axis, mm.
pub(crate) const TABLE_PASS_MM: f64 = 80.0;

/// How to calibrate: where the reference sphere stands and which table angles to use.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CalibrationOptions {
    /// Table angles (encoder readings) the sphere and the top are scanned at, degrees; at least 3,
    /// spread over at least 90°.
    pub table_angles_deg: Vec<f64>,
    /// Radius of the reference sphere, mm.
    pub sphere_radius_mm: f64,
    /// Centre of the sphere in the table's frame (its nest: X, Y on the top from the axis, Z
    /// above the top), mm.
    pub sphere_at_mm: [f64; 3],
    /// Distance between scanner lines, mm.
    pub line_spacing_mm: f64,
    /// Noise seed.
    pub seed: u64,
}

impl Default for CalibrationOptions {
    /// Four angles a quarter turn apart, a 25.4 mm ball 100 mm from the axis on a 20 mm post.
    fn default() -> Self {
        Self {
            table_angles_deg: vec![0.0, 90.0, 180.0, 270.0],
            sphere_radius_mm: 12.7,
            sphere_at_mm: [100.0, 0.0, 32.7],
            line_spacing_mm: 0.5,
            seed: 2002,
        }
    }
}

impl CalibrationOptions {
    /// Checks the options against the cell; the error names the field.
    pub fn validate(&self, layout: &CellLayout) -> Result<(), CalibrationError> {
        let a = &self.table_angles_deg;
        if a.len() < 3 {
            return Err(CalibrationError::Degenerate(format!(
                "table_angles_deg has {} angles: the axis needs the sphere at 3 or more",
                a.len()
            )));
        }
        if a.len() > 36 {
            return Err(invalid("table_angles_deg", a.len(), "at most 36 angles"));
        }
        if let Some(v) = a.iter().find(|v| !v.is_finite()) {
            return Err(invalid("table_angles_deg", v, "finite degrees"));
        }
        let mut norm: Vec<f64> = a.iter().map(|v| v.rem_euclid(360.0)).collect();
        norm.sort_by(f64::total_cmp);
        for w in norm.windows(2) {
            if w[1] - w[0] < 5.0 {
                return Err(CalibrationError::Degenerate(format!(
                    "table_angles_deg has {:.1}° and {:.1}° within 5° of each other: distinct angles are needed",
                    w[0], w[1]
                )));
            }
        }
        // The arc covered: 360° minus the largest gap between neighbours (round the circle).
        let mut gap: f64 = 360.0 - (norm[norm.len() - 1] - norm[0]);
        for w in norm.windows(2) {
            gap = gap.max(w[1] - w[0]);
        }
        if 360.0 - gap < 90.0 {
            return Err(CalibrationError::Degenerate(format!(
                "table_angles_deg cover only {:.1}° of the turn: the sphere's centres are nearly collinear, spread them over at least 90°",
                360.0 - gap
            )));
        }
        let r = self.sphere_radius_mm;
        if !(r.is_finite() && (3.0..=50.0).contains(&r)) {
            return Err(invalid("sphere_radius_mm", r, "between 3 and 50 mm"));
        }
        let [x, y, z] = self.sphere_at_mm;
        let from_axis = x.hypot(y);
        if !(from_axis.is_finite() && from_axis >= 30.0 && from_axis + r + 5.0 <= layout.table_radius_mm) {
            return Err(invalid(
                "sphere_at_mm",
                format!("[{x}, {y}, {z}]"),
                &format!(
                    "the sphere's centre must stand 30 mm or more from the axis and the sphere 5 mm inside the {} mm table",
                    layout.table_radius_mm
                ),
            ));
        }
        if !(z.is_finite() && z >= r + 1.0 && z <= 150.0) {
            return Err(invalid(
                "sphere_at_mm[2]",
                z,
                &format!("from {} (the ball clear of the top) to 150 mm", r + 1.0),
            ));
        }
        let s = self.line_spacing_mm;
        if !(s.is_finite() && (0.05..=2.0).contains(&s)) {
            return Err(invalid("line_spacing_mm", s, "between 0.05 and 2 mm"));
        }
        Ok(())
    }
}

/// A UV sphere of `radius` at `centre` fine enough that its facets stay within a micrometre of
/// the true sphere at the reference ball's size.
pub fn sphere_mesh(centre: Point3<f64>, radius: f64) -> Mesh {
    let (n_lat, n_lon) = (120u32, 240u32);
    let mut vertices = vec![centre + Vector3::new(0.0, 0.0, radius)];
    for i in 1..n_lat {
        let th = std::f64::consts::PI * f64::from(i) / f64::from(n_lat);
        for j in 0..n_lon {
            let ph = 2.0 * std::f64::consts::PI * f64::from(j) / f64::from(n_lon);
            vertices.push(centre + radius * Vector3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()));
        }
    }
    vertices.push(centre - Vector3::new(0.0, 0.0, radius));
    let ring = |i: u32, j: u32| 1 + (i - 1) * n_lon + (j % n_lon);
    let south = vertices.len() as u32 - 1;
    let mut triangles = Vec::new();
    for j in 0..n_lon {
        triangles.push([0, ring(1, j), ring(1, j + 1)]);
        triangles.push([south, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)]);
    }
    for i in 1..n_lat - 1 {
        for j in 0..n_lon {
            let (a, b, c, d) = (ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1));
            triangles.push([a, c, d]);
            triangles.push([a, d, b]);
        }
    }
    Mesh { vertices, triangles }
}

/// The calibration scan: a session over the sphere on the table (capturing every frame for the
/// fit) and its plan. Options are checked first; a pass the arm cannot reach is an error naming
/// it (the routine needs every view).
pub fn calibration_session(
    cell: &Cell,
    layout: CellLayout,
    opts: &CalibrationOptions,
) -> Result<(ScanSession, ScanPlan), CalibrationError> {
    opts.validate(&layout)?;
    let scan_opts = scan_options(opts);
    let centre = Point3::from(opts.sphere_at_mm);
    let mesh = sphere_mesh(centre, opts.sphere_radius_mm);
    let scan = |e: &dyn std::fmt::Display| CalibrationError::Scan(e.to_string());
    let session = ScanSession::for_calibration(&mesh, scan_opts.clone(), layout, cell.clone(), opts.clone())
        .map_err(|e| scan(&e))?;
    let away = 0.4 * opts.sphere_at_mm[0].hypot(opts.sphere_at_mm[1]);
    let stations =
        calibration_stations(session.arm(), session.layout(), opts, &scan_opts, &[], (false, away), 1)
            .map_err(|e| scan(&e))?;
    Ok((session, ScanPlan { stations, skipped: Vec::new() }))
}

/// The scan options of the calibration passes.
pub(crate) fn scan_options(opts: &CalibrationOptions) -> ScanOptions {
    ScanOptions {
        mode: ScanMode::Dynamic,
        table_angles_deg: opts.table_angles_deg.clone(),
        line_spacing_mm: opts.line_spacing_mm,
        adaptive_rescan: false,
        seed: opts.seed,
        ..ScanOptions::default()
    }
}

/// The routine's passes at every angle of `opts` (ids from `first_id`), planned for `arm` on
/// `layout` (as believed) clear of `obstacles`: straight down over the sphere everywhere, and
/// tilted and from farther at the angle where it comes nearest the robot; then the table top
/// across, `table_pass.1` from the axis: on the side away from the sphere, or (`table_pass.0`)
/// on the side nearest the robot, where the arm works in its most accurate posture.
pub(crate) fn calibration_stations(
    arm: &depthmill_geometry::arm::ArmModel,
    layout: &CellLayout,
    opts: &CalibrationOptions,
    scan_opts: &ScanOptions,
    obstacles: &[crate::domain::scan::obstacles::Obstacle],
    table_pass: (bool, f64),
    first_id: u16,
) -> Result<Vec<Station>, crate::domain::scan::ScanError> {
    let centre = Point3::from(opts.sphere_at_mm);
    let r = opts.sphere_radius_mm;
    let mut stations = Vec::with_capacity(opts.table_angles_deg.len());
    let mut id = first_id.saturating_sub(1);
    let mut next_id = || {
        id = id.checked_add(1).ok_or_else(|| crate::domain::scan::ScanError::InvalidOption {
            field: "passes".into(),
            value: String::new(),
            reason: "pass ids exhausted (65535 passes)".into(),
        })?;
        Ok::<u16, crate::domain::scan::ScanError>(id)
    };
    let mut seed = depthmill_geometry::arm::ArmModel::HOME_DEG;
    // The turned views where the sphere comes nearest the robot (the arm has room to lean).
    let nearest = opts
        .table_angles_deg
        .iter()
        .map(|&deg| (layout.world_from_table(deg) * centre).coords.xy().norm())
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map_or(0, |(k, _)| k);
    let outward = Vector3::new(opts.sphere_at_mm[0], opts.sphere_at_mm[1], 0.0)
        .try_normalize(1e-9)
        .unwrap_or_else(Vector3::x);
    for (k, &deg) in opts.table_angles_deg.iter().enumerate() {
        let w = layout.world_from_table(deg);
        let top = w * (centre + Vector3::new(0.0, 0.0, r));
        // (direction, tilt, standoff) of the sphere passes.
        let mut views = vec![(Vector3::y(), 0.0, STANDOFF_MM)];
        if k == nearest {
            views.extend([
                (Vector3::y(), VIEW_TILT_DEG, STANDOFF_MM),
                (Vector3::y(), -VIEW_TILT_DEG, STANDOFF_MM),
                (Vector3::x(), 0.0, STANDOFF_MM),
                (Vector3::x(), VIEW_TILT_DEG, STANDOFF_MM),
                (Vector3::x(), -VIEW_TILT_DEG, STANDOFF_MM),
            ]);
            views.extend(EXTRA_STANDOFFS_MM.map(|s| (Vector3::y(), 0.0, s)));
        }
        let mut passes: Vec<Pass> = Vec::new();
        let half = r + 12.0;
        for (dir, tilt, standoff) in views {
            let axis = plan::sensor_orientation(&dir, tilt) * Vector3::z();
            let (a, b) = (top - dir * half - axis * standoff, top + dir * half - axis * standoff);
            let o = ScanOptions { tilt_deg: tilt, ..scan_opts.clone() };
            let p = plan::make_pass(arm, &o, obstacles, next_id()?, deg, a, b, &seed)?;
            seed = p.q_end_deg;
            passes.push(p);
        }
        // The table top across the axis, on the side away from the sphere or nearest the robot.
        let away = if table_pass.0 {
            let axis = w * Point3::origin();
            let toward =
                Vector3::new(-axis.x, -axis.y, 0.0).try_normalize(1e-9).unwrap_or_else(|| -Vector3::x());
            axis + toward * table_pass.1
        } else {
            w * Point3::from(-outward * table_pass.1)
        };
        let d = Vector3::y() * (0.5 * TABLE_PASS_MM);
        let lift = Vector3::new(0.0, 0.0, STANDOFF_MM);
        let p = plan::make_pass(
            arm,
            scan_opts,
            obstacles,
            next_id()?,
            deg,
            away - d + lift,
            away + d + lift,
            &seed,
        )?;
        seed = p.q_end_deg;
        passes.push(p);
        stations.push(Station { table_deg: deg, passes, table_offset_deg: 0.0 });
    }
    Ok(stations)
}

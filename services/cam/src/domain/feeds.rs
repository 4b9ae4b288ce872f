//! Feeds and speeds, and machining-time estimates.
//!
//! Units at the API: feeds mm/min, rapid mm/min, acceleration mm/s², spindle rpm, surface speed
//! m/min, chip load mm per tooth, lengths mm, time s.

use nalgebra::Point3;

use super::CamError;
use super::cleanup::move_geometry;
use super::path::Segment;
use super::tool::{Tool, ToolKind};

/// What the machine can do.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MachineLimits {
    /// Slowest programmable feed, mm/min.
    pub feed_min_mm_min: f64,
    /// Fastest programmable feed, mm/min.
    pub feed_max_mm_min: f64,
    /// Rapid (G0) traverse rate, mm/min.
    pub rapid_mm_min: f64,
    /// Axis acceleration, mm/s² (same for every axis and for feed and rapid moves).
    pub accel_mm_s2: f64,
    /// Slowest spindle speed, rpm.
    pub rpm_min: f64,
    /// Fastest spindle speed, rpm.
    pub rpm_max: f64,
}

impl MachineLimits {
    /// The EMCO F1 (CNC): feed 5–400 mm/min, spindle 300–2000 rpm (DESIGN §5; the seed writes
    /// the feed in mm/s, a unit slip: 400 mm/s at 0.01 mm per step would be a 40 kHz step rate).
    /// Rapid traverse 700 mm/min, the F1-CNC's G0 rate, again mm/min and not mm/s. Acceleration
    /// 50 mm/s² is an assumption for a small stepper mill (ramped steppers), not a datasheet
    /// figure.
    pub fn emco_f1() -> Self {
        MachineLimits {
            feed_min_mm_min: 5.0,
            feed_max_mm_min: 400.0,
            rapid_mm_min: 700.0,
            accel_mm_s2: 50.0,
            rpm_min: 300.0,
            rpm_max: 2000.0,
        }
    }

    /// Checks every figure is finite and positive and every min <= its max.
    pub fn validate(&self) -> Result<(), CamError> {
        let fields = [
            ("limits.feed_min_mm_min", self.feed_min_mm_min),
            ("limits.feed_max_mm_min", self.feed_max_mm_min),
            ("limits.rapid_mm_min", self.rapid_mm_min),
            ("limits.accel_mm_s2", self.accel_mm_s2),
            ("limits.rpm_min", self.rpm_min),
            ("limits.rpm_max", self.rpm_max),
        ];
        for (field, v) in fields {
            if !(v.is_finite() && v > 0.0) {
                return Err(CamError::param(field, format!("must be finite and positive, got {v}")));
            }
        }
        if self.feed_min_mm_min > self.feed_max_mm_min {
            return Err(CamError::param(
                "limits.feed_min_mm_min",
                format!("{} is above feed_max_mm_min {}", self.feed_min_mm_min, self.feed_max_mm_min),
            ));
        }
        if self.rpm_min > self.rpm_max {
            return Err(CamError::param(
                "limits.rpm_min",
                format!("{} is above rpm_max {}", self.rpm_min, self.rpm_max),
            ));
        }
        Ok(())
    }
}

/// Spindle speed, feeds and coolant for one tool in one material.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CuttingData {
    /// rpm.
    pub spindle_rpm: f64,
    /// Cutting feed (G1 and arcs), mm/min.
    pub feed_mm_min: f64,
    /// Plunge feed (downward entries), mm/min.
    pub plunge_mm_min: f64,
    /// Flood coolant (M8).
    pub coolant: bool,
}

/// One row of the material table.
struct Material {
    name: &'static str,
    /// Surface speed, m/min.
    vc_m_min: f64,
    /// Chip load per tooth (mm) at the diameters of [`FZ_DIAMETERS_MM`].
    fz_mm: [f64; 5],
    coolant: bool,
}

/// Tool diameters (mm) of the chip-load columns; linear in between, constant outside.
const FZ_DIAMETERS_MM: [f64; 5] = [1.0, 3.0, 6.0, 10.0, 16.0];

/// Conservative figures for carbide end mills on a light machine (lower end of common
/// handbook ranges: a 440 W spindle and a flexible frame).
const MATERIALS: &[Material] = &[
    Material {
        name: "aluminium",
        vc_m_min: 120.0,
        fz_mm: [0.005, 0.015, 0.030, 0.050, 0.070],
        coolant: true,
    },
    Material { name: "brass", vc_m_min: 90.0, fz_mm: [0.005, 0.012, 0.025, 0.040, 0.060], coolant: true },
    Material { name: "copper", vc_m_min: 70.0, fz_mm: [0.004, 0.010, 0.020, 0.035, 0.050], coolant: true },
    Material {
        name: "mild_steel",
        vc_m_min: 30.0,
        fz_mm: [0.003, 0.008, 0.015, 0.025, 0.035],
        coolant: true,
    },
    Material { name: "plastic", vc_m_min: 150.0, fz_mm: [0.010, 0.030, 0.050, 0.080, 0.100], coolant: false },
    Material { name: "wood", vc_m_min: 200.0, fz_mm: [0.020, 0.050, 0.080, 0.120, 0.150], coolant: false },
    Material { name: "wax", vc_m_min: 150.0, fz_mm: [0.020, 0.050, 0.100, 0.150, 0.200], coolant: false },
    Material { name: "foam", vc_m_min: 200.0, fz_mm: [0.050, 0.100, 0.150, 0.200, 0.250], coolant: false },
];

/// Other spellings accepted for table names.
const ALIASES: &[(&str, &str)] = &[
    ("aluminum", "aluminium"),
    ("al", "aluminium"),
    ("steel", "mild_steel"),
    ("mild-steel", "mild_steel"),
    ("pom", "plastic"),
    ("acrylic", "plastic"),
    ("mdf", "wood"),
];

/// A material of the cutting table, as the service lists it.
#[derive(Debug, Clone, PartialEq)]
pub struct MaterialInfo {
    pub name: &'static str,
    /// Surface speed, m/min.
    pub surface_speed_m_min: f64,
    pub coolant: bool,
    /// Other spellings accepted for it.
    pub aliases: Vec<&'static str>,
}

/// Every material of the cutting table, in table order.
pub fn materials() -> Vec<MaterialInfo> {
    MATERIALS
        .iter()
        .map(|m| MaterialInfo {
            name: m.name,
            surface_speed_m_min: m.vc_m_min,
            coolant: m.coolant,
            aliases: ALIASES.iter().filter(|(_, to)| *to == m.name).map(|(a, _)| *a).collect(),
        })
        .collect()
}

fn interpolate(xs: &[f64; 5], ys: &[f64; 5], x: f64) -> f64 {
    if x <= xs[0] {
        return ys[0];
    }
    for i in 1..xs.len() {
        if x <= xs[i] {
            let t = (x - xs[i - 1]) / (xs[i] - xs[i - 1]);
            return ys[i - 1] + (ys[i] - ys[i - 1]) * t;
        }
    }
    ys[xs.len() - 1]
}

/// The diameter that actually cuts (mm): the full diameter for flat, bull and custom tools;
/// for a ball, the diameter at an engagement depth of D/10 (2·√(ap·(D−ap)) = 0.6·D); for a V
/// tool, half its diameter (mid-flank).
fn effective_diameter_mm(tool: &Tool) -> f64 {
    let d = tool.diameter_mm();
    match tool.kind {
        ToolKind::Ball => {
            let ap = 0.1 * d;
            2.0 * (ap * (d - ap)).sqrt()
        }
        ToolKind::V => 0.5 * d,
        ToolKind::Flat | ToolKind::Bull | ToolKind::Custom => d,
    }
}

/// Feeds and speeds from the tool × material table.
///
/// Algorithm: `D_eff` as in the effective-diameter rule (ball: 0.6·D, V: D/2, others D);
/// `rpm = vc·1000 / (π·D_eff)` rounded to whole rpm and clamped to the machine; chip load `fz`
/// interpolated in the table at the nominal diameter D (the tool's strength sets the chip load;
/// the effective diameter only sets the surface speed);
/// `feed = fz · flutes · rpm` rounded to whole mm/min and clamped to the machine's feed range;
/// plunge = feed/2 for ball tools, feed/3 otherwise, at least the machine's minimum feed.
/// Coolant for metals. Materials (case-insensitive, `-`/space read as `_`): aluminium, brass,
/// copper, mild_steel, plastic, wood, wax, foam, plus aliases (aluminum, steel, acrylic, pom, mdf).
///
/// Errors: an unknown material (naming it and the known ones), invalid limits, a tool whose
/// diameter is not positive.
pub fn cutting_data(tool: &Tool, material: &str, limits: &MachineLimits) -> Result<CuttingData, CamError> {
    limits.validate()?;
    let key = material.trim().to_ascii_lowercase().replace([' ', '-'], "_");
    let key = ALIASES.iter().find(|(a, _)| a.replace('-', "_") == key).map_or(key.as_str(), |(_, m)| m);
    let m = MATERIALS.iter().find(|m| m.name == key).ok_or_else(|| {
        CamError::param(
            "material",
            format!(
                "'{material}' is not in the cutting table (known: {})",
                MATERIALS.iter().map(|m| m.name).collect::<Vec<_>>().join(", ")
            ),
        )
    })?;
    let d_eff = effective_diameter_mm(tool);
    if !(d_eff.is_finite() && d_eff > 0.0) {
        return Err(CamError::InvalidTool {
            name: tool.name.clone(),
            message: format!("effective cutting diameter {d_eff} mm is not positive"),
        });
    }
    let rpm =
        (m.vc_m_min * 1000.0 / (std::f64::consts::PI * d_eff)).round().clamp(limits.rpm_min, limits.rpm_max);
    let fz = interpolate(&FZ_DIAMETERS_MM, &m.fz_mm, tool.diameter_mm());
    let feed = (fz * f64::from(tool.flutes.max(1)) * rpm)
        .round()
        .clamp(limits.feed_min_mm_min, limits.feed_max_mm_min);
    let divisor = if tool.kind == ToolKind::Ball { 2.0 } else { 3.0 };
    let plunge = (feed / divisor).round().clamp(limits.feed_min_mm_min, limits.feed_max_mm_min);
    Ok(CuttingData { spindle_rpm: rpm, feed_mm_min: feed, plunge_mm_min: plunge, coolant: m.coolant })
}

/// Largest change of direction (degrees) kept at speed through a joint.
pub const JUNCTION_ANGLE_DEG: f64 = 30.0;

/// The rate (mm/s) a move from `from` runs at, as [`estimate_time_s`] models it, and whether it
/// is a rapid.
fn move_rate(from: Point3<f64>, seg: &Segment, data: &CuttingData, limits: &MachineLimits) -> (f64, bool) {
    let (fmin, fmax) = (limits.feed_min_mm_min, limits.feed_max_mm_min.max(limits.feed_min_mm_min));
    let feed = |f: f64| if f > 0.0 { f.clamp(fmin, fmax) } else { fmin } / 60.0;
    let a = limits.accel_mm_s2;
    match *seg {
        Segment::Rapid(_) => {
            (if limits.rapid_mm_min > 0.0 { limits.rapid_mm_min / 60.0 } else { fmax / 60.0 }, true)
        }
        Segment::Linear(_) => (feed(data.feed_mm_min), false),
        Segment::Plunge(_) => (feed(data.plunge_mm_min), false),
        Segment::Arc { center, .. } => {
            let r = (from.x - center[0]).hypot(from.y - center[1]);
            let v = feed(data.feed_mm_min);
            (if a.is_finite() && a > 0.0 && r > 0.0 { v.min((a * r).sqrt()) } else { v }, false)
        }
    }
}

/// Time (s) of a trapezoidal move of `len` mm entered at `v0`, left at `v1`, cruising at most at
/// `vmax` (mm/s) with acceleration `a` (mm/s²); `v0`, `v1` must be reachable (planner-checked).
fn trapezoid_s(len: f64, v0: f64, v1: f64, vmax: f64, a: f64) -> f64 {
    let vp = vmax.min((a * len + (v0 * v0 + v1 * v1) / 2.0).sqrt()).max(v0.max(v1));
    if vp <= 0.0 {
        return 0.0;
    }
    let d_acc = (vp * vp - v0 * v0) / (2.0 * a);
    let d_dec = (vp * vp - v1 * v1) / (2.0 * a);
    let cruise = (len - d_acc - d_dec).max(0.0);
    (vp - v0) / a + (vp - v1) / a + cruise / vp
}

/// Machining time estimate (s) of `segments` starting at `start`.
///
/// Model:
/// - Rates: rapids at `limits.rapid_mm_min`; Linear and Arc at `data.feed_mm_min`; Plunge at
///   `data.plunge_mm_min`; feeds clamped to the machine's feed range (a non-positive or NaN feed
///   runs at the minimum). Arcs are also capped at the centripetal limit `v ≤ √(a·r)`.
/// - Lengths: straight moves by distance, arcs (helices) by `√((sweep·r)² + Δz²)`.
/// - Each move is a trapezoid (accelerate at `a`, cruise, decelerate at `a`).
/// - Junctions: the machine stops at the start, at the end, between a rapid and a feed move, and at
///   any joint whose direction changes by more than 30°; through a gentler joint it keeps
///   `min` of the two moves' rates. A forward/backward pass then lowers junction speeds so each
///   is reachable from its neighbours with acceleration `a` (look-ahead over the whole program).
/// - Zero-length moves take no time and do not break a joint.
///
/// Guarantees: every move takes at least length/rate, so the total is at least Σ length/rate
/// (in particular ≥ cut length / feed); non-negative; a non-positive acceleration counts as
/// infinite (pure length/rate). Tool changes, spindle ramp-up and dwell are not counted.
pub fn estimate_time_s(
    start: Point3<f64>,
    segments: &[Segment],
    data: &CuttingData,
    limits: &MachineLimits,
) -> f64 {
    let a = limits.accel_mm_s2;
    let a_ok = a.is_finite() && a > 0.0;
    let cos_limit = JUNCTION_ANGLE_DEG.to_radians().cos();
    // One pass builds each move's length and rate and the junction speed before it, already
    // lowered to what the move before can reach (the forward pass); the backward pass then
    // finishes the junctions and adds the trapezoids. 24 bytes per move, no direction kept.
    let mut moves: Vec<[f64; 3]> = Vec::with_capacity(segments.len());
    let mut prev: Option<(bool, nalgebra::Vector3<f64>)> = None;
    let mut from = start;
    let mut plain = 0.0;
    for seg in segments {
        let (len, dir_in, dir_out) = move_geometry(from, seg);
        let (v, is_rapid) = move_rate(from, seg, data, limits);
        from = seg.end();
        if !(len.is_finite() && len > 0.0 && v > 0.0) {
            continue;
        }
        if !a_ok {
            plain += len / v;
            continue;
        }
        let j = match (prev, moves.last()) {
            (Some((p_rapid, p_out)), Some(&[p_len, p_v, p_j])) => {
                let keep =
                    if p_rapid == is_rapid && p_out.dot(&dir_in) >= cos_limit { p_v.min(v) } else { 0.0 };
                keep.min((p_j * p_j + 2.0 * a * p_len).sqrt())
            }
            _ => 0.0,
        };
        moves.push([len, v, j]);
        prev = Some((is_rapid, dir_out));
    }
    if !a_ok {
        return plain;
    }
    // Backward: the junction after the last move is a stop.
    let (mut total, mut next) = (0.0, 0.0f64);
    for &[len, v, j] in moves.iter().rev() {
        let j = j.min((next * next + 2.0 * a * len).sqrt());
        total += trapezoid_s(len, j, next, v, a);
        next = j;
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tool(name: &str) -> Tool {
        Tool::from_spec(&name.parse().expect("spec")).expect("tool")
    }

    fn data(feed: f64) -> CuttingData {
        CuttingData { spindle_rpm: 1000.0, feed_mm_min: feed, plunge_mm_min: feed / 2.0, coolant: false }
    }

    #[test]
    fn emco_limits_and_table() {
        let lim = MachineLimits::emco_f1();
        lim.validate().expect("valid");
        // flat-6 in aluminium: 120 m/min on 6 mm wants 6366 rpm -> 2000; 0.03 · 3 · 2000 = 180.
        let d = cutting_data(&tool("flat-6"), "aluminium", &lim).expect("data");
        assert_eq!(
            d,
            CuttingData { spindle_rpm: 2000.0, feed_mm_min: 180.0, plunge_mm_min: 60.0, coolant: true }
        );
        // Ball 3 in mild steel: D_eff 1.8 mm, 30 m/min -> 5305 rpm -> 2000; fz 0.008 · 2 · 2000 = 32.
        let d = cutting_data(&tool("ball-3"), "Mild Steel", &lim).expect("data");
        assert_eq!((d.spindle_rpm, d.feed_mm_min, d.plunge_mm_min), (2000.0, 32.0, 16.0));
        // Big tool in steel: 30 m/min on 16 mm = 597 rpm, not clamped.
        let t = Tool::parse("name = f16\ntype = flat\ndiameter_mm = 16\nflutes = 4\n", "mem").expect("tool");
        let d = cutting_data(&t, "steel", &lim).expect("data");
        assert_eq!(d.spindle_rpm, 597.0);
        assert_eq!(d.feed_mm_min, (0.035f64 * 4.0 * 597.0).round());
        // Feeds never leave the machine's range.
        for m in ["aluminum", "brass", "copper", "plastic", "wood", "wax", "foam"] {
            for t in ["ball-1", "ball-6", "flat-3", "flat-10", "bull-6-1", "v-6-90"] {
                let d = cutting_data(&tool(t), m, &lim).expect("data");
                assert!((300.0..=2000.0).contains(&d.spindle_rpm), "{m} {t} {d:?}");
                assert!(
                    (5.0..=400.0).contains(&d.feed_mm_min)
                        && (5.0..=d.feed_mm_min).contains(&d.plunge_mm_min)
                );
            }
        }
        let e = cutting_data(&tool("flat-6"), "unobtainium", &lim).expect_err("unknown").to_string();
        assert!(e.contains("unobtainium") && e.contains("aluminium") && e.contains("wood"), "{e}");
        let bad = MachineLimits { rpm_min: 3000.0, ..lim };
        assert!(
            cutting_data(&tool("flat-6"), "wood", &bad).expect_err("bad").to_string().contains("rpm_min")
        );
    }

    #[test]
    fn straight_move_time_is_a_trapezoid() {
        let lim = MachineLimits::emco_f1();
        // 100 mm at 300 mm/min = 5 mm/s, a = 50: ramps of 0.1 s each covering 0.25 mm each.
        let t = estimate_time_s(
            Point3::origin(),
            &[Segment::Linear(Point3::new(100.0, 0.0, 0.0))],
            &data(300.0),
            &lim,
        );
        let expect = 0.1 + 0.1 + 99.5 / 5.0;
        assert!((t - expect).abs() < 1e-9, "{t} vs {expect}");
        // Collinear split keeps speed; a right-angle corner stops.
        let split =
            [Segment::Linear(Point3::new(50.0, 0.0, 0.0)), Segment::Linear(Point3::new(100.0, 0.0, 0.0))];
        let t2 = estimate_time_s(Point3::origin(), &split, &data(300.0), &lim);
        assert!((t2 - expect).abs() < 1e-9, "{t2}");
        let corner =
            [Segment::Linear(Point3::new(50.0, 0.0, 0.0)), Segment::Linear(Point3::new(50.0, 50.0, 0.0))];
        let t3 = estimate_time_s(Point3::origin(), &corner, &data(300.0), &lim);
        assert!((t3 - (expect + 0.1)).abs() < 1e-9, "{t3}");
        // Rapids at 700 mm/min; a half circle of r = 10 by its length.
        let t4 = estimate_time_s(
            Point3::origin(),
            &[Segment::Rapid(Point3::new(0.0, 0.0, 70.0))],
            &data(300.0),
            &lim,
        );
        assert!(t4 > 6.0 && t4 < 6.3, "{t4}");
        let arc = Segment::Arc { end: Point3::new(20.0, 0.0, 0.0), center: [10.0, 0.0], clockwise: true };
        let t5 = estimate_time_s(Point3::origin(), &[arc], &data(300.0), &lim);
        let len = std::f64::consts::PI * 10.0;
        assert!(t5 >= len / 5.0 && t5 < len / 5.0 + 0.25, "{t5}");
    }

    /// One move for the reference time planner.
    struct Move {
        len_mm: f64,
        v_max_mm_s: f64,
        rapid: bool,
        dir_in: nalgebra::Vector3<f64>,
        dir_out: nalgebra::Vector3<f64>,
    }

    /// The estimate move by move as the model states it: every move's geometry kept, the
    /// junctions set, then a forward and a backward pass over them, the trapezoids summed.
    fn reference_time_s(
        start: Point3<f64>,
        segments: &[Segment],
        data: &CuttingData,
        limits: &MachineLimits,
    ) -> f64 {
        let a = limits.accel_mm_s2;
        let a_ok = a.is_finite() && a > 0.0;
        let mut moves = Vec::with_capacity(segments.len());
        let mut from = start;
        for seg in segments {
            let (len, dir_in, dir_out) = move_geometry(from, seg);
            let (v, is_rapid) = move_rate(from, seg, data, limits);
            from = seg.end();
            if len.is_finite() && len > 0.0 && v > 0.0 {
                moves.push(Move { len_mm: len, v_max_mm_s: v, rapid: is_rapid, dir_in, dir_out });
            }
        }
        if !a_ok {
            return moves.iter().map(|m| m.len_mm / m.v_max_mm_s).sum();
        }
        // Junction speeds: j[k] is the speed between moves k-1 and k; j[0] = j[n] = 0.
        let n = moves.len();
        let cos_limit = JUNCTION_ANGLE_DEG.to_radians().cos();
        let mut j = vec![0.0f64; n + 1];
        for k in 1..n {
            let (p, q) = (&moves[k - 1], &moves[k]);
            if p.rapid == q.rapid && p.dir_out.dot(&q.dir_in) >= cos_limit {
                j[k] = p.v_max_mm_s.min(q.v_max_mm_s);
            }
        }
        for k in 1..=n {
            j[k] = j[k].min((j[k - 1] * j[k - 1] + 2.0 * a * moves[k - 1].len_mm).sqrt());
        }
        for k in (0..n).rev() {
            j[k] = j[k].min((j[k + 1] * j[k + 1] + 2.0 * a * moves[k].len_mm).sqrt());
        }
        moves.iter().enumerate().map(|(k, m)| trapezoid_s(m.len_mm, j[k], j[k + 1], m.v_max_mm_s, a)).sum()
    }

    fn random_path(raw: &[(f64, f64, f64, u8)]) -> Vec<Segment> {
        let mut pos = Point3::origin();
        raw.iter()
            .map(|&(x, y, z, kind)| {
                let to = Point3::new(pos.x + x, pos.y + y, pos.z + z);
                let seg = match kind % 4 {
                    0 => Segment::Rapid(to),
                    1 => Segment::Plunge(to),
                    2 => {
                        let mid = Point3::new((pos.x + to.x) / 2.0, (pos.y + to.y) / 2.0, 0.0);
                        Segment::Arc { end: to, center: [mid.x, mid.y], clockwise: x > 0.0 }
                    }
                    _ => Segment::Linear(to),
                };
                pos = to;
                seg
            })
            .collect()
    }

    proptest! {
        #[test]
        fn the_one_pass_estimate_is_the_reference_plan(
            raw in prop::collection::vec((-20.0f64..20.0, -20.0f64..20.0, -2.0f64..2.0, 0u8..6), 1..60),
            feed in 5.0f64..400.0,
            accel in prop_oneof![Just(0.0), 1.0f64..500.0],
        ) {
            // Straight runs (small turns keep the speed), zero-length moves, every kind of move.
            let mut segs = random_path(&raw);
            for (k, &(x, _, _, kind)) in raw.iter().enumerate() {
                if kind >= 4 && k < segs.len() {
                    let end = segs[k].end();
                    segs.insert(k, Segment::Linear(end - nalgebra::Vector3::new(x.abs() + 1.0, 0.1, 0.0)));
                    segs.insert(k, Segment::Linear(segs[k].end()));
                }
            }
            let lim = MachineLimits { accel_mm_s2: accel, ..MachineLimits::emco_f1() };
            let (fast, slow) = (
                estimate_time_s(Point3::origin(), &segs, &data(feed), &lim),
                reference_time_s(Point3::origin(), &segs, &data(feed), &lim),
            );
            prop_assert!((fast - slow).abs() <= 1e-9 * slow.max(1.0), "{} against {}", fast, slow);
        }

        #[test]
        fn time_is_at_least_length_over_feed_and_grows_with_length(
            raw in prop::collection::vec((-20.0f64..20.0, -20.0f64..20.0, -2.0f64..2.0, 0u8..4), 1..30),
            feed in 5.0f64..400.0,
            extra in 0.0f64..50.0,
        ) {
            let lim = MachineLimits::emco_f1();
            let d = data(feed);
            let segs = random_path(&raw);
            let t = estimate_time_s(Point3::origin(), &segs, &d, &lim);
            // Reference: Σ length / rate.
            let mut from = Point3::origin();
            let mut bound = 0.0;
            for s in &segs {
                let (len, _, _) = move_geometry(from, s);
                let rate = match s {
                    Segment::Rapid(_) => lim.rapid_mm_min,
                    Segment::Plunge(_) => d.plunge_mm_min.max(5.0),
                    _ => feed,
                };
                bound += len / rate * 60.0;
                from = s.end();
            }
            prop_assert!(t >= bound - 1e-9, "{} < {}", t, bound);
            // Longer: extend the path with a straight cut continuing from its end.
            let end = segs.last().map_or(Point3::origin(), Segment::end);
            let mut longer = segs.clone();
            longer.push(Segment::Linear(end + nalgebra::Vector3::new(extra, 0.0, 0.0)));
            let t_longer = estimate_time_s(Point3::origin(), &longer, &d, &lim);
            prop_assert!(t_longer >= t - 1e-9, "{} < {}", t_longer, t);
            // Longer still: the same cut made longer.
            let mut longest = longer.clone();
            if let Some(Segment::Linear(p)) = longest.last_mut() {
                p.x += 10.0;
            }
            prop_assert!(estimate_time_s(Point3::origin(), &longest, &d, &lim) >= t_longer - 1e-9);
        }

        #[test]
        fn straight_line_time_is_monotone_in_length(a in 0.0f64..200.0, b in 0.0f64..200.0, feed in 5.0f64..400.0) {
            let lim = MachineLimits::emco_f1();
            let t = |l: f64| estimate_time_s(Point3::origin(), &[Segment::Linear(Point3::new(l, 0.0, 0.0))], &data(feed), &lim);
            let (lo, hi) = if a < b { (a, b) } else { (b, a) };
            prop_assert!(t(lo) <= t(hi) + 1e-12);
            prop_assert!(t(hi) >= hi / feed * 60.0 - 1e-9);
        }
    }
}

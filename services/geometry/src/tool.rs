//! Cutting tools: [`ToolProfile`] (the tool's lower surface as a solid of revolution) and
//! [`ToolSpec`] (the short names `ball-6`, `flat-6`, `bull-6-1`, `v-6-90`).
//!
//! A profile is the cross-section of the cutting surface from the tip outward: a polyline of
//! `(radius_mm, height_mm)` vertices starting at the tip `(0, 0)`, non-decreasing in both
//! coordinates, ending at the tool radius. `height_at(r)` is the height of the tool surface above
//! the tip at distance `r` from the axis: what compensation subtracts (`B(i, j)` in DESIGN §3).
//!
//! A `.tool` file is the JSON form of a profile: `{"spec": "ball-6"}` or
//! `{"radius_mm": [0, 3, 3], "height_mm": [0, 0, 20]}`.

use std::fmt;
use std::fs;
use std::path::Path;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::error::{GeometryError, Result};

/// Segments used to draw a quarter arc into the polyline of a ball or bull-nose profile
/// (chord error below `1.3e-4 · r`). [`ToolProfile::height_at`] uses the exact arc.
pub const ARC_SEGMENTS: usize = 64;

/// A named standard tool. Diameters in mm, angles in degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ToolSpec {
    /// Spherical end: `ball-D`.
    Ball { diameter_mm: f64 },
    /// Cylindrical end: `flat-D`.
    Flat { diameter_mm: f64 },
    /// Flat end with a rounded corner: `bull-D-R`.
    Bull { diameter_mm: f64, corner_radius_mm: f64 },
    /// Conical: `v-D-ANGLE`, or `v-D-ANGLE-T` with a flat tip of diameter `T`.
    V { diameter_mm: f64, included_angle_deg: f64, tip_flat_diameter_mm: f64 },
}

impl ToolSpec {
    /// The profile of this tool (validating its numbers).
    pub fn profile(&self) -> Result<ToolProfile> {
        match *self {
            ToolSpec::Ball { diameter_mm } => ToolProfile::ball(diameter_mm),
            ToolSpec::Flat { diameter_mm } => ToolProfile::flat(diameter_mm),
            ToolSpec::Bull { diameter_mm, corner_radius_mm } => {
                ToolProfile::bull(diameter_mm, corner_radius_mm)
            }
            ToolSpec::V { diameter_mm, included_angle_deg, tip_flat_diameter_mm } => {
                ToolProfile::v(diameter_mm, included_angle_deg, tip_flat_diameter_mm)
            }
        }
    }

    /// The tool diameter.
    pub fn diameter_mm(&self) -> f64 {
        match *self {
            ToolSpec::Ball { diameter_mm }
            | ToolSpec::Flat { diameter_mm }
            | ToolSpec::Bull { diameter_mm, .. }
            | ToolSpec::V { diameter_mm, .. } => diameter_mm,
        }
    }
}

impl fmt::Display for ToolSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            ToolSpec::Ball { diameter_mm } => write!(f, "ball-{diameter_mm}"),
            ToolSpec::Flat { diameter_mm } => write!(f, "flat-{diameter_mm}"),
            ToolSpec::Bull { diameter_mm, corner_radius_mm } => {
                write!(f, "bull-{diameter_mm}-{corner_radius_mm}")
            }
            ToolSpec::V { diameter_mm, included_angle_deg, tip_flat_diameter_mm } => {
                write!(f, "v-{diameter_mm}-{included_angle_deg}")?;
                if tip_flat_diameter_mm != 0.0 {
                    write!(f, "-{tip_flat_diameter_mm}")?;
                }
                Ok(())
            }
        }
    }
}

impl FromStr for ToolSpec {
    type Err = GeometryError;

    /// Parses `ball-D`, `flat-D`, `bull-D-R`, `v-D-ANGLE[-TIP]` (kind case-insensitive). Only the
    /// syntax is checked here; [`ToolSpec::profile`] checks the values.
    fn from_str(s: &str) -> Result<Self> {
        let err = || GeometryError::Parse {
            what: "tool",
            input: s.to_string(),
            expected: "ball-D, flat-D, bull-D-R or v-D-ANGLE[-TIP] with D, R, TIP in mm and ANGLE in degrees",
        };
        let mut parts = s.trim().split('-');
        let kind = parts.next().unwrap_or_default().to_ascii_lowercase();
        let nums = parts.map(|p| p.parse::<f64>().map_err(|_| err())).collect::<Result<Vec<f64>>>()?;
        Ok(match (kind.as_str(), nums.as_slice()) {
            ("ball", &[d]) => ToolSpec::Ball { diameter_mm: d },
            ("flat", &[d]) => ToolSpec::Flat { diameter_mm: d },
            ("bull", &[d, r]) => ToolSpec::Bull { diameter_mm: d, corner_radius_mm: r },
            ("v", &[d, a]) => {
                ToolSpec::V { diameter_mm: d, included_angle_deg: a, tip_flat_diameter_mm: 0.0 }
            }
            ("v", &[d, a, t]) => {
                ToolSpec::V { diameter_mm: d, included_angle_deg: a, tip_flat_diameter_mm: t }
            }
            _ => return Err(err()),
        })
    }
}

impl Serialize for ToolSpec {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for ToolSpec {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        String::deserialize(d)?.parse().map_err(serde::de::Error::custom)
    }
}

/// Exact description used by `height_at`.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Surface {
    /// Sphere of radius `r`.
    Ball { r: f64 },
    /// Flat bottom to `r − c`, then a torus of tube radius `c`.
    Bull { r: f64, c: f64 },
    /// Linear interpolation of the polyline (flat, V and custom tools).
    Polyline,
}

/// A tool's cutting surface as a solid of revolution (see the module docs).
///
/// Invariant: at least two vertices, the first `(0, 0)`, all finite, both coordinates
/// non-decreasing, last radius positive.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "ToolFile", into = "ToolFile")]
pub struct ToolProfile {
    radii_mm: Vec<f64>,
    heights_mm: Vec<f64>,
    surface: Surface,
    spec: Option<ToolSpec>,
}

fn check_diameter(d: f64) -> Result<f64> {
    if d.is_finite() && d > 0.0 {
        Ok(d / 2.0)
    } else {
        Err(GeometryError::invalid("diameter_mm", d, "a finite positive diameter"))
    }
}

/// `n` points of a quarter arc of radius `c` whose bottom touches `(r0, 0)`, after the bottom.
fn quarter_arc(r0: f64, c: f64, radii: &mut Vec<f64>, heights: &mut Vec<f64>) {
    for i in 1..=ARC_SEGMENTS {
        let t = std::f64::consts::FRAC_PI_2 * i as f64 / ARC_SEGMENTS as f64;
        radii.push(r0 + c * t.sin());
        heights.push(c * (1.0 - t.cos()));
    }
    // Snap the end exactly onto the tool radius and the equator.
    if let (Some(r), Some(h)) = (radii.last_mut(), heights.last_mut()) {
        *r = r0 + c;
        *h = c;
    }
}

impl ToolProfile {
    /// Ball end mill of diameter `d` mm: a hemisphere of radius `d/2`, `h(r) = R − √(R² − r²)`.
    pub fn ball(diameter_mm: f64) -> Result<Self> {
        let r = check_diameter(diameter_mm)?;
        let (mut radii, mut heights) = (vec![0.0], vec![0.0]);
        quarter_arc(0.0, r, &mut radii, &mut heights);
        Ok(ToolProfile {
            radii_mm: radii,
            heights_mm: heights,
            surface: Surface::Ball { r },
            spec: Some(ToolSpec::Ball { diameter_mm }),
        })
    }

    /// Flat end mill of diameter `d` mm: `h(r) = 0` up to the radius.
    pub fn flat(diameter_mm: f64) -> Result<Self> {
        let r = check_diameter(diameter_mm)?;
        Ok(ToolProfile {
            radii_mm: vec![0.0, r],
            heights_mm: vec![0.0, 0.0],
            surface: Surface::Polyline,
            spec: Some(ToolSpec::Flat { diameter_mm }),
        })
    }

    /// Bull-nose end mill: flat to `d/2 − c`, then a quarter torus of radius `c`
    /// (`0 <= c <= d/2`; `c = 0` is a flat mill, `c = d/2` a ball).
    pub fn bull(diameter_mm: f64, corner_radius_mm: f64) -> Result<Self> {
        let r = check_diameter(diameter_mm)?;
        let c = corner_radius_mm;
        if !(c.is_finite() && c >= 0.0) {
            return Err(GeometryError::invalid("corner_radius_mm", c, "a finite non-negative radius"));
        }
        if c > r {
            return Err(GeometryError::CornerRadius { corner_radius_mm: c, radius_mm: r });
        }
        let (mut radii, mut heights) = (vec![0.0], vec![0.0]);
        if r - c > 0.0 {
            radii.push(r - c);
            heights.push(0.0);
        }
        if c > 0.0 {
            quarter_arc(r - c, c, &mut radii, &mut heights);
            // (r − c) + c may round away from r.
            if let Some(last) = radii.last_mut() {
                *last = r;
            }
        }
        Ok(ToolProfile {
            radii_mm: radii,
            heights_mm: heights,
            surface: Surface::Bull { r, c },
            spec: Some(ToolSpec::Bull { diameter_mm, corner_radius_mm }),
        })
    }

    /// V (engraving) cutter: a flat tip of diameter `tip_flat_diameter_mm` (may be 0), then a cone
    /// of `included_angle_deg` (0 < angle < 180) up to diameter `d`:
    /// `h(r) = (r − t/2) / tan(angle/2)` beyond the flat.
    pub fn v(diameter_mm: f64, included_angle_deg: f64, tip_flat_diameter_mm: f64) -> Result<Self> {
        let r = check_diameter(diameter_mm)?;
        let a = included_angle_deg;
        if !(a.is_finite() && a > 0.0 && a < 180.0) {
            return Err(GeometryError::invalid(
                "included_angle_deg",
                a,
                "an angle strictly between 0 and 180",
            ));
        }
        let t = tip_flat_diameter_mm;
        if !(t.is_finite() && t >= 0.0 && t < diameter_mm) {
            return Err(GeometryError::invalid(
                "tip_flat_diameter_mm",
                t,
                "a finite non-negative diameter below the tool diameter",
            ));
        }
        let cone_top = (r - t / 2.0) / (a / 2.0).to_radians().tan();
        let (radii, heights) = if t > 0.0 {
            (vec![0.0, t / 2.0, r], vec![0.0, 0.0, cone_top])
        } else {
            (vec![0.0, r], vec![0.0, cone_top])
        };
        Ok(ToolProfile {
            radii_mm: radii,
            heights_mm: heights,
            surface: Surface::Polyline,
            spec: Some(ToolSpec::V { diameter_mm, included_angle_deg, tip_flat_diameter_mm }),
        })
    }

    /// Any profile from its radius and height vectors (DESIGN §3's "two vectors").
    ///
    /// Errors: [`GeometryError::ProfileLength`] (lengths differ or < 2),
    /// [`GeometryError::InvalidParameter`] (non-finite or negative value, a first vertex other than
    /// `(0, 0)`, a zero last radius), [`GeometryError::ProfileNotMonotone`].
    pub fn custom(radii_mm: Vec<f64>, heights_mm: Vec<f64>) -> Result<Self> {
        if radii_mm.len() != heights_mm.len() || radii_mm.len() < 2 {
            return Err(GeometryError::ProfileLength { radii: radii_mm.len(), heights: heights_mm.len() });
        }
        for (field, values) in [("radius_mm", &radii_mm), ("height_mm", &heights_mm)] {
            for (i, &v) in values.iter().enumerate() {
                if !v.is_finite() {
                    return Err(GeometryError::invalid(format!("{field}[{i}]"), v, "a finite value"));
                }
                if v < 0.0 {
                    return Err(GeometryError::invalid(format!("{field}[{i}]"), v, "a non-negative value"));
                }
                if i == 0 && v != 0.0 {
                    return Err(GeometryError::invalid(
                        format!("{field}[0]"),
                        v,
                        "0 (the profile starts at the tip)",
                    ));
                }
                if i > 0 && v < values[i - 1] {
                    return Err(GeometryError::ProfileNotMonotone {
                        field,
                        index: i,
                        value: v,
                        previous: values[i - 1],
                    });
                }
            }
        }
        let last = radii_mm.len() - 1;
        if radii_mm[last] <= 0.0 {
            return Err(GeometryError::invalid(
                format!("radius_mm[{last}]"),
                radii_mm[last],
                "a positive tool radius",
            ));
        }
        Ok(ToolProfile { radii_mm, heights_mm, surface: Surface::Polyline, spec: None })
    }

    /// Radius of the tool (the profile's last radius).
    pub fn radius_mm(&self) -> f64 {
        self.radii_mm.last().copied().unwrap_or_default()
    }

    /// `2 · radius_mm()`.
    pub fn diameter_mm(&self) -> f64 {
        2.0 * self.radius_mm()
    }

    /// Height of the profile's last vertex above the tip.
    pub fn max_height_mm(&self) -> f64 {
        self.heights_mm.last().copied().unwrap_or_default()
    }

    /// Polyline radii, tip first.
    pub fn radii_mm(&self) -> &[f64] {
        &self.radii_mm
    }

    /// Polyline heights, tip first.
    pub fn heights_mm(&self) -> &[f64] {
        &self.heights_mm
    }

    /// The standard tool this profile was built from, if any.
    pub fn spec(&self) -> Option<ToolSpec> {
        self.spec
    }

    /// Height of the cutting surface above the tip at distance `r_mm` from the axis, or `None`
    /// for `r_mm` outside `[0, radius_mm()]` (or NaN).
    ///
    /// Exact for ball and bull-nose arcs; linear between vertices otherwise. Where the polyline
    /// has a vertical run (several vertices at one radius) the lowest height is returned, i.e.
    /// the surface that touches the part first. Non-decreasing in `r_mm`.
    pub fn height_at(&self, r_mm: f64) -> Option<f64> {
        if !(r_mm >= 0.0 && r_mm <= self.radius_mm()) {
            return None;
        }
        Some(match self.surface {
            Surface::Ball { r } => r - (r * r - r_mm * r_mm).max(0.0).sqrt(),
            Surface::Bull { r, c } => {
                let u = r_mm - (r - c);
                if u <= 0.0 { 0.0 } else { c - (c * c - u * u).max(0.0).sqrt() }
            }
            Surface::Polyline => {
                let i = self.radii_mm.partition_point(|&x| x < r_mm);
                match (self.radii_mm.get(i), i.checked_sub(1)) {
                    (Some(&ri), Some(j)) if ri > r_mm => {
                        let (r0, h0, h1) = (self.radii_mm[j], self.heights_mm[j], self.heights_mm[i]);
                        h0 + (h1 - h0) * (r_mm - r0) / (ri - r0)
                    }
                    _ => self.heights_mm.get(i).copied().unwrap_or_default(),
                }
            }
        })
    }

    /// Reads a `.tool` file (JSON, see the module docs); errors name the file.
    pub fn read_tool_file(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let run = || -> Result<Self> {
            let text = fs::read_to_string(path)?;
            serde_json::from_str(&text).map_err(|e| GeometryError::Json { reason: e.to_string() })
        };
        run().map_err(|e| e.in_file(path))
    }

    /// Writes a `.tool` file; errors name the file.
    pub fn write_tool_file(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let run = || -> Result<()> {
            let json = serde_json::to_string_pretty(self)
                .map_err(|e| GeometryError::Json { reason: e.to_string() })?;
            fs::write(path, json)?;
            Ok(())
        };
        run().map_err(|e| e.in_file(path))
    }
}

impl FromStr for ToolProfile {
    type Err = GeometryError;

    /// `"ball-6".parse::<ToolProfile>()`: a [`ToolSpec`] name, validated.
    fn from_str(s: &str) -> Result<Self> {
        s.parse::<ToolSpec>()?.profile()
    }
}

/// The serde form of a profile (`.tool` files).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ToolFile {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    spec: Option<ToolSpec>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    radius_mm: Option<Vec<f64>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    height_mm: Option<Vec<f64>>,
}

impl TryFrom<ToolFile> for ToolProfile {
    type Error = GeometryError;

    fn try_from(f: ToolFile) -> Result<Self> {
        match f {
            ToolFile { spec: Some(spec), radius_mm: None, height_mm: None } => spec.profile(),
            ToolFile { spec: None, radius_mm: Some(r), height_mm: Some(h) } => ToolProfile::custom(r, h),
            _ => Err(GeometryError::Json {
                reason: "a tool is either {\"spec\": NAME} or {\"radius_mm\": [...], \"height_mm\": [...]}"
                    .into(),
            }),
        }
    }
}

impl From<ToolProfile> for ToolFile {
    fn from(p: ToolProfile) -> Self {
        match p.spec {
            Some(spec) => ToolFile { spec: Some(spec), radius_mm: None, height_mm: None },
            None => ToolFile { spec: None, radius_mm: Some(p.radii_mm), height_mm: Some(p.heights_mm) },
        }
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    #[test]
    fn spec_names_round_trip() {
        for name in ["ball-6", "flat-6", "bull-6-1", "v-6-90", "v-6.35-60-0.2"] {
            let spec: ToolSpec = name.parse().expect(name);
            assert_eq!(spec.to_string(), name);
            assert!(spec.profile().is_ok(), "{name}");
        }
        assert_eq!("BALL-3".parse::<ToolSpec>().ok(), Some(ToolSpec::Ball { diameter_mm: 3.0 }));
        for bad in ["ball", "ball-x", "bull-6", "drill-6", "v-6", "flat-6-1", ""] {
            let e = bad.parse::<ToolSpec>().expect_err(bad);
            assert!(e.to_string().starts_with(&format!("cannot parse tool '{bad}'")), "{e}");
        }
        assert_eq!(
            serde_json::to_string(&ToolSpec::Bull { diameter_mm: 6.0, corner_radius_mm: 1.0 }).ok(),
            Some("\"bull-6-1\"".to_string())
        );
    }

    #[test]
    fn analytic_heights() {
        let ball = ToolProfile::ball(6.0).expect("ball");
        assert_eq!(ball.radius_mm(), 3.0);
        assert_eq!(ball.height_at(0.0), Some(0.0));
        assert_eq!(ball.height_at(3.0), Some(3.0));
        assert!((ball.height_at(1.5).unwrap_or(f64::NAN) - (3.0 - 6.75f64.sqrt())).abs() < 1e-12);
        assert_eq!(ball.height_at(3.0001), None);
        assert_eq!(ball.height_at(-0.1), None);
        assert_eq!(ball.height_at(f64::NAN), None);
        // The polyline stays within the chord error of the exact arc.
        for (r, h) in ball.radii_mm().iter().zip(ball.heights_mm()) {
            assert!((ball.height_at(*r).unwrap_or(f64::NAN) - h).abs() < 1e-9);
        }

        let bull = ToolProfile::bull(6.0, 1.0).expect("bull");
        assert_eq!(bull.height_at(2.0), Some(0.0));
        assert!((bull.height_at(3.0).unwrap_or(f64::NAN) - 1.0).abs() < 1e-12);
        assert!((bull.height_at(2.5).unwrap_or(f64::NAN) - (1.0 - 0.75f64.sqrt())).abs() < 1e-12);

        let v = ToolProfile::v(6.0, 90.0, 0.0).expect("v");
        assert!((v.height_at(2.0).unwrap_or(f64::NAN) - 2.0).abs() < 1e-12);
        let vt = ToolProfile::v(6.0, 90.0, 2.0).expect("v tip");
        assert_eq!(vt.height_at(0.5), Some(0.0));
        assert!((vt.height_at(3.0).unwrap_or(f64::NAN) - 2.0).abs() < 1e-12);

        let flat = ToolProfile::flat(6.0).expect("flat");
        assert_eq!(flat.height_at(3.0), Some(0.0));

        // A vertical run (shank) returns the lowest height at that radius.
        let c = ToolProfile::custom(vec![0.0, 1.0, 2.0, 2.0], vec![0.0, 0.5, 1.0, 10.0]).expect("custom");
        assert_eq!(
            (c.height_at(2.0), c.height_at(1.5), c.height_at(1.0)),
            (Some(1.0), Some(0.75), Some(0.5))
        );
    }

    #[test]
    fn invalid_profiles_are_explained() {
        let cases: Vec<(Result<ToolProfile>, &str)> = vec![
            (ToolProfile::ball(0.0), "invalid diameter_mm 0: expected a finite positive diameter"),
            (ToolProfile::bull(6.0, 4.0), "corner radius 4 mm exceeds the tool radius 3 mm"),
            (ToolProfile::v(6.0, 180.0, 0.0), "invalid included_angle_deg 180"),
            (ToolProfile::custom(vec![0.0, 1.0], vec![0.0]), "tool profile has 2 radii and 1 heights"),
            (
                ToolProfile::custom(vec![0.0, -1.0], vec![0.0, 1.0]),
                "invalid radius_mm[1] -1: expected a non-negative value",
            ),
            (
                ToolProfile::custom(vec![0.0, 2.0, 1.0], vec![0.0, 1.0, 2.0]),
                "tool profile radius_mm[2] = 1 is less than the previous value 2",
            ),
            (ToolProfile::custom(vec![0.0, 1.0], vec![0.0, -0.5]), "invalid height_mm[1] -0.5"),
            (ToolProfile::custom(vec![0.5, 1.0], vec![0.0, 0.0]), "invalid radius_mm[0] 0.5"),
            (
                ToolProfile::custom(vec![0.0, 0.0], vec![0.0, 1.0]),
                "invalid radius_mm[1] 0: expected a positive tool radius",
            ),
        ];
        for (r, msg) in cases {
            let e = r.expect_err(msg).to_string();
            assert!(e.starts_with(msg), "{e} / {msg}");
        }
    }

    #[test]
    fn tool_json_forms() {
        let ball = ToolProfile::ball(6.0).expect("ball");
        let json = serde_json::to_string(&ball).expect("json");
        assert_eq!(json, r#"{"spec":"ball-6"}"#);
        assert_eq!(serde_json::from_str::<ToolProfile>(&json).ok(), Some(ball));
        let custom: ToolProfile =
            serde_json::from_str(r#"{"radius_mm": [0, 3, 3], "height_mm": [0, 0, 20]}"#).expect("custom");
        assert_eq!(custom.max_height_mm(), 20.0);
        assert!(
            serde_json::from_str::<ToolProfile>(r#"{"radius_mm": [0, 3], "height_mm": [1, 0]}"#).is_err()
        );
        assert!(serde_json::from_str::<ToolProfile>(r#"{"spec": "ball-6", "radius_mm": [0, 3]}"#).is_err());
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("t.tool");
        custom.write_tool_file(&path).expect("write");
        assert_eq!(ToolProfile::read_tool_file(&path).ok(), Some(custom));
    }

    fn arb_tool() -> impl Strategy<Value = ToolProfile> {
        prop_oneof![
            (0.1f64..50.0).prop_map(|d| ToolProfile::ball(d).expect("ball")),
            (0.1f64..50.0).prop_map(|d| ToolProfile::flat(d).expect("flat")),
            (0.1f64..50.0, 0.0f64..1.0).prop_map(|(d, f)| ToolProfile::bull(d, f * d / 2.0).expect("bull")),
            (0.1f64..50.0, 1.0f64..179.0, 0.0f64..0.99)
                .prop_map(|(d, a, f)| ToolProfile::v(d, a, f * d).expect("v")),
            prop::collection::vec((0.0f64..5.0, 0.0f64..5.0), 1..10).prop_map(|steps| {
                let (mut r, mut h) = (vec![0.0], vec![0.0]);
                for (dr, dh) in steps {
                    r.push(r[r.len() - 1] + dr);
                    h.push(h[h.len() - 1] + dh);
                }
                if let Some(last) = r.last_mut() {
                    *last += 0.1;
                }
                ToolProfile::custom(r, h).expect("custom")
            }),
        ]
    }

    proptest! {
        #[test]
        fn height_is_monotone_and_defined_exactly_on_the_disc(tool in arb_tool()) {
            let radius = tool.radius_mm();
            let mut prev = 0.0;
            for i in 0..=200 {
                let r = radius * (f64::from(i) / 200.0);
                let h = tool.height_at(r);
                prop_assert!(h.is_some(), "{r}");
                let h = h.unwrap_or_default();
                prop_assert!(h >= prev - 1e-12, "{tool:?} at {r}: {h} < {prev}");
                prev = h;
            }
            prop_assert_eq!(tool.height_at(0.0), Some(0.0));
            prop_assert!(tool.height_at(radius * (1.0 + 1e-9) + 1e-12).is_none());
        }
    }
}

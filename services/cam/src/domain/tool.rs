//! Cutting tools: the cutting profile (ball, flat, bull-nose, V, custom), cutting length, shank,
//! holder and flutes, the `.tool` text format and the tool library.
//!
//! # The `.tool` format
//!
//! UTF-8 text, one `key = value` per line; `#` starts a comment; blank lines are ignored; keys may
//! come in any order, each at most once. Lengths in millimetres, angles in degrees.
//!
//! ```text
//! # 6 mm ball end mill, 2 flutes
//! name = ball-6
//! type = ball                 # ball | flat | bull | v | custom
//! diameter_mm = 6
//! cutting_length_mm = 18      # fluted length from the tip
//! shank_diameter_mm = 6
//! stickout_mm = 30            # tip to holder face
//! holder_diameter_mm = 32
//! holder_length_mm = 40
//! flutes = 2
//! ```
//!
//! Shape keys by type: `bull` needs `corner_radius_mm`; `v` needs `angle_deg` (included angle) and
//! takes `tip_diameter_mm` (flat tip, default 0); `custom` needs `profile_r_mm` and `profile_h_mm`,
//! comma-separated radius/height pairs of the cross-section from the tip outward, both
//! non-decreasing, starting at r = 0, h = 0, ending at the tool radius (`diameter_mm` is then
//! optional and must match). Every key but `name`, `type` and the shape keys has a default derived
//! from the diameter. Errors name the file, line, key and value.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use depthmill_geometry::{ToolProfile, ToolSpec};

use super::CamError;

/// Kind of cutting profile.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ToolKind {
    Ball,
    Flat,
    Bull,
    V,
    Custom,
}

impl ToolKind {
    pub fn as_str(self) -> &'static str {
        match self {
            ToolKind::Ball => "ball",
            ToolKind::Flat => "flat",
            ToolKind::Bull => "bull",
            ToolKind::V => "v",
            ToolKind::Custom => "custom",
        }
    }
}

/// A cutting tool in its holder.
#[derive(Debug, Clone, PartialEq)]
pub struct Tool {
    pub name: String,
    pub kind: ToolKind,
    /// Cross-section of the cutting end, from the tip.
    pub profile: ToolProfile,
    /// Fluted length from the tip; only this part may touch the part.
    pub cutting_length_mm: f64,
    pub shank_diameter_mm: f64,
    /// From the tip to the holder face.
    pub stickout_mm: f64,
    pub holder_diameter_mm: f64,
    pub holder_length_mm: f64,
    pub flutes: u32,
}

fn err(name: &str, message: impl Into<String>) -> CamError {
    CamError::InvalidTool { name: name.to_string(), message: message.into() }
}

impl Tool {
    /// A tool of `spec`'s shape with holder geometry typical for its diameter: cutting length
    /// 3·D (at least the profile's height), shank D (at least 3 mm), stick-out cutting length + D +
    /// 10 mm, a 32 mm x 40 mm holder (larger for shanks over 12 mm), 2 flutes (3 for flat ≥ 6 mm).
    pub fn from_spec(spec: &ToolSpec) -> Result<Self, CamError> {
        let name = spec.to_string();
        let profile = spec.profile().map_err(|e| err(&name, e.to_string()))?;
        let (kind, flutes) = match spec {
            ToolSpec::Ball { .. } => (ToolKind::Ball, 2),
            ToolSpec::Flat { diameter_mm } => (ToolKind::Flat, if *diameter_mm >= 6.0 { 3 } else { 2 }),
            ToolSpec::Bull { .. } => (ToolKind::Bull, 2),
            ToolSpec::V { .. } => (ToolKind::V, 2),
        };
        Self::with_defaults(name, kind, profile, &BTreeMap::new(), flutes)
    }

    fn with_defaults(
        name: String,
        kind: ToolKind,
        profile: ToolProfile,
        given: &BTreeMap<&str, f64>,
        default_flutes: u32,
    ) -> Result<Self, CamError> {
        let d = profile.diameter_mm();
        let cutting_length_mm =
            given.get("cutting_length_mm").copied().unwrap_or((3.0 * d).max(profile.max_height_mm()));
        let shank_diameter_mm = given.get("shank_diameter_mm").copied().unwrap_or(d.max(3.0));
        let stickout_mm = given.get("stickout_mm").copied().unwrap_or(cutting_length_mm + d + 10.0);
        let holder_diameter_mm = given
            .get("holder_diameter_mm")
            .copied()
            .unwrap_or(if shank_diameter_mm > 12.0 { 50.0 } else { 32.0 });
        let holder_length_mm = given.get("holder_length_mm").copied().unwrap_or(40.0);
        let flutes = match given.get("flutes") {
            Some(f) if f.fract() == 0.0 && *f >= 1.0 && *f <= 32.0 => *f as u32,
            Some(f) => {
                return Err(err(&name, format!("flutes must be a whole number from 1 to 32, got {f}")));
            }
            None => default_flutes,
        };
        let tool = Tool {
            name,
            kind,
            profile,
            cutting_length_mm,
            shank_diameter_mm,
            stickout_mm,
            holder_diameter_mm,
            holder_length_mm,
            flutes,
        };
        tool.validate()?;
        Ok(tool)
    }

    /// Checks the geometry is physically consistent.
    pub fn validate(&self) -> Result<(), CamError> {
        let n = &self.name;
        let positive = |key: &str, v: f64| -> Result<(), CamError> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(err(n, format!("{key} must be positive, got {v}")))
            }
        };
        positive("cutting_length_mm", self.cutting_length_mm)?;
        positive("shank_diameter_mm", self.shank_diameter_mm)?;
        positive("stickout_mm", self.stickout_mm)?;
        positive("holder_diameter_mm", self.holder_diameter_mm)?;
        positive("holder_length_mm", self.holder_length_mm)?;
        if self.cutting_length_mm < self.profile.max_height_mm() - 1e-9 {
            return Err(err(
                n,
                format!(
                    "cutting_length_mm {} is shorter than the cutting profile's height {}",
                    self.cutting_length_mm,
                    self.profile.max_height_mm()
                ),
            ));
        }
        if self.stickout_mm < self.cutting_length_mm {
            return Err(err(
                n,
                format!(
                    "stickout_mm {} is shorter than cutting_length_mm {}",
                    self.stickout_mm, self.cutting_length_mm
                ),
            ));
        }
        if self.holder_diameter_mm < self.shank_diameter_mm {
            return Err(err(
                n,
                format!(
                    "holder_diameter_mm {} is narrower than the shank ({} mm)",
                    self.holder_diameter_mm, self.shank_diameter_mm
                ),
            ));
        }
        Ok(())
    }

    pub fn diameter_mm(&self) -> f64 {
        self.profile.diameter_mm()
    }

    pub fn radius_mm(&self) -> f64 {
        self.profile.radius_mm()
    }

    /// The non-cutting part above the cutting length as one profile from the tip: the shank from
    /// `cutting_length_mm` to `stickout_mm`, then the holder. Radius/height pairs, heights from the tip.
    pub fn body_profile(&self) -> Vec<(f64, f64)> {
        let shank_r = self.shank_diameter_mm / 2.0;
        let holder_r = self.holder_diameter_mm / 2.0;
        vec![
            (shank_r, self.cutting_length_mm),
            (shank_r, self.stickout_mm),
            (holder_r, self.stickout_mm),
            (holder_r, self.stickout_mm + self.holder_length_mm),
        ]
    }

    /// Parses a `.tool` file's text; `origin` names the file in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, CamError> {
        let mut values: BTreeMap<&str, (usize, &str)> = BTreeMap::new();
        for (i, raw) in text.lines().enumerate() {
            let line_no = i + 1;
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let (k, v) = line.split_once('=').ok_or_else(|| {
                err(origin, format!("line {line_no}: expected 'key = value', got '{line}'"))
            })?;
            let (k, v) = (k.trim(), v.trim());
            if values.insert(k, (line_no, v)).is_some() {
                return Err(err(origin, format!("line {line_no}: key '{k}' given twice")));
            }
        }
        const KNOWN: [&str; 16] = [
            "name",
            "type",
            "diameter_mm",
            "corner_radius_mm",
            "angle_deg",
            "tip_diameter_mm",
            "profile_r_mm",
            "profile_h_mm",
            "cutting_length_mm",
            "shank_diameter_mm",
            "stickout_mm",
            "holder_diameter_mm",
            "holder_length_mm",
            "flutes",
            "material",
            "description",
        ];
        if let Some((k, (line, _))) = values.iter().find(|(k, _)| !KNOWN.contains(k)) {
            return Err(err(origin, format!("line {line}: unknown key '{k}' (known: {})", KNOWN.join(", "))));
        }
        let text_of = |k: &str| values.get(k).map(|(_, v)| *v);
        let number = |k: &str| -> Result<Option<f64>, CamError> {
            match values.get(k) {
                None => Ok(None),
                Some((line, v)) => v
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .map(Some)
                    .ok_or_else(|| err(origin, format!("line {line}: {k} = '{v}' is not a number"))),
            }
        };
        let list = |k: &str| -> Result<Option<Vec<f64>>, CamError> {
            match values.get(k) {
                None => Ok(None),
                Some((line, v)) => v
                    .split(',')
                    .map(|s| s.trim().parse::<f64>().ok().filter(|x| x.is_finite()))
                    .collect::<Option<Vec<_>>>()
                    .map(Some)
                    .ok_or_else(|| {
                        err(
                            origin,
                            format!("line {line}: {k} = '{v}' is not a comma-separated list of numbers"),
                        )
                    }),
            }
        };
        let require = |k: &str, v: Option<f64>| v.ok_or_else(|| err(origin, format!("missing key '{k}'")));
        let name = text_of("name").ok_or_else(|| err(origin, "missing key 'name'"))?.to_string();
        let kind = match text_of("type") {
            Some("ball") => ToolKind::Ball,
            Some("flat") => ToolKind::Flat,
            Some("bull") => ToolKind::Bull,
            Some("v") => ToolKind::V,
            Some("custom") => ToolKind::Custom,
            Some(other) => {
                let line = values.get("type").map(|(l, _)| *l).unwrap_or(0);
                return Err(err(
                    origin,
                    format!("line {line}: type '{other}' is not one of ball, flat, bull, v, custom"),
                ));
            }
            None => return Err(err(origin, "missing key 'type'")),
        };
        let diameter = number("diameter_mm")?;
        let geometry = |r: Result<ToolProfile, depthmill_geometry::GeometryError>| {
            r.map_err(|e| err(origin, e.to_string()))
        };
        let profile = match kind {
            ToolKind::Ball => geometry(ToolProfile::ball(require("diameter_mm", diameter)?))?,
            ToolKind::Flat => geometry(ToolProfile::flat(require("diameter_mm", diameter)?))?,
            ToolKind::Bull => geometry(ToolProfile::bull(
                require("diameter_mm", diameter)?,
                require("corner_radius_mm", number("corner_radius_mm")?)?,
            ))?,
            ToolKind::V => geometry(ToolProfile::v(
                require("diameter_mm", diameter)?,
                require("angle_deg", number("angle_deg")?)?,
                number("tip_diameter_mm")?.unwrap_or(0.0),
            ))?,
            ToolKind::Custom => {
                let r = list("profile_r_mm")?.ok_or_else(|| err(origin, "missing key 'profile_r_mm'"))?;
                let h = list("profile_h_mm")?.ok_or_else(|| err(origin, "missing key 'profile_h_mm'"))?;
                let p = geometry(ToolProfile::custom(r, h))?;
                if let Some(d) = diameter
                    && (d - p.diameter_mm()).abs() > 1e-9
                {
                    return Err(err(
                        origin,
                        format!("diameter_mm {d} does not match the profile's diameter {}", p.diameter_mm()),
                    ));
                }
                p
            }
        };
        let mut given = BTreeMap::new();
        for k in [
            "cutting_length_mm",
            "shank_diameter_mm",
            "stickout_mm",
            "holder_diameter_mm",
            "holder_length_mm",
            "flutes",
        ] {
            if let Some(v) = number(k)? {
                given.insert(k, v);
            }
        }
        Self::with_defaults(name, kind, profile, &given, 2).map_err(|e| match e {
            CamError::InvalidTool { message, .. } => err(origin, message),
            other => other,
        })
    }

    /// Reads a `.tool` file.
    pub fn read_file(path: &Path) -> Result<Self, CamError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| CamError::Io { path: path.display().to_string(), message: e.to_string() })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// The `.tool` text of this tool (parses back to an equal tool).
    pub fn to_text(&self) -> String {
        let mut s = format!("# depthmill tool\nname = {}\ntype = {}\n", self.name, self.kind.as_str());
        let list = |v: &[f64]| v.iter().map(|x| format!("{x}")).collect::<Vec<_>>().join(", ");
        match (self.kind, self.profile.spec()) {
            (ToolKind::Bull, Some(ToolSpec::Bull { diameter_mm, corner_radius_mm })) => {
                s += &format!("diameter_mm = {diameter_mm}\ncorner_radius_mm = {corner_radius_mm}\n");
            }
            (ToolKind::V, Some(ToolSpec::V { diameter_mm, included_angle_deg, tip_flat_diameter_mm })) => {
                s += &format!(
                    "diameter_mm = {diameter_mm}\nangle_deg = {included_angle_deg}\ntip_diameter_mm = {tip_flat_diameter_mm}\n"
                );
            }
            (ToolKind::Ball | ToolKind::Flat, _) => s += &format!("diameter_mm = {}\n", self.diameter_mm()),
            _ => {
                s += &format!(
                    "profile_r_mm = {}\nprofile_h_mm = {}\n",
                    list(self.profile.radii_mm()),
                    list(self.profile.heights_mm())
                );
            }
        }
        s += &format!(
            "cutting_length_mm = {}\nshank_diameter_mm = {}\nstickout_mm = {}\nholder_diameter_mm = {}\nholder_length_mm = {}\nflutes = {}\n",
            self.cutting_length_mm,
            self.shank_diameter_mm,
            self.stickout_mm,
            self.holder_diameter_mm,
            self.holder_length_mm,
            self.flutes
        );
        s
    }
}

/// Tools by name: `.tool` files of a folder, falling back to standard names (`ball-6`, `flat-6`,
/// `bull-6-1`, `v-6-90`) with default holder geometry.
#[derive(Debug, Clone, Default)]
pub struct ToolLibrary {
    tools: BTreeMap<String, Tool>,
}

/// The tool library that ships with depthmill (`services/cam/tools/`), compiled in.
const BUILTIN: &[(&str, &str)] = &[
    ("ball-1.tool", include_str!("../../tools/ball-1.tool")),
    ("ball-3.tool", include_str!("../../tools/ball-3.tool")),
    ("ball-6.tool", include_str!("../../tools/ball-6.tool")),
    ("flat-3.tool", include_str!("../../tools/flat-3.tool")),
    ("flat-6.tool", include_str!("../../tools/flat-6.tool")),
    ("flat-10.tool", include_str!("../../tools/flat-10.tool")),
    ("bull-6-1.tool", include_str!("../../tools/bull-6-1.tool")),
    ("v-6-90.tool", include_str!("../../tools/v-6-90.tool")),
];

impl ToolLibrary {
    /// The library shipped with depthmill.
    pub fn builtin() -> Result<Self, CamError> {
        let mut lib = Self::default();
        for (file, text) in BUILTIN {
            lib.insert(Tool::parse(text, file)?);
        }
        Ok(lib)
    }

    /// This library with the tools of `other` added (replacing same-named ones).
    pub fn merged(mut self, other: ToolLibrary) -> Self {
        self.tools.extend(other.tools);
        self
    }

    /// Loads every `*.tool` file of `dir`. A tool named twice is an error naming both files.
    pub fn load_dir(dir: &Path) -> Result<Self, CamError> {
        let io = |e: std::io::Error| CamError::Io { path: dir.display().to_string(), message: e.to_string() };
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(io)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "tool"))
            .collect();
        files.sort();
        let mut lib = Self::default();
        let mut origin: BTreeMap<String, PathBuf> = BTreeMap::new();
        for f in files {
            let tool = Tool::read_file(&f)?;
            if let Some(first) = origin.insert(tool.name.clone(), f.clone()) {
                return Err(err(
                    &tool.name,
                    format!("defined twice: {} and {}", first.display(), f.display()),
                ));
            }
            lib.tools.insert(tool.name.clone(), tool);
        }
        Ok(lib)
    }

    /// The tool called `name`: from the library, else a standard name with default geometry.
    pub fn resolve(&self, name: &str) -> Result<Tool, CamError> {
        if let Some(t) = self.tools.get(name) {
            return Ok(t.clone());
        }
        let spec: ToolSpec = name.parse().map_err(|_| {
            err(
                name,
                format!(
                    "not in the tool library ({}) and not a standard name like ball-6, flat-6, bull-6-1 or v-6-90",
                    self.tools.keys().cloned().collect::<Vec<_>>().join(", ")
                ),
            )
        })?;
        Tool::from_spec(&spec)
    }

    pub fn tools(&self) -> impl Iterator<Item = &Tool> {
        self.tools.values()
    }

    pub fn insert(&mut self, tool: Tool) {
        self.tools.insert(tool.name.clone(), tool);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_round_trips_through_its_text() {
        for name in ["ball-6", "flat-3", "bull-6-1", "v-6-90"] {
            let tool = Tool::from_spec(&name.parse().expect("spec")).expect("tool");
            let back = Tool::parse(&tool.to_text(), "mem").expect("parse");
            assert_eq!(back, tool, "{name}");
        }
        let custom = "name = lollipop\ntype = custom\nprofile_r_mm = 0, 1, 2\nprofile_h_mm = 0, 0.5, 2\n";
        let tool = Tool::parse(custom, "mem").expect("custom");
        assert_eq!(tool.diameter_mm(), 4.0);
        assert_eq!(Tool::parse(&tool.to_text(), "mem").expect("again"), tool);
    }

    #[test]
    fn bad_files_name_the_line_and_the_problem() {
        let cases = [
            ("name = x\ntype = ball\ndiameter_mm = -3\n", "diameter"),
            ("name = x\ntype = ball\ndiameter_mm = six\n", "line 3"),
            ("name = x\ntype = drill\n", "line 2: type 'drill'"),
            ("name = x\ntype = ball\ndiameter_mm = 6\nholder_diameter_mm = 4\n", "narrower than the shank"),
            ("name = x\ntype = custom\nprofile_r_mm = 0, 2, 1\nprofile_h_mm = 0, 1, 2\n", "radius_mm[2]"),
            ("name = x\ntype = ball\ndiameter_mm = 6\ncolour = red\n", "unknown key 'colour'"),
            ("name = x\ntype = ball\ndiameter_mm = 6\ndiameter_mm = 7\n", "given twice"),
            ("type = ball\ndiameter_mm = 6\n", "missing key 'name'"),
            (
                "name = x\ntype = ball\ndiameter_mm = 6\ncutting_length_mm = 1\n",
                "shorter than the cutting profile",
            ),
        ];
        for (text, needle) in cases {
            let e = Tool::parse(text, "t.tool").expect_err(text).to_string();
            assert!(e.contains(needle) && e.contains("t.tool"), "{text:?} -> {e}");
        }
    }

    #[test]
    fn the_shipped_library_loads() {
        let lib = ToolLibrary::builtin().expect("builtin");
        assert_eq!(lib.tools().count(), 8);
        assert_eq!(lib.resolve("flat-6").expect("flat-6").flutes, 3);
        assert_eq!(lib.resolve("v-6-90").expect("v").kind, ToolKind::V);
    }

    #[test]
    fn the_library_resolves_files_then_standard_names() {
        let dir = tempfile::tempdir().expect("tmp");
        std::fs::write(
            dir.path().join("a.tool"),
            "name = my-ball\ntype = ball\ndiameter_mm = 4\nflutes = 4\n",
        )
        .expect("w");
        let lib = ToolLibrary::load_dir(dir.path()).expect("load");
        assert_eq!(lib.resolve("my-ball").expect("lib").flutes, 4);
        assert_eq!(lib.resolve("flat-6").expect("std").diameter_mm(), 6.0);
        assert!(lib.resolve("spoon-3").expect_err("unknown").to_string().contains("my-ball"));
    }
}

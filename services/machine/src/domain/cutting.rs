//! Cutting forces: the Kienzle model per material, from the chip the tool takes in one spindle
//! revolution to the torque, power and motor current of the spindle.
//!
//! Kienzle: the specific cutting force at chip thickness `h` (mm) is `kc(h) = kc1.1 · h^(−mc)`
//! (N/mm²), so a chip of width `b` takes `Fc = kc1.1 · b · h^(1−mc)`. Energy per revolution is the
//! removed volume times the specific cutting energy, `E = kc(hm) · V` (N·mm = mJ, with `V` in mm³),
//! with `hm` the mean chip thickness over the engaged arc; the mean torque over the revolution is
//! `T = E / 2π` (N·mm). This is the same model as `Fc·r` summed over the teeth in contact, written
//! with the volume the material-removal simulation measures directly. A hardness factor scales
//! `kc1.1` (1 = nominal; a hard inclusion is 1.5-3).
//!
//! Mean chip thickness for a radial engagement `φe` (entry at 0, exit at `φe`, radians) and feed
//! per tooth `fz`: `hm = fz · (1 − cos φe) / φe` (for `φe → 0`, `hm → 0`).

use serde::{Deserialize, Serialize};

/// Kienzle constants of a work material.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material {
    pub name: String,
    /// Specific cutting force for a 1 mm × 1 mm chip, N/mm².
    pub kc11_n_mm2: f64,
    /// Kienzle exponent.
    pub mc: f64,
    /// Density, g/cm³ (for the productivity index).
    pub density_g_cm3: f64,
}

/// The shipped materials: the middle of the ranges in DESIGN §5 (aluminium kc1.1 700-800, mc 0.25;
/// brass 700-780, 0.18-0.27; mild steel 1350-1780, 0.17-0.21) and two soft stocks whose figures
/// are assumptions (machinable wax, a generic engineering plastic).
pub fn materials() -> Vec<Material> {
    let m = |name: &str, kc: f64, mc: f64, rho: f64| Material {
        name: name.to_string(),
        kc11_n_mm2: kc,
        mc,
        density_g_cm3: rho,
    };
    vec![
        m("aluminium", 750.0, 0.25, 2.70),
        m("brass", 740.0, 0.22, 8.50),
        m("mild_steel", 1560.0, 0.19, 7.85),
        m("wax", 40.0, 0.30, 0.93),
        m("plastic", 150.0, 0.30, 1.20),
    ]
}

/// Looks a material up by name (case-insensitive; `aluminum`, `steel`, `machinable_wax` accepted).
pub fn material(name: &str) -> Option<Material> {
    let key = name.trim().to_ascii_lowercase().replace([' ', '-'], "_");
    let key = match key.as_str() {
        "aluminum" | "al" => "aluminium",
        "steel" | "mild steel" => "mild_steel",
        "machinable_wax" => "wax",
        "pom" | "delrin" | "abs" | "pvc" => "plastic",
        k => k,
    };
    materials().into_iter().find(|m| m.name == key)
}

impl Material {
    /// `kc(h)` in N/mm² at chip thickness `h_mm` (clamped below at 1 µm, where the model ends).
    pub fn specific_force(&self, h_mm: f64) -> f64 {
        self.kc11_n_mm2 * h_mm.max(0.001).powf(-self.mc)
    }
}

/// Mean chip thickness (mm) for feed per tooth `fz_mm` and radial engagement `engagement_rad`.
pub fn mean_chip_thickness(fz_mm: f64, engagement_rad: f64) -> f64 {
    if engagement_rad <= 1e-9 || fz_mm <= 0.0 {
        return 0.0;
    }
    let phi = engagement_rad.min(std::f64::consts::PI);
    fz_mm * (1.0 - phi.cos()) / phi
}

/// The load of one spindle revolution.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct RevLoad {
    /// Mean cutting torque at the spindle over the revolution, N·m.
    pub torque_nm: f64,
    /// Cutting power, W (torque × ω).
    pub power_w: f64,
    /// Mean chip thickness, mm.
    pub chip_mm: f64,
}

/// Torque and power of a revolution that removed `volume_mm3` (hardness-weighted: pass the volume
/// times the hardness factor) with feed per tooth `fz_mm`, engagement `engagement_rad`, at `rpm`.
pub fn rev_load(material: &Material, volume_mm3: f64, fz_mm: f64, engagement_rad: f64, rpm: f64) -> RevLoad {
    if volume_mm3 <= 0.0 {
        return RevLoad::default();
    }
    let hm = mean_chip_thickness(fz_mm, engagement_rad);
    let energy_nmm = material.specific_force(hm) * volume_mm3;
    let torque_nm = energy_nmm / std::f64::consts::TAU / 1000.0;
    let power_w = torque_nm * rpm * std::f64::consts::TAU / 60.0;
    RevLoad { torque_nm, power_w, chip_mm: hm }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn materials_match_the_design_ranges() {
        let al = material("Aluminum").expect("aluminium");
        assert!((700.0..=800.0).contains(&al.kc11_n_mm2) && al.mc == 0.25);
        let st = material("mild steel").expect("steel");
        assert!((1350.0..=1780.0).contains(&st.kc11_n_mm2) && (0.17..=0.21).contains(&st.mc));
        let br = material("brass").expect("brass");
        assert!((700.0..=780.0).contains(&br.kc11_n_mm2) && (0.18..=0.27).contains(&br.mc));
        assert!(material("unobtainium").is_none());
    }

    #[test]
    fn kienzle_force_equals_energy_per_volume() {
        // A chip b × h over a length L: Fc·L = kc(h)·b·h·L.
        let al = material("aluminium").expect("al");
        let (b, h, l) = (2.0f64, 0.05f64, 10.0f64);
        let fc = al.kc11_n_mm2 * b * h.powf(1.0 - al.mc);
        assert!((fc * l - al.specific_force(h) * b * h * l).abs() < 1e-9);
    }

    #[test]
    fn chip_thickness_limits() {
        // Slotting (180°): hm = 2·fz/π.
        let hm = mean_chip_thickness(0.1, std::f64::consts::PI);
        assert!((hm - 0.2 / std::f64::consts::PI).abs() < 1e-12);
        assert_eq!(mean_chip_thickness(0.1, 0.0), 0.0);
        assert!(mean_chip_thickness(0.1, 0.3) < mean_chip_thickness(0.1, 1.0));
    }

    #[test]
    fn a_typical_aluminium_cut_is_a_few_torque_counts() {
        // DESIGN §5 scale check: a typical aluminium cut is about 0.16 N·m / 33 W on this
        // machine, i.e. about one count (0.139 N·m) of the torque channel. A flat-6 roughing
        // pass 2 mm deep, 1.5 mm wide, 0.1 mm per revolution (2 teeth, fz 0.05), at 2000 rpm.
        let al = material("aluminium").expect("al");
        let phi = (1.0 - 2.0 * 1.5 / 6.0f64).acos(); // radial engagement of a 1.5 mm side cut
        let load = rev_load(&al, 2.0 * 1.5 * 0.1, 0.05, phi, 2000.0);
        assert!((0.03..0.3).contains(&load.torque_nm), "{load:?}");
        assert!((5.0..60.0).contains(&load.power_w), "{load:?}");
    }
}

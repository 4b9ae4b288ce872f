//! [`Face`]: which view of the part a height map looks from.

use std::fmt;
use std::str::FromStr;

use nalgebra::{Unit, Vector3};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::error::GeometryError;

/// The view a height map looks from, named by the outward normal of the part face that ends up
/// facing the spindle (+Z of the view frame).
///
/// Text form (Display, FromStr, serde): `+Z`, `-Z`, `+X`, `-X`, `+Y`, `-Y`, `A=<deg>` for a
/// rotation of the part by `<deg>` degrees about the X axis (the mill's 4th, A axis), or
/// `N=<x>,<y>,<z>` for any outward normal (a unit vector; the text is normalised on parsing).
/// `A=0` is the same view as `+Z`, `A=90` as `+Y`, `A=180` as `-Z`, `A=-90` as `-Y`: the face
/// with outward normal `(0, sin a, cos a)` looks up. See [`Face::view_from_part`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Face {
    /// Looking down on the part's top, the identity view.
    #[default]
    PosZ,
    NegZ,
    PosX,
    NegX,
    PosY,
    NegY,
    /// The part rotated by `angle_deg` about the X axis (finite).
    A {
        angle_deg: f64,
    },
    /// Any outward normal, a finite unit vector (build it with [`Face::normal`]).
    Normal {
        x: f64,
        y: f64,
        z: f64,
    },
}

impl Face {
    /// The six named views, in the order `+Z -Z +X -X +Y -Y`.
    pub const NAMED: [Face; 6] = [Face::PosZ, Face::NegZ, Face::PosX, Face::NegX, Face::PosY, Face::NegY];

    /// The face with outward normal `n` (normalised); `None` for a zero or non-finite vector.
    pub fn normal(n: Vector3<f64>) -> Option<Face> {
        let norm = n.norm();
        if !norm.is_finite() || norm < 1e-12 {
            return None;
        }
        let u = n / norm;
        Some(Face::Normal { x: u.x, y: u.y, z: u.z })
    }

    /// Outward normal, in the part frame, of the face this view looks at.
    pub fn normal_in_part(&self) -> Unit<Vector3<f64>> {
        let v = match *self {
            Face::PosZ => Vector3::z(),
            Face::NegZ => -Vector3::z(),
            Face::PosX => Vector3::x(),
            Face::NegX => -Vector3::x(),
            Face::PosY => Vector3::y(),
            Face::NegY => -Vector3::y(),
            Face::A { angle_deg } => {
                let a = angle_deg.to_radians();
                Vector3::new(0.0, a.sin(), a.cos())
            }
            Face::Normal { x, y, z } => Vector3::new(x, y, z),
        };
        Unit::new_normalize(v)
    }
}

impl fmt::Display for Face {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Face::PosZ => f.write_str("+Z"),
            Face::NegZ => f.write_str("-Z"),
            Face::PosX => f.write_str("+X"),
            Face::NegX => f.write_str("-X"),
            Face::PosY => f.write_str("+Y"),
            Face::NegY => f.write_str("-Y"),
            Face::A { angle_deg } => write!(f, "A={angle_deg}"),
            Face::Normal { x, y, z } => write!(f, "N={x},{y},{z}"),
        }
    }
}

impl FromStr for Face {
    type Err = GeometryError;

    /// Parses `+Z`, `-z`, `A=90`, `a=-22.5` (case-insensitive, surrounding blanks ignored).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let t = s.trim();
        let err = || GeometryError::Parse {
            what: "face",
            input: s.to_string(),
            expected: "+Z, -Z, +X, -X, +Y, -Y, A=<finite degrees> or N=<x>,<y>,<z>",
        };
        let face = match t.to_ascii_uppercase().as_str() {
            "+Z" => Face::PosZ,
            "-Z" => Face::NegZ,
            "+X" => Face::PosX,
            "-X" => Face::NegX,
            "+Y" => Face::PosY,
            "-Y" => Face::NegY,
            u if u.starts_with("N=") => {
                let parts: Vec<f64> = u[2..]
                    .split(',')
                    .map(|c| c.trim().parse::<f64>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| err())?;
                match parts[..] {
                    [x, y, z] => Face::normal(Vector3::new(x, y, z)).ok_or_else(err)?,
                    _ => return Err(err()),
                }
            }
            u => {
                let deg = u.strip_prefix("A=").ok_or_else(err)?;
                let angle_deg: f64 = deg.trim().parse().map_err(|_| err())?;
                if !angle_deg.is_finite() {
                    return Err(err());
                }
                Face::A { angle_deg }
            }
        };
        Ok(face)
    }
}

impl Serialize for Face {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for Face {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_round_trip() {
        for face in Face::NAMED.into_iter().chain([Face::A { angle_deg: 90.0 }, Face::A { angle_deg: -22.5 }])
        {
            let text = face.to_string();
            assert_eq!(text.parse::<Face>().ok(), Some(face), "{text}");
            let json = serde_json::to_string(&face).expect("serialize");
            assert_eq!(json, format!("\"{text}\""));
            assert_eq!(serde_json::from_str::<Face>(&json).ok(), Some(face));
        }
        assert_eq!(Face::A { angle_deg: 90.0 }.to_string(), "A=90");
        assert_eq!(" a=45 ".parse::<Face>().ok(), Some(Face::A { angle_deg: 45.0 }));
        assert_eq!("-x".parse::<Face>().ok(), Some(Face::NegX));
        let n: Face = "N=0,3,4".parse().expect("normal");
        assert_eq!(n, Face::Normal { x: 0.0, y: 0.6, z: 0.8 });
        assert_eq!(n.to_string().parse::<Face>().ok(), Some(n));
    }

    #[test]
    fn bad_text_is_rejected() {
        for bad in [
            "",
            "Z",
            "+W",
            "A=",
            "A=abc",
            "A=inf",
            "A=NaN",
            "B=3",
            "N=0,0,0",
            "N=1,2",
            "N=1,x,2",
            "N=1,2,3,4",
        ] {
            let e = bad.parse::<Face>().expect_err(bad);
            assert!(e.to_string().contains("cannot parse face"), "{e}");
        }
    }
}

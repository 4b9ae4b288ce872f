//! Frames and poses on nalgebra: [`Pose`], X/Y/Z + yaw/pitch/roll conversion, and the rotation
//! that brings a [`Face`] up.
//!
//! Naming: a pose `b_from_a` maps coordinates in frame `a` to frame `b` (`p_b = b_from_a * p_a`).
//! Translations are in millimetres; angles are degrees at the API and radians inside.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{GeometryError, Result};
use crate::face::Face;

/// A rigid transform in millimetres (rotation then translation).
pub type Pose = Isometry3<f64>;

/// A pose as X, Y, Z (mm) and yaw, pitch, roll (degrees), in the intrinsic Z-Y'-X'' (ZYX)
/// convention: `R = Rz(yaw) · Ry(pitch) · Rx(roll)`, i.e. roll about X is applied first, then
/// pitch about Y, then yaw about Z, all about the fixed axes.
///
/// [`XyzYpr::from_pose`] returns yaw and roll in `[-180, 180]` and pitch in `[-90, 90]`; a round
/// trip `from_pose(to_pose(v))` reproduces `v` (to ~1e-9) when its angles lie in those ranges and
/// pitch is away from ±90° (gimbal lock, where only yaw ± roll is defined).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct XyzYpr {
    pub x_mm: f64,
    pub y_mm: f64,
    pub z_mm: f64,
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    pub roll_deg: f64,
}

impl XyzYpr {
    /// The pose, after checking that all six values are finite.
    pub fn to_pose(&self) -> Result<Pose> {
        let fields = [
            ("x_mm", self.x_mm),
            ("y_mm", self.y_mm),
            ("z_mm", self.z_mm),
            ("yaw_deg", self.yaw_deg),
            ("pitch_deg", self.pitch_deg),
            ("roll_deg", self.roll_deg),
        ];
        if let Some((field, v)) = fields.into_iter().find(|(_, v)| !v.is_finite()) {
            return Err(GeometryError::invalid(field, v, "a finite value"));
        }
        Ok(Isometry3::from_parts(
            Translation3::new(self.x_mm, self.y_mm, self.z_mm),
            rotation_from_ypr_deg(self.yaw_deg, self.pitch_deg, self.roll_deg),
        ))
    }

    /// Position and ZYX angles of `pose`.
    pub fn from_pose(pose: &Pose) -> Self {
        let (roll, pitch, yaw) = pose.rotation.euler_angles();
        let t = pose.translation.vector;
        XyzYpr {
            x_mm: t.x,
            y_mm: t.y,
            z_mm: t.z,
            yaw_deg: yaw.to_degrees(),
            pitch_deg: pitch.to_degrees(),
            roll_deg: roll.to_degrees(),
        }
    }
}

/// `Rz(yaw) · Ry(pitch) · Rx(roll)` from degrees (see [`XyzYpr`]).
pub fn rotation_from_ypr_deg(yaw_deg: f64, pitch_deg: f64, roll_deg: f64) -> UnitQuaternion<f64> {
    // nalgebra's from_euler_angles(roll, pitch, yaw) is exactly Rz(yaw)·Ry(pitch)·Rx(roll).
    UnitQuaternion::from_euler_angles(roll_deg.to_radians(), pitch_deg.to_radians(), yaw_deg.to_radians())
}

impl Face {
    /// `view_from_part`: the rotation that brings this face's outward normal
    /// ([`Face::normal_in_part`]) to +Z, so a 3-axis mill sees the face from above.
    ///
    /// One rotation about a machine axis: `+Z` identity; `-Z` 180° about X; `+Y` +90° about X;
    /// `-Y` −90° about X; `+X` −90° about Y; `-X` +90° about Y; `A=a` `a` degrees about X (so
    /// `A=90` equals `+Y` and `A=180` equals `-Z`); `N=n` the shortest rotation taking `n` to +Z
    /// (180° about X when `n` points straight down).
    pub fn view_from_part(&self) -> UnitQuaternion<f64> {
        let about = |axis: nalgebra::Unit<Vector3<f64>>, deg: f64| {
            UnitQuaternion::from_axis_angle(&axis, deg.to_radians())
        };
        match *self {
            Face::PosZ => UnitQuaternion::identity(),
            Face::NegZ => about(Vector3::x_axis(), 180.0),
            Face::PosY => about(Vector3::x_axis(), 90.0),
            Face::NegY => about(Vector3::x_axis(), -90.0),
            Face::PosX => about(Vector3::y_axis(), -90.0),
            Face::NegX => about(Vector3::y_axis(), 90.0),
            Face::A { angle_deg } => about(Vector3::x_axis(), angle_deg),
            Face::Normal { .. } => {
                let n = self.normal_in_part();
                // The shortest rotation; straight down has no unique one: turn 180° about X like -Z.
                UnitQuaternion::rotation_between(&n, &Vector3::z())
                    .unwrap_or_else(|| about(Vector3::x_axis(), 180.0))
            }
        }
    }

    /// [`Face::view_from_part`] as a [`Pose`] (no translation).
    pub fn view_from_part_pose(&self) -> Pose {
        Isometry3::from_parts(Translation3::identity(), self.view_from_part())
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Point3;
    use proptest::prelude::*;

    use super::*;

    fn near(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    #[test]
    fn ypr_is_zyx() {
        let (y, p, r) = (30f64, -20f64, 75f64);
        let q = rotation_from_ypr_deg(y, p, r);
        let rz = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), y.to_radians());
        let ry = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), p.to_radians());
        let rx = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), r.to_radians());
        assert!(q.angle_to(&(rz * ry * rx)) < 1e-12);
        // Pure yaw of 90°: +X goes to +Y.
        let pose = XyzYpr { x_mm: 1.0, yaw_deg: 90.0, ..Default::default() }.to_pose().expect("finite");
        let p = pose * Point3::new(1.0, 0.0, 0.0);
        assert!((p - Point3::new(1.0, 1.0, 0.0)).norm() < 1e-12);
        let e = XyzYpr { pitch_deg: f64::NAN, ..Default::default() }.to_pose().expect_err("nan");
        assert_eq!(e.to_string(), "invalid pitch_deg NaN: expected a finite value");
    }

    #[test]
    fn named_faces_match_a_angles() {
        let pairs = [(Face::PosZ, 0.0), (Face::PosY, 90.0), (Face::NegZ, 180.0), (Face::NegY, -90.0)];
        for (face, a) in pairs {
            assert!(
                face.view_from_part().angle_to(&Face::A { angle_deg: a }.view_from_part()) < 1e-12,
                "{face}"
            );
        }
    }

    fn arb_face() -> impl Strategy<Value = Face> {
        prop_oneof![
            (0usize..6).prop_map(|i| Face::NAMED[i]),
            (-720.0f64..720.0).prop_map(|angle_deg| Face::A { angle_deg }),
            (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0)
                .prop_filter_map("zero", |(x, y, z)| Face::normal(Vector3::new(x, y, z))),
            Just(Face::Normal { x: 0.0, y: 0.0, z: -1.0 }),
        ]
    }

    proptest! {
        #[test]
        fn face_rotation_brings_normal_to_plus_z(face in arb_face()) {
            let up = face.view_from_part() * face.normal_in_part().into_inner();
            prop_assert!((up - Vector3::z()).norm() < 1e-12, "{face}: {up:?}");
        }

        #[test]
        fn xyz_ypr_round_trip(
            x in -1e4f64..1e4, y in -1e4f64..1e4, z in -1e4f64..1e4,
            yaw in -179.0f64..179.0, pitch in -89.0f64..89.0, roll in -179.0f64..179.0,
        ) {
            let v = XyzYpr { x_mm: x, y_mm: y, z_mm: z, yaw_deg: yaw, pitch_deg: pitch, roll_deg: roll };
            let back = XyzYpr::from_pose(&v.to_pose().expect("finite"));
            prop_assert!(near(back.x_mm, x) && near(back.y_mm, y) && near(back.z_mm, z));
            prop_assert!(near(back.yaw_deg, yaw) && near(back.pitch_deg, pitch) && near(back.roll_deg, roll),
                "{v:?} -> {back:?}");
        }
    }
}

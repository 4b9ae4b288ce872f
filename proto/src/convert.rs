//! Conversions between wire types and `depthmill-geometry` types, shared by both ends of every wire.

use crate::types::v1 as pb;

/// A wire transform (`repeated double`, row-major 4x4) as a matrix: `Ok(None)` when empty,
/// `Err(len)` when it has neither 0 nor 16 numbers.
pub fn matrix4_row_major(v: &[f64]) -> Result<Option<[[f64; 4]; 4]>, usize> {
    match v.len() {
        0 => Ok(None),
        16 => Ok(Some(std::array::from_fn(|r| std::array::from_fn(|c| v[4 * r + c])))),
        n => Err(n),
    }
}

impl From<depthmill_geometry::ArtifactRef> for pb::ArtifactRef {
    fn from(a: depthmill_geometry::ArtifactRef) -> Self {
        Self { uri: a.uri, sha256: a.sha256, size: a.size, media_type: a.media_type }
    }
}

impl From<pb::ArtifactRef> for depthmill_geometry::ArtifactRef {
    fn from(a: pb::ArtifactRef) -> Self {
        Self { uri: a.uri, sha256: a.sha256, size: a.size, media_type: a.media_type }
    }
}

/// Wire units (`LengthUnit`, an `i32` on the wire) as the units to read an input in; `Err(v)` for
/// a value the enum does not have.
pub fn units(v: i32) -> Result<depthmill_geometry::Units, i32> {
    use depthmill_geometry::{LengthUnit, Units};
    match pb::LengthUnit::try_from(v) {
        Ok(pb::LengthUnit::Unspecified) => Ok(Units::Auto),
        Ok(pb::LengthUnit::Mm) => Ok(Units::Given(LengthUnit::Millimetre)),
        Ok(pb::LengthUnit::M) => Ok(Units::Given(LengthUnit::Metre)),
        Ok(pb::LengthUnit::In) => Ok(Units::Given(LengthUnit::Inch)),
        Err(_) => Err(v),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn row_major_matrices() {
        let v: Vec<f64> = (0..16).map(f64::from).collect();
        let m = matrix4_row_major(&v).expect("16").expect("some");
        assert_eq!(m[1][2], 6.0);
        assert_eq!(m[3], [12.0, 13.0, 14.0, 15.0]);
        assert_eq!(matrix4_row_major(&[]), Ok(None));
        assert_eq!(matrix4_row_major(&[1.0; 9]), Err(9));
    }

    #[test]
    fn wire_units() {
        use depthmill_geometry::{LengthUnit, Units};
        assert_eq!(units(0), Ok(Units::Auto));
        assert_eq!(units(pb::LengthUnit::In as i32), Ok(Units::Given(LengthUnit::Inch)));
        assert_eq!(units(9), Err(9));
    }
}

//! [`ArtifactRef`]: a reference to a content-addressed blob, and the [`MediaType`]s depthmill knows.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::error::{GeometryError, Result};

/// A blob in the artifact store: where it is, its SHA-256, size and media type.
///
/// Fields are public so wire conversions stay plain; [`ArtifactRef::new`] and
/// [`ArtifactRef::validate`] check the digest (64 lowercase hex digits).
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ArtifactRef {
    pub uri: String,
    pub sha256: String,
    pub size: u64,
    pub media_type: String,
}

impl ArtifactRef {
    /// A validated reference.
    pub fn new(
        uri: impl Into<String>,
        sha256: impl Into<String>,
        size: u64,
        media_type: impl Into<String>,
    ) -> Result<Self> {
        let r = ArtifactRef { uri: uri.into(), sha256: sha256.into(), size, media_type: media_type.into() };
        r.validate()?;
        Ok(r)
    }

    /// Checks that `sha256` is 64 lowercase hex digits.
    pub fn validate(&self) -> Result<()> {
        if is_sha256_hex(&self.sha256) {
            Ok(())
        } else {
            Err(GeometryError::InvalidSha256 { value: self.sha256.clone() })
        }
    }

    /// The media type if it is one depthmill knows (parameters such as `; charset=utf-8` ignored).
    pub fn known_media_type(&self) -> Option<MediaType> {
        self.media_type.parse().ok()
    }
}

/// True when `s` is exactly 64 lowercase hexadecimal digits.
pub fn is_sha256_hex(s: &str) -> bool {
    s.len() == 64 && s.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

/// The media types of depthmill artifacts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MediaType {
    /// `model/stl`: triangle mesh.
    Stl,
    /// `application/x-ply`: mesh or point cloud.
    Ply,
    /// `text/x-xyz`: point cloud, one `x y z [...]` per line.
    Xyz,
    /// `model/obj`: Wavefront OBJ mesh (or, without faces, point cloud).
    Obj,
    /// `model/x-off`: OFF mesh.
    Off,
    /// `application/x-pcd`: the Point Cloud Library's point cloud.
    Pcd,
    /// `image/png`: depth map.
    Png,
    /// `application/x-npy`: depth map as a NumPy array.
    Npy,
    /// `text/x-gcode`: NC program.
    Gcode,
    /// `application/json`: options, reports, telemetry.
    Json,
    /// `text/html`: human-readable report.
    Html,
    /// `application/octet-stream`: anything else.
    OctetStream,
}

impl MediaType {
    /// Every known media type.
    pub const ALL: [MediaType; 12] = [
        MediaType::Stl,
        MediaType::Ply,
        MediaType::Xyz,
        MediaType::Obj,
        MediaType::Off,
        MediaType::Pcd,
        MediaType::Png,
        MediaType::Npy,
        MediaType::Gcode,
        MediaType::Json,
        MediaType::Html,
        MediaType::OctetStream,
    ];

    /// The media type string, e.g. `image/png`.
    pub fn as_str(self) -> &'static str {
        match self {
            MediaType::Stl => "model/stl",
            MediaType::Ply => "application/x-ply",
            MediaType::Xyz => "text/x-xyz",
            MediaType::Obj => "model/obj",
            MediaType::Off => "model/x-off",
            MediaType::Pcd => "application/x-pcd",
            MediaType::Png => "image/png",
            MediaType::Npy => "application/x-npy",
            MediaType::Gcode => "text/x-gcode",
            MediaType::Json => "application/json",
            MediaType::Html => "text/html",
            MediaType::OctetStream => "application/octet-stream",
        }
    }

    /// The usual file extension (without dot).
    pub fn extension(self) -> &'static str {
        match self {
            MediaType::Stl => "stl",
            MediaType::Ply => "ply",
            MediaType::Xyz => "xyz",
            MediaType::Obj => "obj",
            MediaType::Off => "off",
            MediaType::Pcd => "pcd",
            MediaType::Png => "png",
            MediaType::Npy => "npy",
            MediaType::Gcode => "ngc",
            MediaType::Json => "json",
            MediaType::Html => "html",
            MediaType::OctetStream => "bin",
        }
    }

    /// The media type of a file extension (case-insensitive, without dot), if known.
    pub fn from_extension(ext: &str) -> Option<MediaType> {
        Some(match ext.to_ascii_lowercase().as_str() {
            "stl" => MediaType::Stl,
            "ply" => MediaType::Ply,
            "xyz" | "pts" | "txt" => MediaType::Xyz,
            "obj" => MediaType::Obj,
            "off" => MediaType::Off,
            "pcd" => MediaType::Pcd,
            "png" => MediaType::Png,
            "npy" => MediaType::Npy,
            "ngc" | "nc" | "gcode" | "tap" => MediaType::Gcode,
            "json" => MediaType::Json,
            "html" | "htm" => MediaType::Html,
            "bin" => MediaType::OctetStream,
            _ => return None,
        })
    }
}

impl fmt::Display for MediaType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for MediaType {
    type Err = GeometryError;

    /// Parses a media type, ignoring case and parameters (`text/html; charset=utf-8`).
    fn from_str(s: &str) -> Result<Self> {
        let essence = s.split(';').next().unwrap_or_default().trim().to_ascii_lowercase();
        MediaType::ALL.into_iter().find(|m| m.as_str() == essence).ok_or_else(|| GeometryError::Parse {
            what: "media type",
            input: s.to_string(),
            expected: "one of model/stl, application/x-ply, text/x-xyz, model/obj, model/x-off, \
                       application/x-pcd, image/png, application/x-npy, text/x-gcode, application/json, \
                       text/html, application/octet-stream",
        })
    }
}

impl Serialize for MediaType {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for MediaType {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        String::deserialize(d)?.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DIGEST: &str = "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855";

    #[test]
    fn sha256_is_validated() {
        let r = ArtifactRef::new("file:///x", DIGEST, 0, "image/png").expect("valid");
        assert_eq!(r.known_media_type(), Some(MediaType::Png));
        let json = serde_json::to_string(&r).expect("json");
        assert_eq!(serde_json::from_str::<ArtifactRef>(&json).ok(), Some(r));
        for bad in [&DIGEST[1..], &DIGEST.to_uppercase(), &DIGEST.replace('e', "g"), ""] {
            let e = ArtifactRef::new("u", bad, 0, "image/png").expect_err(bad);
            assert_eq!(e.to_string(), format!("invalid sha256 '{bad}': expected 64 lowercase hex digits"));
        }
    }

    #[test]
    fn media_types_round_trip() {
        for m in MediaType::ALL {
            assert_eq!(m.as_str().parse::<MediaType>().ok(), Some(m));
            assert_eq!(MediaType::from_extension(m.extension()), Some(m));
            let json = serde_json::to_string(&m).expect("json");
            assert_eq!(serde_json::from_str::<MediaType>(&json).ok(), Some(m));
        }
        assert_eq!("Text/HTML; charset=utf-8".parse::<MediaType>().ok(), Some(MediaType::Html));
        assert!("image/jpeg".parse::<MediaType>().is_err());
    }
}

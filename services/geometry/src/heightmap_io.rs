//! File-level entry points for height maps: [`HeightMap::read`] and [`HeightMap::write`],
//! dispatching on [`HeightMapFormat`] (PNG in [`crate::png_io`], `.npy` in [`crate::npy`]).

use std::path::Path;

use crate::artifact::MediaType;
use crate::error::{GeometryError, Result};
use crate::heightmap::HeightMap;
use crate::npy::{read_npy, write_npy};
use crate::png_io::{ImageMapping, PngDepth, read_png, write_png};

/// A height-map file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum HeightMapFormat {
    /// 8-bit grayscale PNG (256 levels over the Z range).
    Png8,
    /// 16-bit grayscale PNG (65536 levels over the Z range).
    Png16,
    /// `.npy` f32 array plus `MAP.npy.json` sidecar, lossless.
    Npy,
}

impl HeightMapFormat {
    /// The default format for a path's extension (case-insensitive): `.png` is [`Self::Png16`],
    /// `.npy` is [`Self::Npy`].
    pub fn from_path(path: &Path) -> Result<Self> {
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or_default().to_ascii_lowercase();
        match ext.as_str() {
            "png" => Ok(HeightMapFormat::Png16),
            "npy" => Ok(HeightMapFormat::Npy),
            _ => Err(GeometryError::UnsupportedExtension { extension: ext }),
        }
    }

    /// Media type of files in this format.
    pub fn media_type(self) -> MediaType {
        match self {
            HeightMapFormat::Png8 | HeightMapFormat::Png16 => MediaType::Png,
            HeightMapFormat::Npy => MediaType::Npy,
        }
    }
}

impl HeightMap {
    /// Reads a `.png` or `.npy` height map (by extension); `fallback` supplies mapping values the
    /// file (or the missing `.npy` sidecar) lacks. Errors name the file.
    pub fn read(path: impl AsRef<Path>, fallback: Option<&ImageMapping>) -> Result<HeightMap> {
        let path = path.as_ref();
        match HeightMapFormat::from_path(path).map_err(|e| e.in_file(path))? {
            HeightMapFormat::Png8 | HeightMapFormat::Png16 => read_png(path, fallback),
            HeightMapFormat::Npy => read_npy(path, fallback),
        }
    }

    /// Writes the map to `path` in `format` (use [`HeightMapFormat::from_path`] for the default of
    /// an extension). `.npy` also writes the sidecar `path.json`. Errors name the file.
    pub fn write(&self, path: impl AsRef<Path>, format: HeightMapFormat) -> Result<()> {
        let path = path.as_ref();
        match format {
            HeightMapFormat::Png8 => write_png(self, path, PngDepth::Bits8),
            HeightMapFormat::Png16 => write_png(self, path, PngDepth::Bits16),
            HeightMapFormat::Npy => write_npy(self, path),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::heightmap::tests::hemisphere;

    #[test]
    fn dispatch_on_extension() {
        let dir = tempfile::tempdir().expect("tempdir");
        let map = hemisphere(9, 0.5, 2.0, true);
        for (name, exact) in [("a.PNG", false), ("b.npy", true)] {
            let path = dir.path().join(name);
            let format = HeightMapFormat::from_path(&path).expect("known");
            map.write(&path, format).expect("write");
            let back = HeightMap::read(&path, None).expect("read");
            let expected = if exact { map.clone() } else { map.quantize(PngDepth::Bits16) };
            assert!(back.bitwise_eq(&expected), "{name}");
        }
        let e = HeightMap::read(dir.path().join("c.tiff"), None).expect_err("tiff");
        assert!(
            e.to_string().ends_with("c.tiff: unsupported height map extension 'tiff': expected .png or .npy"),
            "{e}"
        );
        let e = HeightMap::read(dir.path().join("missing.png"), None).expect_err("missing");
        assert!(matches!(e.root(), GeometryError::Io { .. }), "{e}");
    }
}

//! Conversions between wire types and `depthmill-geometry` types, shared by both ends of every wire.

use crate::types::v1 as pb;

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

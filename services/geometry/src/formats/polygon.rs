//! The mesh under construction shared by the polygon text formats ([`super::off`],
//! [`super::obj`]): vertices through a [`CloudSink`] (double precision with the indices of the
//! non-finite ones dropped for a mesh, single precision for a cloud), polygons fan-triangulated in
//! the file's vertex numbering, and the finish that renumbers them past the dropped vertices and
//! drops degenerate triangles, as the PLY reader does.

use super::error::Result;
use super::ply::finish_triangles;
use super::{CloudSink, Geometry, InputFormat, ReadLimits, ReadStats, too_large};
use crate::mesh::Mesh;

pub(crate) struct PolygonSink {
    pub(crate) vertices: CloudSink,
    tris: Vec<[u32; 3]>,
    /// Faces of fewer than 3 vertices.
    short: u64,
    /// Whether the input had a face statement (an empty face list is still a mesh).
    pub(crate) has_faces: bool,
    /// Read as a cloud: faces are skipped, vertices kept in single precision.
    pub(crate) cloud: bool,
    max_triangles: u64,
    max_points: u64,
}

impl PolygonSink {
    /// `keep`: a cloud keeps a uniform sample of at most that many points ([`CloudSink::sampled`]);
    /// a mesh keeps every vertex (its faces index them all).
    pub(crate) fn new(cloud: bool, limits: &ReadLimits, reserve: usize, keep: Option<usize>) -> Self {
        let vertices = CloudSink::new(false, false, false, !cloud, reserve);
        PolygonSink {
            vertices: if cloud { vertices.sampled(keep) } else { vertices },
            tris: Vec::new(),
            short: 0,
            has_faces: false,
            cloud,
            max_triangles: limits.max_triangles,
            // Triangles index vertices with u32.
            max_points: if cloud { limits.max_points } else { limits.max_points.min(u64::from(u32::MAX)) },
        }
    }

    /// Vertices pushed so far, dropped ones included: the file's numbering.
    pub(crate) fn seen(&self) -> u64 {
        self.vertices.seen
    }

    /// Adds a vertex (a non-finite one is dropped and counted, and so are the faces that use it).
    pub(crate) fn vertex(&mut self, p: [f64; 3], name: &str) -> Result<()> {
        self.vertices.push(p, 0.0, [0.0; 3], 0);
        if self.vertices.seen > self.max_points {
            return Err(too_large(name, "points", self.vertices.seen, self.max_points));
        }
        Ok(())
    }

    /// Adds a polygon of vertex indices in the file's numbering (checked by the caller),
    /// fan-triangulated; fewer than 3 corners count as a dropped face.
    pub(crate) fn face(&mut self, corners: &[u32], name: &str) -> Result<()> {
        self.has_faces = true;
        if self.cloud {
            return Ok(());
        }
        if corners.len() < 3 {
            self.short += 1;
            return Ok(());
        }
        let total = self.tris.len() as u64 + (corners.len() as u64 - 2);
        if total > self.max_triangles {
            return Err(too_large(name, "triangles", total, self.max_triangles));
        }
        for w in 1..corners.len() - 1 {
            self.tris.push([corners[0], corners[w], corners[w + 1]]);
        }
        Ok(())
    }

    /// The mesh (when the input had faces and was not read as a cloud) or the cloud, and the
    /// statistics.
    pub(crate) fn finish(
        mut self,
        format: InputFormat,
        bytes: u64,
        ignored: Vec<String>,
    ) -> (Geometry, ReadStats) {
        let mut stats = ReadStats::new(format);
        stats.bytes = bytes;
        stats.points = self.vertices.len();
        stats.dropped_non_finite = self.vertices.dropped;
        stats.ignored_properties = ignored;
        let seen = self.vertices.seen;
        if self.cloud || !self.has_faces {
            return (Geometry::Cloud(self.vertices.into_cloud().0), stats);
        }
        let dropped_at = self.vertices.dropped_at.take().unwrap_or_default();
        let vertices = self.vertices.into_vertices();
        let mut tris = self.tris;
        let dropped = finish_triangles(&vertices, &mut tris, &dropped_at, seen);
        stats.triangles = tris.len() as u64;
        stats.dropped_triangles = dropped + self.short;
        (Geometry::Mesh(Mesh { vertices, triangles: tris }), stats)
    }
}

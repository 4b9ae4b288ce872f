//! A triangle mesh with one scalar per vertex as binary little-endian PLY: the layout the machine
//! service writes its simulated part in (the deviation from the original part per vertex) and the
//! report reads back. Any PLY viewer opens it (MeshLab and CloudCompare show the scalar).
//!
//! Layout: `element vertex N` with `float x`, `float y`, `float z`, `float <scalar>`; `element
//! face M` with `property list uchar int vertex_indices`, every face a triangle. The reader takes
//! exactly this layout (any comments, any scalar name) and names what differs.

use std::io::Write;

use nalgebra::Point3;

use super::error::{FormatError, Location, Result};
use crate::mesh::Mesh;

const FILE: &str = "mesh PLY";

/// Writes `mesh` with `values` (one per vertex) as the vertex property `name`.
///
/// Errors: a value count that is not the vertex count, a name that is not one word, a comment
/// with a line break, or write failures.
pub fn write_mesh_ply<W: Write>(
    mut w: W,
    mesh: &Mesh,
    name: &str,
    values: &[f32],
    comments: &[String],
) -> Result<()> {
    if values.len() != mesh.vertices.len() {
        return Err(FormatError::param(
            "values",
            format!("{} values", values.len()),
            format!("one per vertex is needed; the mesh has {} vertices", mesh.vertices.len()),
        ));
    }
    if name.is_empty() || name.contains(char::is_whitespace) {
        return Err(FormatError::param("name", format!("{name:?}"), "a property name is one word"));
    }
    if let Some(bad) = comments.iter().find(|c| c.contains(['\n', '\r'])) {
        return Err(FormatError::param("comments", format!("{bad:?}"), "a comment must be one line"));
    }
    let io = |source| FormatError::Io { file: format!("{FILE} output"), source };
    let mut head = String::from("ply\nformat binary_little_endian 1.0\n");
    for c in comments {
        head.push_str(&format!("comment {c}\n"));
    }
    head.push_str(&format!(
        "element vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float {name}\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    ));
    let mut buf = Vec::with_capacity(head.len() + 16 * mesh.vertices.len() + 13 * mesh.triangles.len());
    buf.extend_from_slice(head.as_bytes());
    for (p, v) in mesh.vertices.iter().zip(values) {
        for f in [p.x as f32, p.y as f32, p.z as f32, *v] {
            buf.extend_from_slice(&f.to_le_bytes());
        }
    }
    for t in &mesh.triangles {
        buf.push(3);
        for i in t {
            // Indices are below the vertex count, which the format stores as `int`.
            let i = i32::try_from(*i).map_err(|_| {
                FormatError::param("triangles", i, format!("indices above {} do not fit a PLY int", i32::MAX))
            })?;
            buf.extend_from_slice(&i.to_le_bytes());
        }
    }
    w.write_all(&buf).map_err(io)?;
    w.flush().map_err(io)
}

fn bad(at: u64, problem: impl Into<String>) -> FormatError {
    FormatError::Parse { file: FILE.to_string(), at: Location::Byte(at), problem: problem.into() }
}

/// Reads what [`write_mesh_ply`] writes: the mesh, the scalar's name and its values.
///
/// Errors: a header of another layout (naming the line that differs), counts the bytes cannot
/// hold, a face that is not a triangle or an index out of range (naming the face and its byte).
pub fn read_mesh_ply(bytes: &[u8]) -> Result<(Mesh, String, Vec<f32>)> {
    let end =
        bytes.windows(11).position(|w| w == b"end_header\n").ok_or_else(|| bad(0, "no `end_header` line"))?;
    let head = std::str::from_utf8(&bytes[..end]).map_err(|_| bad(0, "the header is not text"))?;
    let mut lines = head.lines().filter(|l| !l.starts_with("comment"));
    let mut expect = |want: &str| -> Result<String> {
        let line = lines.next().unwrap_or("");
        match line.strip_prefix(want) {
            Some(rest) => Ok(rest.trim().to_string()),
            None => Err(bad(0, format!("expected a header line `{want}...`, found {line:?}"))),
        }
    };
    expect("ply")?;
    expect("format binary_little_endian 1.0")?;
    let nv: usize =
        expect("element vertex")?.parse().map_err(|_| bad(0, "the vertex count is not a number"))?;
    for axis in ["x", "y", "z"] {
        let got = expect("property float")?;
        if got != axis {
            return Err(bad(0, format!("expected property float {axis}, found {got:?}")));
        }
    }
    let name = expect("property float")?;
    let nf: usize = expect("element face")?.parse().map_err(|_| bad(0, "the face count is not a number"))?;
    let list = expect("property list uchar int")?;
    if list.is_empty() {
        return Err(bad(0, "the face list has no name"));
    }
    let body = end as u64 + 11;
    let need = (nv as u64).saturating_mul(16).saturating_add((nf as u64).saturating_mul(13));
    let have = bytes.len() as u64 - body;
    if have != need {
        return Err(bad(
            body,
            format!("{nv} vertices and {nf} triangles need {need} bytes, the file has {have}"),
        ));
    }
    let f32_at = |o: usize| f32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
    let mut vertices = Vec::with_capacity(nv);
    let mut values = Vec::with_capacity(nv);
    let mut o = body as usize;
    for _ in 0..nv {
        vertices.push(Point3::new(f64::from(f32_at(o)), f64::from(f32_at(o + 4)), f64::from(f32_at(o + 8))));
        values.push(f32_at(o + 12));
        o += 16;
    }
    let mut triangles = Vec::with_capacity(nf);
    for t in 0..nf {
        if bytes[o] != 3 {
            return Err(bad(o as u64, format!("face {t} has {} corners; expected a triangle", bytes[o])));
        }
        let mut tri = [0u32; 3];
        for (k, slot) in tri.iter_mut().enumerate() {
            let at = o + 1 + 4 * k;
            let i = i32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
            *slot = u32::try_from(i)
                .ok()
                .filter(|&i| (i as usize) < nv)
                .ok_or_else(|| bad(at as u64, format!("face {t}: vertex index {i} is not below {nv}")))?;
        }
        triangles.push(tri);
        o += 13;
    }
    let mesh = Mesh::new(vertices, triangles)?;
    Ok((mesh, name, values))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mesh_and_its_scalar_come_back_as_written_and_bad_files_are_named() {
        let mesh = Mesh::cuboid(2.0, 3.0, 4.0);
        let values: Vec<f32> = (0..8).map(|i| i as f32 * 0.5 - 1.0).collect();
        let mut bytes = Vec::new();
        write_mesh_ply(&mut bytes, &mesh, "deviation", &values, &["units mm".into()]).expect("write");
        let (back, name, vals) = read_mesh_ply(&bytes).expect("read");
        assert_eq!((back, name.as_str(), vals), (mesh.clone(), "deviation", values.clone()));
        // The general reader opens it too (the scalar listed as ignored).
        let (g, _) = crate::formats::read_ply_from(
            std::io::Cursor::new(&bytes),
            "part.ply",
            &crate::formats::ReadLimits::default(),
        )
        .expect("general reader");
        assert!(matches!(g, crate::formats::Geometry::Mesh(m) if m.triangles.len() == 12));

        assert!(write_mesh_ply(Vec::new(), &mesh, "deviation", &values[..3], &[]).is_err());
        assert!(write_mesh_ply(Vec::new(), &mesh, "two words", &values, &[]).is_err());
        let e = read_mesh_ply(&bytes[..bytes.len() - 1]).expect_err("short").to_string();
        assert!(e.contains("need") && e.contains("bytes"), "{e}");
        let mut wrong = bytes.clone();
        let last = wrong.len() - 1;
        wrong[last] = 0x7f; // the last triangle's last index's high byte
        let e = read_mesh_ply(&wrong).expect_err("index").to_string();
        assert!(e.contains("face 11") && e.contains("not below 8"), "{e}");
        let e = read_mesh_ply(b"ply\nformat ascii 1.0\nend_header\n").expect_err("ascii").to_string();
        assert!(e.contains("binary_little_endian"), "{e}");
    }
}

//! Tests of the OFF, OBJ and PCD readers: each against hand-written files, against the STL and
//! PLY readers on the same geometry (random meshes and clouds), and on malformed input.

use std::collections::BTreeSet;
use std::io::Cursor;

use nalgebra::{Point3, Vector3};
use rand::rngs::StdRng as ChaCha8Rng;
use rand::{Rng, SeedableRng};

use super::pcd::lzf_decompress;
use super::*;

fn any(bytes: &[u8]) -> Result<(Geometry, ReadStats)> {
    read_any_from(Cursor::new(bytes.to_vec()), "in", Some(bytes.len() as u64), &ReadLimits::default())
}

fn mesh(bytes: &[u8]) -> (Mesh, ReadStats) {
    match any(bytes).expect("read") {
        (Geometry::Mesh(m), s) => (m, s),
        (Geometry::Cloud(_), _) => panic!("a cloud, not a mesh"),
    }
}

fn cloud(bytes: &[u8]) -> (PointCloud, ReadStats) {
    match any(bytes).expect("read") {
        (Geometry::Cloud(c), s) => (c, s),
        (Geometry::Mesh(_), _) => panic!("a mesh, not a cloud"),
    }
}

fn err(bytes: &[u8]) -> String {
    any(bytes).expect_err("malformed").to_string()
}

/// A mesh's triangles as corner coordinates, rotated so the smallest corner comes first (the
/// winding kept), in a set: equal for the same surface whatever the vertex numbering.
fn triangle_set(m: &Mesh) -> BTreeSet<[[u32; 3]; 3]> {
    m.triangles
        .iter()
        .map(|t| {
            let c = t.map(|i| {
                let p = m.vertices[i as usize];
                // Single precision, as STL stores it.
                [p.x, p.y, p.z].map(|v| (v as f32 + 0.0).to_bits())
            });
            let k = (0..3).min_by_key(|&k| c[k]).unwrap_or(0);
            [c[k], c[(k + 1) % 3], c[(k + 2) % 3]]
        })
        .collect()
}

const CUBE_OFF: &str = "OFF\n# a unit cube, quads\n8 6 12\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n1 0 1\n1 1 1\n0 1 1\n\
4 0 3 2 1\n4 4 5 6 7\n4 0 1 5 4\n4 1 2 6 5\n4 2 3 7 6\n4 3 0 4 7\n";

#[test]
fn off_cube_of_quads_and_its_variants() {
    let (m, s) = mesh(CUBE_OFF.as_bytes());
    assert_eq!((s.format, s.points, s.triangles, s.dropped_triangles), (InputFormat::Off, 8, 12, 0));
    assert_eq!(m.triangles[0], [0, 3, 2]);
    assert_eq!(m.triangles[1], [0, 2, 1]);
    assert_eq!(s.bytes, CUBE_OFF.len() as u64);
    // Counts on the keyword's line, colours after vertices and faces, comments, blank lines,
    // CRLF: the same mesh.
    let coff = "COFF 8 6 0\r\n\r\n0 0 0 255 0 0 255\n1 0 0 1 1 1 1\n1 1 0 1 1 1 1\n0 1 0 1 1 1 1 # c\n\
                0 0 1 1 1 1 1\n1 0 1 1 1 1 1\n1 1 1 1 1 1 1\n0 1 1 1 1 1 1\n\
                4 0 3 2 1 0.5 0.5 0.5\n4 4 5 6 7\n4 0 1 5 4\n4 1 2 6 5\n  4 2 3 7 6\n4 3 0 4 7 1 0 0\n";
    assert_eq!(mesh(coff.as_bytes()).0, m);
    // Homogeneous coordinates are divided by w; normals are skipped.
    let four = "4OFF\n8 6 12\n0 0 0 1\n1 0 0 1\n2 2 0 2\n0 1 0 1\n0 0 1 1\n1 0 1 1\n2 2 2 2\n0 0.5 0.5 0.5\n"
        .to_string()
        + &CUBE_OFF.lines().skip(11).map(|l| format!("{l}\n")).collect::<String>();
    assert_eq!(mesh(four.as_bytes()).0, m);
    let noff = "NOFF\n3 1 0\n0 0 0 0 0 1\n1 0 0 0 0 1\n0 1 0 0 0 1\n3 0 1 2\n";
    assert_eq!(mesh(noff.as_bytes()).0.triangles, vec![[0, 1, 2]]);
    let n_off = "nOFF\n3\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    assert_eq!(mesh(n_off.as_bytes()).0.triangles, vec![[0, 1, 2]]);
    // A face of two corners and a degenerate triangle are dropped and counted; a non-finite
    // vertex is dropped with its face, and the rest renumbered.
    let odd = "OFF\n5 4 0\nnan 0 0\n0 0 0\n1 0 0\n0 1 0\n2 0 0\n3 1 2 3\n2 1 2\n3 1 2 4\n3 0 1 2\n";
    let (m, s) = mesh(odd.as_bytes());
    assert_eq!(m.triangles, vec![[0, 1, 2]]);
    assert_eq!(m.vertices[0], Point3::new(0.0, 0.0, 0.0));
    assert_eq!((s.points, s.dropped_non_finite, s.triangles, s.dropped_triangles), (4, 1, 1, 3));
    // No faces: a point set (as CGAL writes one).
    let (c, s) = cloud(b"OFF\n2 0 0\n1 2 3\n4 5 6\n");
    assert_eq!((c.points.len(), s.format), (2, InputFormat::Off));
}

#[test]
fn off_errors_name_the_line() {
    assert_eq!(
        err(b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n"),
        "in: line 6: face 0: vertex index 3 out of range (the file has 3 vertices)"
    );
    assert_eq!(
        err(b"OFF\n3 1 0\n0 0 0\n1 0\n0 1 0\n3 0 1 2\n"),
        "in: line 4: vertex 1: expected 3 coordinates, found 2"
    );
    assert_eq!(err(b"OFF\n3 1 0\n0 0 0\n1 x 0\n"), "in: line 4: vertex 1: cannot parse \"x\" as a number");
    assert_eq!(err(b"OFF\n3 1 0\n0 0 0\n1 0 0\n"), "in: line 4: OFF: the file ends after 2 of 3 vertices");
    assert_eq!(
        err(b"OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"),
        "in: line 6: OFF: the file ends after 1 of 2 faces"
    );
    assert_eq!(
        err(b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n4 0 1 2\n"),
        "in: line 6: face 0: 4 corners announced, 3 given"
    );
    assert_eq!(err(b"OFF\n3 1.5 0\n"), "in: line 2: face count: \"1.5\" is not a whole number");
    assert_eq!(err(b"OFF\n"), "in: line 1: OFF: the file ends before the vertex and face counts");
    assert_eq!(err(b"nOFF 4 3 1 0\n"), "in: line 1: OFF: dimension 4; only 3 is read");
    assert!(err(b"OFF BINARY\n").contains("binary OFF is not read"), "{}", err(b"OFF BINARY\n"));
    let tight = ReadLimits { max_points: 2, ..ReadLimits::default() };
    let e = read_any_from(Cursor::new(CUBE_OFF.as_bytes().to_vec()), "in", None, &tight).expect_err("limit");
    assert_eq!(e.to_string(), "in: points 8 exceeds the limit of 2");
    // A mesh is asked for and the OFF has no faces.
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("points.off");
    std::fs::write(&path, "OFF\n1 0 0\n1 2 3\n").expect("write");
    let e = read_mesh(&path, &ReadLimits::default()).expect_err("no faces");
    assert!(e.to_string().contains("the OFF file has no faces"), "{e}");
}

#[test]
fn obj_statements_references_and_continuations() {
    let text = "# exported\nmtllib part.mtl\no part\nv 0 0 0\nv 1 0 0 1.0\nv 1 1 0 0.5 0.5 0.5\nv 0 1 0\n\
                vt 0 0\nvn 0 0 1\ng top\nusemtl steel\ns off\nf 1/1/1 2/1/1 3/1/1 4/1/1\n\
                v 0 0 1\nf -5//1 -4//1 \\\n -1//1 # a continued line\nl 1 2\n";
    let (m, s) = mesh(text.as_bytes());
    assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 1, 4]]);
    assert_eq!(m.vertices.len(), 5);
    assert_eq!((s.format, s.points, s.triangles, s.dropped_triangles), (InputFormat::Obj, 5, 3, 0));
    assert_eq!(s.ignored_properties, ["mtllib", "o", "vt", "vn", "g", "usemtl", "s", "l"]);
    // A face may name a vertex defined after it.
    let (m, _) = mesh(b"f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n");
    assert_eq!(m.triangles, vec![[0, 1, 2]]);
    // A non-finite vertex goes with its faces; a two-corner face is dropped and counted.
    let (m, s) = mesh(b"v 0 0 0\nv inf 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\nf 1 3\n");
    assert_eq!(m.triangles, vec![[0, 1, 2]]);
    assert_eq!((s.dropped_non_finite, s.dropped_triangles), (1, 2));
    // Vertices only: a point cloud.
    let (c, s) = cloud(b"# scanner export\nv 1 2 3\nv 4 5 6\n");
    assert_eq!(
        (c.points, s.format),
        (vec![Point3::new(1.0, 2.0, 3.0), Point3::new(4.0, 5.0, 6.0)], InputFormat::Obj)
    );
}

#[test]
fn obj_errors_name_the_line() {
    let long = format!("v 0 0 0\n{}", "f 1 \\\n".repeat(MAX_LINE_LEN / 4));
    assert_eq!(
        err(long.as_bytes()),
        format!("in: line 2: a line continued with \\ grows longer than {MAX_LINE_LEN} bytes")
    );
    assert_eq!(err(b"v 0 0 0\nv 1 0\n"), "in: line 2: v: expected 3 coordinates, found 2");
    assert_eq!(err(b"v 0 0 0\nv 1 y 0\n"), "in: line 2: v: cannot parse \"y\" as a number");
    assert_eq!(
        err(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n"),
        "in: line 4: f: vertex reference \"0\": indices start at 1"
    );
    assert_eq!(
        err(b"v 0 0 0\nv 1 0 0\nf -3 1 2\n"),
        "in: line 3: f: vertex reference \"-3\": only 2 vertices precede it"
    );
    assert_eq!(
        err(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/a x/2 3\n"),
        "in: line 4: f: vertex reference \"x/2\": not an integer"
    );
    assert_eq!(
        err(b"v 0 0 0\nf 1 2 9\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
        "in: line 2: f: vertex index 9 out of range (the file has 3 vertices)"
    );
}

/// A random closed-ish mesh: a grid of quads over random heights, every vertex used.
fn random_mesh(rng: &mut ChaCha8Rng) -> Mesh {
    let (nx, ny) = (rng.random_range(2..9u32), rng.random_range(2..9u32));
    let mut vertices = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            let z: f32 = rng.random_range(-5.0..5.0);
            let x = i as f32 * 1.25 + rng.random_range(-0.3..0.3f32);
            vertices.push(Point3::new(f64::from(x), f64::from(j as f32 * 0.75), f64::from(z)));
        }
    }
    let mut triangles = Vec::new();
    for j in 0..ny - 1 {
        for i in 0..nx - 1 {
            let a = j * nx + i;
            triangles.push([a, a + 1, a + nx + 1]);
            triangles.push([a, a + nx + 1, a + nx]);
        }
    }
    Mesh { vertices, triangles }
}

#[test]
fn off_and_obj_read_the_surface_stl_reads() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x0ff);
    for _ in 0..20 {
        let m = random_mesh(&mut rng);
        let mut stl = Vec::new();
        write_stl(&mut stl, &m, "random").expect("stl");
        let (from_stl, _) = mesh(&stl);
        // OFF with the faces as quads where two triangles share a diagonal: fan-triangulated
        // back to the same triangles.
        let mut off = format!("OFF\n{} {} 0\n", m.vertices.len(), m.triangles.len() / 2);
        let mut obj = String::from("# random\n");
        for p in &m.vertices {
            off += &format!("{} {} {}\n", p.x as f32, p.y as f32, p.z as f32);
            obj += &format!("v {} {} {}\n", p.x as f32, p.y as f32, p.z as f32);
        }
        for pair in m.triangles.chunks(2) {
            let ([a, b, c], [_, _, d]) = (pair[0], pair[1]);
            off += &format!("4 {a} {b} {c} {d}\n");
            // OBJ: the first triangle by absolute, the second by relative references.
            let n = m.vertices.len() as i64;
            obj += &format!("f {}/1 {}/1 {}/1\n", a + 1, b + 1, c + 1);
            obj += &format!("f {}//2 {}//2 {}//2\n", i64::from(a) - n, i64::from(c) - n, i64::from(d) - n);
        }
        let (from_off, s) = mesh(off.as_bytes());
        assert_eq!(s.triangles, m.triangles.len() as u64);
        assert_eq!(triangle_set(&from_off), triangle_set(&from_stl));
        let (from_obj, s) = mesh(obj.as_bytes());
        assert_eq!(s.triangles, m.triangles.len() as u64);
        assert_eq!(triangle_set(&from_obj), triangle_set(&from_stl));
        assert_eq!(from_obj, from_off);
    }
}

// ---------------------------------------------------------------------------------------------
// PCD.

/// A slow, plain LZF encoder (the longest match among all earlier positions within reach): the
/// reference the decoder is checked against.
fn lzf_compress_reference(data: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut lit: Vec<u8> = Vec::new();
    let flush = |out: &mut Vec<u8>, lit: &mut Vec<u8>| {
        for chunk in lit.chunks(32) {
            out.push((chunk.len() - 1) as u8);
            out.extend_from_slice(chunk);
        }
        lit.clear();
    };
    let mut i = 0;
    while i < data.len() {
        let mut best = (0usize, 0usize);
        for from in i.saturating_sub(8192)..i {
            let mut n = 0;
            while i + n < data.len() && n < 264 && data[from + n] == data[i + n] {
                n += 1;
            }
            if n > best.0 {
                best = (n, i - from);
            }
        }
        if best.0 >= 3 {
            flush(&mut out, &mut lit);
            let (len, back) = (best.0 - 2, best.1 - 1);
            if len < 7 {
                out.push(((len << 5) | (back >> 8)) as u8);
            } else {
                out.push(((7 << 5) | (back >> 8)) as u8);
                out.push((len - 7) as u8);
            }
            out.push((back & 0xff) as u8);
            i += best.0;
        } else {
            lit.push(data[i]);
            i += 1;
        }
    }
    flush(&mut out, &mut lit);
    out
}

#[test]
fn lzf_decodes_what_the_reference_encoder_wrote() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for round in 0..60 {
        let n = rng.random_range(0..3000);
        let alphabet = if round % 3 == 0 { 256 } else { rng.random_range(1..6) };
        let mut data: Vec<u8> = Vec::with_capacity(n);
        while data.len() < n {
            if !data.is_empty() && rng.random_bool(0.3) {
                // Repeat an earlier stretch, overlapping the end at times.
                let from = rng.random_range(0..data.len());
                let len = rng.random_range(1..300).min(n - data.len());
                for k in 0..len {
                    let b = data[from + k];
                    data.push(b);
                }
            } else {
                data.push(rng.random_range(0..alphabet) as u8);
            }
        }
        let packed = lzf_compress_reference(&data);
        assert_eq!(lzf_decompress(&packed, data.len()).expect("decode"), data, "round {round}");
        if !packed.is_empty() {
            assert!(lzf_decompress(&packed, data.len() + 1).is_err());
            assert!(lzf_decompress(&packed[..packed.len() - 1], data.len()).is_err());
        }
    }
    assert!(lzf_decompress(&[0x20, 0x05], 3).expect_err("back past the start").contains("bytes back"));
}

/// A PCD field: name, size, type, count.
type PcdField<'a> = (&'a str, usize, char, usize);

/// A PCD header for `fields` and `points`.
fn pcd_header(fields: &[PcdField], points: usize, data: &str) -> String {
    let col = |f: &dyn Fn(&PcdField) -> String| fields.iter().map(f).collect::<Vec<_>>().join(" ");
    format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {}\nSIZE {}\nTYPE {}\nCOUNT {}\n\
         WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n",
        col(&|f| f.0.to_string()),
        col(&|f| f.1.to_string()),
        col(&|f| f.2.to_string()),
        col(&|f| f.3.to_string()),
    )
}

/// Little-endian bytes of `v` as a field of `size` bytes and type `ty`.
fn encode(v: f64, size: usize, ty: char) -> Vec<u8> {
    match (ty, size) {
        ('F', 4) => (v as f32).to_le_bytes().to_vec(),
        ('F', _) => v.to_le_bytes().to_vec(),
        ('I', n) => (v as i64).to_le_bytes()[..n].to_vec(),
        (_, n) => (v as u64).to_le_bytes()[..n].to_vec(),
    }
}

#[test]
fn pcd_all_three_bodies_read_the_same_cloud() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x9cd);
    let fields: [PcdField; 7] = [
        ("x", 4, 'F', 1),
        ("rgb", 4, 'U', 1),
        ("y", 8, 'F', 1),
        ("z", 4, 'F', 1),
        ("histogram", 2, 'I', 3),
        ("intensity", 2, 'U', 1),
        ("sid", 1, 'I', 1),
    ];
    for n in [0usize, 1, 7, 500] {
        let mut rows: Vec<Vec<Vec<f64>>> = Vec::new();
        for k in 0..n {
            let invalid = k % 11 == 3;
            rows.push(vec![
                vec![if invalid { f64::NAN } else { f64::from(rng.random_range(-100.0..100.0f32)) }],
                vec![f64::from(rng.random_range(0..1u32 << 24))],
                vec![rng.random_range(-1.0..1.0f64)],
                vec![f64::from(rng.random_range(0.0..9.0f32))],
                (0..3).map(|_| f64::from(rng.random_range(-300..300i32))).collect(),
                vec![f64::from(rng.random_range(0..65535u32))],
                vec![f64::from(rng.random_range(-128..128i32))],
            ]);
        }
        let ascii = pcd_header(&fields, n, "ascii")
            + &rows
                .iter()
                .map(|r| r.iter().flatten().map(|v| format!("{v}")).collect::<Vec<_>>().join(" ") + "\n")
                .collect::<String>();
        let mut binary = pcd_header(&fields, n, "binary").into_bytes();
        for r in &rows {
            for (f, vals) in fields.iter().zip(r) {
                for v in vals {
                    binary.extend(encode(*v, f.1, f.2));
                }
            }
        }
        let mut soa = Vec::new();
        for (i, f) in fields.iter().enumerate() {
            for r in &rows {
                for v in &r[i] {
                    soa.extend(encode(*v, f.1, f.2));
                }
            }
        }
        let packed = lzf_compress_reference(&soa);
        let mut compressed = pcd_header(&fields, n, "binary_compressed").into_bytes();
        compressed.extend((packed.len() as u32).to_le_bytes());
        compressed.extend((soa.len() as u32).to_le_bytes());
        compressed.extend(&packed);

        let want: Vec<Point3<f32>> = rows
            .iter()
            .filter(|r| r[0][0].is_finite())
            .map(|r| Point3::new(r[0][0] as f32, r[2][0] as f32, r[3][0] as f32))
            .collect();
        let want_intensity: Vec<f32> =
            rows.iter().filter(|r| r[0][0].is_finite()).map(|r| r[5][0] as f32).collect();
        for (what, bytes) in [("ascii", ascii.into_bytes()), ("binary", binary), ("compressed", compressed)] {
            let (c, s) = cloud(&bytes);
            assert_eq!(c.points, want, "{what}, {n} points");
            assert_eq!(c.intensity.as_deref(), Some(want_intensity.as_slice()), "{what}");
            assert_eq!(c.normals, None);
            assert_eq!(
                (s.format, s.points, s.dropped_non_finite),
                (InputFormat::Pcd, want.len() as u64, (n as u64 + 7) / 11),
                "{what}"
            );
            assert_eq!(s.ignored_properties, ["rgb", "histogram", "sid"]);
            assert_eq!(s.bytes, bytes.len() as u64, "{what}");
        }
    }
}

#[test]
fn pcd_normals_and_errors() {
    let text = "VERSION .7\nFIELDS x y z normal_x normal_y normal_z curvature\nSIZE 4 4 4 4 4 4 4\nTYPE F F F F F F F\n\
                WIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n1 2 3 0 0 1 0.1\n4 5 6 0 1 0 0.2\n";
    let (c, _) = cloud(text.as_bytes());
    assert_eq!(c.normals, Some(vec![Vector3::new(0.0, 0.0, 1.0), Vector3::new(0.0, 1.0, 0.0)]));
    assert_eq!(c.points[1], Point3::new(4.0, 5.0, 6.0));
    // The header without POINTS: WIDTH × HEIGHT.
    let organised = text.replace("WIDTH 2\nHEIGHT 1\nPOINTS 2\n", "WIDTH 1\nHEIGHT 2\n");
    assert_eq!(cloud(organised.as_bytes()).0.points.len(), 2);

    let h = "VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\n";
    assert_eq!(
        err(format!("{h}DATA ascii\n1 2 3\n4 5\n").as_bytes()),
        "in: line 11: PCD: 2 values, the fields hold 3"
    );
    assert_eq!(
        err(format!("{h}DATA ascii\n1 2 3\n").as_bytes()),
        "in: line 10: PCD: the file ends after 1 of 2 points"
    );
    assert_eq!(
        err(format!("{h}DATA ascii\n1 2 3\n4 5 q\n").as_bytes()),
        "in: line 11: cannot parse \"q\" as a number"
    );
    assert_eq!(
        err(format!("{h}DATA binary\n").as_bytes()),
        format!("in: byte {}: PCD: the file ends after 0 of 2 points", h.len() + 12)
    );
    assert_eq!(
        err(format!("{h}DATA lzma\n").as_bytes()),
        "in: line 9: PCD: DATA \"lzma\": expected ascii, binary or binary_compressed"
    );
    assert_eq!(
        err(format!("{}DATA ascii\n", h.replace("SIZE 4 4 4", "SIZE 4 4")).as_bytes()),
        "in: line 3: PCD: SIZE has 2 entries but FIELDS names 3"
    );
    assert_eq!(
        err(format!("{}DATA ascii\n", h.replace("SIZE 4 4 4", "SIZE 4 4 3")).as_bytes()),
        "in: line 3: PCD: SIZE 3: a field is 1, 2, 4 or 8 bytes"
    );
    assert_eq!(
        err(format!("{}DATA ascii\n", h.replace("FIELDS x y z", "FIELDS x y w")).as_bytes()),
        "in: line 2: PCD: no field z (the fields are x y w)"
    );
    assert_eq!(err(b"VERSION .7\nFIELDS x y z\n"), "in: line 2: PCD: the file ends before the DATA line");
    let mut bad = format!("{h}DATA binary_compressed\n").into_bytes();
    bad.extend(4u32.to_le_bytes());
    bad.extend(20u32.to_le_bytes());
    assert_eq!(
        any(&bad).expect_err("size").to_string(),
        format!("in: byte {}: PCD: the uncompressed size 20 is not 2 points of 12 bytes (24)", h.len() + 27)
    );
    let huge = h.replace("FIELDS x y z", "FIELDS x y z h").replace("SIZE 4 4 4", "SIZE 4 4 4 8");
    let huge = huge.replace("TYPE F F F", "TYPE F F F F").replace("COUNT 1 1 1", "COUNT 1 1 1 1000000");
    assert_eq!(
        err(format!("{huge}DATA ascii\n").as_bytes()),
        "in: line 5: PCD: a point of 8000012 bytes or more, over the limit of 65536"
    );
    let tight = ReadLimits { max_points: 1, ..ReadLimits::default() };
    let e =
        read_any_from(Cursor::new(format!("{h}DATA ascii\n1 2 3\n4 5 6\n").into_bytes()), "in", None, &tight);
    assert_eq!(e.expect_err("limit").to_string(), "in: points 2 exceeds the limit of 1");
}

#[test]
fn sniffing_the_text_formats() {
    assert_eq!(sniff_format(b"OFF\n8 6 0\n", None), InputFormat::Off);
    assert_eq!(sniff_format(b"# cgal\n\nCOFF 3 1 0\n", None), InputFormat::Off);
    assert_eq!(sniff_format(b"STCNOFF\n", None), InputFormat::Off);
    assert_eq!(sniff_format(b"# Blender\nmtllib a.mtl\no Cube\nv 1 1 1\n", None), InputFormat::Obj);
    assert_eq!(sniff_format(b"v 1 2 3\nv 4 5 6\n", None), InputFormat::Obj);
    assert_eq!(
        sniff_format(b"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n", None),
        InputFormat::Pcd
    );
    assert_eq!(sniff_format(b"FIELDS x y z\nSIZE 4 4 4\nDATA ascii\n", None), InputFormat::Pcd);
    // A binary STL whose header starts with a PCD keyword, its size unknown.
    let mut stl = b"VERSION 2 exported".to_vec();
    stl.resize(80, 0);
    stl.extend_from_slice(&1u32.to_le_bytes());
    stl.resize(134, 0);
    assert_eq!(sniff_format(&stl, None), InputFormat::StlBinary);
    assert_eq!(sniff_format(b"# x y z\n1 2 3\n", None), InputFormat::Xyz);
    assert_eq!(sniff_format(b"OFFSET 1 2\n", None), InputFormat::Xyz);
}

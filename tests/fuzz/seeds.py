#!/usr/bin/env python3
"""Writes the fuzzers' starting inputs into corpus/<target>/: small valid files of every format
and variant a reader takes, the bad-input corpus of tests/corpus, the shipped tools and machine
profiles. libFuzzer grows the corpus from there (run.sh campaign keeps it minimal)."""
import json, pathlib, shutil, struct, zlib

here = pathlib.Path(__file__).resolve().parent
repo = here.parent.parent


def put(target, name, data):
    d = here / "corpus" / target
    d.mkdir(parents=True, exist_ok=True)
    (d / f"seed-{name}").write_bytes(data if isinstance(data, bytes) else data.encode())


def copy_dir(target, src, pattern="*"):
    for f in sorted((repo / src).glob(pattern)):
        if f.is_file():
            put(target, f.name, f.read_bytes())


pts = [(0.0, 0.0, 1.0), (1.0, 0.0, 1.5), (0.0, 1.0, 2.0), (1.0, 1.0, 0.5)]
tris = [(0, 1, 2), (1, 3, 2)]

# PLY: ascii, binary le/be, cloud with intensity and normals, mesh.
def ply(fmt, faces, extra=True):
    props = "property float x\nproperty float y\nproperty float z\n"
    if extra:
        props += "property float intensity\nproperty float nx\nproperty float ny\nproperty float nz\n"
    head = f"ply\nformat {fmt} 1.0\ncomment seed\nelement vertex {len(pts)}\n{props}"
    if faces:
        head += f"element face {len(tris)}\nproperty list uchar int vertex_indices\n"
    head += "end_header\n"
    if fmt == "ascii":
        body = "".join(" ".join(str(v) for v in (p + ((0.5, 0, 0, 1) if extra else ()))) + "\n" for p in pts)
        if faces:
            body += "".join(f"3 {a} {b} {c}\n" for a, b, c in tris)
        return head.encode() + body.encode()
    e = "<" if fmt == "binary_little_endian" else ">"
    body = b"".join(struct.pack(e + ("7f" if extra else "3f"), *(p + ((0.5, 0, 0, 1) if extra else ()))) for p in pts)
    if faces:
        body += b"".join(struct.pack(e + "B3i", 3, *t) for t in tris)
    return head.encode() + body

for fmt in ("ascii", "binary_little_endian", "binary_big_endian"):
    for faces in (False, True):
        data = ply(fmt, faces, extra=not faces)
        put("ply", f"{fmt}-{'mesh' if faces else 'cloud'}.ply", data)
        put("cloud", f"{fmt}-{'mesh' if faces else 'cloud'}.ply", data)

# STL ascii and binary.
def stl_ascii():
    s = "solid seed\n"
    for t in tris:
        s += " facet normal 0 0 1\n  outer loop\n" + "".join(f"   vertex {pts[i][0]} {pts[i][1]} {pts[i][2]}\n" for i in t) + "  endloop\n endfacet\n"
    return s + "endsolid seed\n"

def stl_binary():
    b = b"seed".ljust(80, b" ") + struct.pack("<I", len(tris))
    for t in tris:
        b += struct.pack("<3f", 0, 0, 1) + b"".join(struct.pack("<3f", *pts[i]) for i in t) + b"\0\0"
    return b

for name, data in (("ascii.stl", stl_ascii()), ("binary.stl", stl_binary())):
    put("stl", name, data)
    put("cloud", name, data)

# XYZ: 3, 4 and 7 columns, comments, commas.
xyz = {
    "3col.xyz": "".join(f"{x} {y} {z}\n" for x, y, z in pts),
    "4col.xyz": "# x y z i\n" + "".join(f"{x}\t{y}\t{z}\t0.5\n" for x, y, z in pts),
    "7col.xyz": "".join(f"{x},{y},{z},0.5,0,0,1\n" for x, y, z in pts),
}
for name, data in xyz.items():
    put("xyz", name, data)
    put("cloud", name, data)

# OBJ, OFF and PCD (ascii, binary, LZF-compressed), through the sniffing reader.
obj = "# seed\nmtllib a.mtl\no part\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in pts) + "vn 0 0 1\n"
obj += "f 1//1 2//1 3//1\nf -3/1 -1/2 -2/3\nf 1 2 \\\n 4 3\n"
put("cloud", "mesh.obj", obj)
put("cloud", "points.obj", "".join(f"v {x} {y} {z}\n" for x, y, z in pts))
off = "OFF\n# seed\n%d %d 0\n" % (len(pts), len(tris)) + "".join(f"{x} {y} {z}\n" for x, y, z in pts)
put("cloud", "mesh.off", off + "".join(f"3 {a} {b} {c}\n" for a, b, c in tris))
put("cloud", "quads.coff", "COFF 4 1 0\n" + "".join(f"{x} {y} {z} 1 0 0 1\n" for x, y, z in pts) + "4 0 1 3 2 0.5 0.5 0.5\n")

def pcd(data, body, fields="x y z intensity", size="4 4 4 2", types="F F F U"):
    head = (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\n"
            f"TYPE {types}\nCOUNT 1 1 1 1\nWIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {len(pts)}\nDATA {data}\n")
    return head.encode() + body

put("cloud", "ascii.pcd", pcd("ascii", "".join(f"{x} {y} {z} 7\n" for x, y, z in pts).encode()))
rec = b"".join(struct.pack("<3fH", x, y, z, 7) for x, y, z in pts)
put("cloud", "binary.pcd", pcd("binary", rec))
soa = b"".join(struct.pack("<f", p[k]) for k in range(3) for p in pts) + struct.pack("<4H", 7, 7, 7, 7)
# LZF: the columns as literal runs (at most 32 bytes each), then the intensities' last 6 bytes as
# an overlapping back reference 2 bytes back (the u16 7 repeated): control (6 - 2) << 5, offset 1.
lits = soa[:-6]
body = b"".join(bytes([len(lits[i:i + 32]) - 1]) + lits[i:i + 32] for i in range(0, len(lits), 32))
body += bytes([4 << 5, 1])
put("cloud", "compressed.pcd", pcd("binary_compressed", struct.pack("<II", len(body), len(soa)) + body))

# PNG: grey 8 and 16 bit, with and without the depthmill metadata chunk.
def png(bits, text=None):
    w, h = 4, 3
    raw = b""
    for y in range(h):
        raw += b"\0" + b"".join((x * 40 + y * 9).to_bytes(bits // 8, "big") for x in range(w))
    chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))
    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bits, 0, 0, 0, 0))
    if text:
        out += chunk(b"tEXt", text)
    return out + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")

put("png", "grey8.png", png(8))
put("png", "grey16.png", png(16))
meta = json.dumps({"pixel_mm": 0.1, "z_min_mm": -5.0, "z_max_mm": 0.0, "width": 4, "height": 3}).encode()
put("png", "grey16-meta.png", png(16, b"depthmill\0" + meta))

# NPY: float32/64 little- and big-endian, C and Fortran order.
def npy(descr, fortran, fmt):
    header = "{'descr': '%s', 'fortran_order': %s, 'shape': (3, 4), }" % (descr, "True" if fortran else "False")
    header = header.ljust(118) + "\n"
    vals = [float(i) * 0.25 for i in range(12)]
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + struct.pack(fmt % 12, *vals)

for descr, fmt in (("<f4", "<%df"), ("<f8", "<%dd"), (">f4", ">%df"), (">f8", ">%dd")):
    for fortran in (False, True):
        put("npy", f"{descr[1:]}-{'be' if descr[0] == '>' else 'le'}-{'f' if fortran else 'c'}.npy", npy(descr, fortran, fmt))

copy_dir("tool", "services/cam/tools", "*.tool")
copy_dir("machine_toml", "services/machine/machines", "*.toml")

for kind in ("ply", "stl", "xyz", "png", "npy"):
    copy_dir(kind, f"tests/corpus/{kind}")
for kind in ("ply", "stl", "xyz", "obj", "off", "pcd"):
    copy_dir("cloud", f"tests/corpus/{kind}")
copy_dir("job_json", "tests/corpus/job")
copy_dir("gcode", "tests/corpus/gcode")
copy_dir("report_gcode", "tests/corpus/gcode")

program = """%
(seed: a slot, an arc, a tool change)
G21 G90 G17 G94 G40 G49 G80
T1 M6
S1500 M3
G43 H1
G0 X-5 Y10
G0 Z5
G1 Z8 F100
G1 X35 F200
G2 X25 Y15 I-5 J0 F150
G3 X15 Y10 R5
G0 Z15
T2 M6
S3000 M3 M8
G43 H2
G0 X10 Y5
G1 Z9 F80
G1 X20 Y12 Z8.5 F150
G91 G1 X-2 Y1
G90 G0 Z20 M9
G53 G0 Z0
M30
%
"""
put("gcode", "slot.ngc", program)
put("report_gcode", "slot.ngc", program)
put("gcode", "fanuc.ngc", "O1234\nN10 G21 G90 G17\nN20 T1 M6\nN30 S1200 M3\nN40 G0 X5 Y5 Z20\nN50 G1 Z9 F100\nN60 G2 X5 Y5 I3 J0 P2\nN70 M30\n")

jobs = [
    {"name": "seed", "input": {"kind": "depth_map", "artifact": "a" * 64, "pixel_mm": 0.2, "z_min_mm": -5, "z_max_mm": 0},
     "plan": {"roughing": {"tool": "flat-6", "step_down_mm": 2, "stock_to_leave_mm": 0.3},
              "finishing": {"tool": "ball-3", "strategy": "raster_angle", "angle_deg": 45, "step_over_mm": 0.3},
              "stock": {"x_mm": 60, "y_mm": 40, "z_mm": 20, "material": "aluminium"}},
     "execute": {"adaptive": "aco", "cell_mm": 0.2, "dexel": {"x_cell_mm": 0.5}}},
    {"input": {"kind": "mesh", "artifact": "b" * 64, "units": "inch"}, "scan": {}, "reconstruct": {}},
    {"input": {"kind": "gcode", "artifact": "c" * 64}, "execute": {"stock_z_mm": 30}},
]
for i, j in enumerate(jobs):
    put("job_json", f"job{i}.json", json.dumps(j))
print("seeds written to", here / "corpus")

#!/usr/bin/env python3
"""Writes the bad-input corpus (tests/corpus/<reader>/<case>): small files, each broken in one
named way. The files are committed; this script documents and regenerates them:
    python3 tests/corpus/make.py
What each one must give is in corpus.toml, checked by tests/e2e/corpus.rs."""
import gzip, os, struct, zlib

HERE = os.path.dirname(os.path.abspath(__file__))

def put(rel, data):
    path = os.path.join(HERE, rel)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(data if isinstance(data, bytes) else data.encode())

def stl_binary(tris, count=None, header=b"depthmill corpus"):
    out = header.ljust(80, b" ")[:80] + struct.pack("<I", len(tris) if count is None else count)
    for t in tris:
        out += struct.pack("<3f", 0, 0, 1)
        for v in t:
            out += struct.pack("<3f", *v)
        out += b"\0\0"
    return out

tri = [(0, 0, 0), (10, 0, 0), (0, 10, 1)]
# STL
put("stl/truncated-binary.stl", stl_binary([tri] * 3, count=10))
put("stl/count-overflow.stl", stl_binary([tri], count=0xFFFFFFFF))
put("stl/ascii-bad-number.stl", "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 zero\nvertex 0 1 0\nendloop\nendfacet\nendsolid x\n")
put("stl/ascii-truncated.stl", "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n")
put("stl/nan-vertices.stl", stl_binary([[(float("nan"),) * 3] * 3] * 4))
put("stl/zero-area.stl", stl_binary([[(1, 1, 1), (1, 1, 1), (1, 1, 1)]] * 4))
put("stl/empty.stl", b"")
# PLY
ply_head = "ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
put("ply/huge-vertex-count.ply", ply_head.format(fmt="ascii", n=4000000000) + "0 0 0\n1 1 1\n")
put("ply/truncated-binary.ply", ply_head.format(fmt="binary_little_endian", n=100).encode() + struct.pack("<9f", *range(9)))
put("ply/bad-format.ply", ply_head.format(fmt="binary_middle_endian", n=1) + "0 0 0\n")
put("ply/no-vertex-element.ply", "ply\nformat ascii 1.0\nelement point 1\nproperty float x\nend_header\n0\n")
put("ply/bad-number.ply", ply_head.format(fmt="ascii", n=3) + "0 0 0\n1 1 1\n2 two 2\n")
put("ply/all-nan.ply", ply_head.format(fmt="ascii", n=3) + "nan nan nan\nnan 0 0\ninf 1 1\n")
put("ply/no-end-header.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n0 0 0\n")
# XYZ
put("xyz/bad-number.xyz", "0 0 0\n1 1 1\n2 2 x\n")
put("xyz/column-count-changes.xyz", "0 0 0\n1 1 1 7\n")
put("xyz/nul-byte.xyz", b"0 0 0\n1\x001 1\n")
put("xyz/one-column.xyz", "12\n13\n")
# OBJ, OFF (meshes) and PCD (clouds)
put("obj/index-out-of-range.obj", "# a triangle\nv 0 0 0\nv 10 0 0\nv 0 10 1\nf 1 2 4\n")
put("obj/zero-index.obj", "v 0 0 0\nv 10 0 0\nv 0 10 1\nf 0 1 2\n")
put("off/truncated.off", "OFF\n3 1 0\n0 0 0\n10 0 0\n")
# Gzip-compressed meshes (read decompressed, whatever the name): cut short, and with its deflate
# data corrupted (mtime 0: the same bytes on every run).
good_stl_gz = gzip.compress(stl_binary([((0, 0, 0), (10, 0, 0), (0, 10, 1))] * 40), mtime=0)
put("stl/truncated.stl.gz", good_stl_gz[: len(good_stl_gz) // 2])
corrupt = bytearray(gzip.compress(b"".join(b"v %d 0 0\nv 0 %d 0\nv 0 0 %d\nf 1 2 3\n" % (i, i, i) for i in range(1, 200)), mtime=0))
for i in range(12, 40):
    corrupt[i] ^= 0x5A
put("obj/corrupt.obj.gz", bytes(corrupt))
put("off/binary.off", b"OFF BINARY\n" + struct.pack(">3i", 3, 1, 0) + struct.pack(">9f", 0, 0, 0, 10, 0, 0, 0, 10, 1))
pcd_head = "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
put("pcd/no-z-field.pcd", pcd_head.format(fields="x y w", n=2, data="ascii") + "0 0 0\n1 1 1\n")
put("pcd/compressed-size-mismatch.pcd", pcd_head.format(fields="x y z", n=100, data="binary_compressed").encode() + struct.pack("<II", 4, 1000) + bytes(4))
# PNG
def png(width, height, color_type, bit_depth, rows, text=None):
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    raw = b"".join(b"\0" + r for r in rows)
    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, bit_depth, color_type, 0, 0, 0))
    for k, v in (text or {}).items():
        out += chunk(b"tEXt", k.encode() + b"\0" + v.encode())
    return out + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
put("png/truncated.png", png(4, 4, 0, 8, [bytes(4)] * 4)[:40])
put("png/palette-without-plte.png", png(2, 2, 3, 8, [bytes(2)] * 2))
good = bytearray(png(4, 4, 0, 8, [bytes(4)] * 4))
at = good.index(b"IDAT")
good[at + 4 + struct.unpack(">I", bytes(good[at - 4:at]))[0]] ^= 0xFF  # the first byte of IDAT's CRC
put("png/bad-crc.png", bytes(good))
put("png/huge-dimensions.png", png(200000, 200000, 0, 8, [bytes(1)]))
put("png/no-scale.png", png(4, 4, 0, 16, [bytes(8)] * 4))
# NPY
def npy(descr, shape, payload):
    header = "{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, shape)
    header = header.ljust(118) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + payload
put("npy/bad-header.npy", b"\x93NUMPY\x01\x00\x10\x00{'descr': <<<<\n")
put("npy/integer-dtype.npy", npy("<i8", "(2, 2)", struct.pack("<4q", 1, 2, 3, 4)))
put("npy/truncated.npy", npy("<f4", "(100, 100)", struct.pack("<4f", 1, 2, 3, 4)))
put("npy/three-dimensions.npy", npy("<f4", "(2, 2, 2)", struct.pack("<8f", *range(8))))
put("npy/huge-shape.npy", npy("<f4", "(4000000000, 4000000000)", b""))
# G-code
put("gcode/unknown-word.ngc", "%\nG21 G90\nG1 X1 Y1 Z5 F100 Q5\nM30\n%\n")
put("gcode/bad-number.ngc", "%\nG21 G90\nG1 X1..5 F100\nM30\n%\n")
put("gcode/out-of-envelope.ngc", "%\nG21 G90\nT1 M6\nS1500 M3\nG0 X0 Y0 Z10\nG1 X5000 F100\nM30\n%\n")
put("gcode/arc-radius-mismatch.ngc", "%\nG21 G90 G17\nG0 X0 Y0 Z5\nG1 Z0 F100\nG2 X10 Y0 I3 J0 F200\nM30\n%\n")
put("gcode/spindle-too-fast.ngc", "%\nG21 G90\nS999999 M3\nG1 X1 F100\nM30\n%\n")
put("gcode/missing-tool.ngc", "%\nG21 G90\nT99 M6\nG1 X1 F100\nM30\n%\n")
# Job JSON
put("job/malformed.json", '{"input": {"kind": "gcode", "artifact": ')
put("job/unknown-field.json", '{"input": {"kind": "gcode", "artifact": "@GCODE@"}, "execute": {"machine": "emco-f1", "adaptve": "off"}}')
put("job/wrong-type.json", '{"input": {"kind": "gcode", "artifact": "@GCODE@"}, "execute": {"cell_mm": "fine"}}')
put("job/out-of-range.json", '{"input": {"kind": "point_cloud", "artifact": "@CLOUD@"}, "reconstruct": {"pixel_mm": 1e308}}')
put("job/negative.json", '{"input": {"kind": "point_cloud", "artifact": "@CLOUD@"}, "reconstruct": {"pixel_mm": -1}}')
put("job/unknown-kind.json", '{"input": {"kind": "hologram", "artifact": "@GCODE@"}}')
put("job/not-an-object.json", '[1, 2, 3]')
put("job/deep-nesting.json", '{"input": ' * 200 + '1' + '}' * 200)

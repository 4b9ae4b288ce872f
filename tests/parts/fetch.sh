#!/usr/bin/env bash
# fetch.sh DEST_DIR -- collect CAD-like test meshes and real range scans from
# Debian 12 (bookworm) packages and one PyPI wheel, and write DEST_DIR/SOURCES.md.
#
# Needs: apt-get + dpkg-deb (run as root, or with a populated apt cache), python3
# (standard library only), and pip (python3 -m pip or pip3) for the one PyPI item.
# Idempotent: a file already in DEST_DIR is left alone, and a package is only
# downloaded when one of its files is missing. Set FETCH_CACHE=/some/dir to keep
# the downloaded .deb/.whl files between runs (default: a temp dir, removed).
#
# ONLY="mesh-hinge.stl mesh-flange.stl" fetches just those files (CI's end-to-end subset).
#
# Output names:  mesh-*.stl  (triangle meshes; OFF sources converted to binary STL)
#                scan-*.ply / scan-*.xyz  (real measured point clouds)
#                bad/*      (broken / degenerate / odd-format inputs for reader tests)
#                native/*   (sources in the format their package ships: OFF, PCD; read natively)
set -euo pipefail

if [ $# -ne 1 ]; then echo "usage: $0 DEST_DIR" >&2; exit 2; fi
DEST=$(realpath -m "$1")
mkdir -p "$DEST" "$DEST/bad" "$DEST/native"
T0=$(date +%s)

if [ -n "${FETCH_CACHE:-}" ]; then
  CACHE=$(realpath -m "$FETCH_CACHE"); mkdir -p "$CACHE"; KEEP=1
else
  CACHE=$(mktemp -d /tmp/fetch-testdata.XXXXXX); KEEP=0
fi
cleanup() { if [ "$KEEP" = 0 ]; then rm -rf "$CACHE"; fi; }
trap cleanup EXIT
mkdir -p "$CACHE/debs" "$CACHE/pip" "$CACHE/x"
chmod 777 "$CACHE/debs" 2>/dev/null || true   # lets apt's _apt user write there

PY=${PYTHON:-python3}
command -v "$PY" >/dev/null || { echo "python3 is required (apt-get install python3)" >&2; exit 1; }
TOOL="$CACHE/meshtool.py"
cat > "$TOOL" <<'MESHTOOL_EOF'
#!/usr/bin/env python3
"""Tiny dependency-free mesh/point-cloud reader, converter and inspector.

Reads:  STL (ascii/binary), OFF (ascii), OBJ (v/f only), PLY (ascii/binary,
        vertex + optional face list), PCD (ascii/binary/binary_compressed),
        XYZ-like text (first 3 numeric columns).  Any of them may be .gz.
Writes: binary STL (meshes, polygons fan-triangulated) or binary little-endian
        PLY with float x,y,z vertices only (point clouds).

usage: meshtool.py info FILE...
       meshtool.py tostl IN OUT.stl [--scale S]
       meshtool.py toply IN OUT.ply [--scale S]   (points only)
       meshtool.py toxyz IN OUT.xyz [--scale S]   (points only)
       meshtool.py table DIR                      (markdown stats rows)
"""
import gzip
import struct
import sys


def _open(path):
    with open(path, 'rb') as f:
        data = f.read()
    if data[:2] == b'\x1f\x8b':
        data = gzip.decompress(data)
    return data


# ---------------------------------------------------------------- readers
def read_stl(data):
    tris = []
    if len(data) >= 84:
        n = struct.unpack_from('<I', data, 80)[0]
        if 84 + 50 * n == len(data):
            for i in range(n):
                v = struct.unpack_from('<12f', data, 84 + 50 * i)
                tris.append((v[3:6], v[6:9], v[9:12]))
            return None, tris
    # ascii
    cur = []
    for line in data.decode('latin-1').splitlines():
        t = line.split()
        if t and t[0].lower() == 'vertex':
            cur.append(tuple(float(x) for x in t[1:4]))
            if len(cur) == 3:
                tris.append(tuple(cur))
                cur = []
    return None, tris


def read_off(data):
    lines = []
    for l in data.decode('latin-1').splitlines():
        t = l.split('#', 1)[0].split()
        if t:
            lines.append(t)
    head = lines[0]
    if head[0] != 'OFF':
        raise ValueError('unsupported OFF header %r' % head[0])
    i = 1
    counts = head[1:]
    if not counts:
        counts = lines[1]
        i = 2
    nv, nf = int(counts[0]), int(counts[1])
    verts = [tuple(float(x) for x in l[:3]) for l in lines[i:i + nv]]
    faces = []
    for l in lines[i + nv:i + nv + nf]:
        k = int(l[0])
        faces.append(tuple(int(x) for x in l[1:1 + k]))
    return verts, faces


def read_obj(data):
    verts, faces = [], []
    for line in data.decode('latin-1').splitlines():
        t = line.split()
        if not t:
            continue
        if t[0] == 'v':
            verts.append((float(t[1]), float(t[2]), float(t[3])))
        elif t[0] == 'f':
            idx = []
            for s in t[1:]:
                j = int(s.split('/')[0])
                idx.append(j - 1 if j > 0 else len(verts) + j)
            faces.append(tuple(idx))
    return verts, faces


_PLY_T = {'char': 'b', 'int8': 'b', 'uchar': 'B', 'uint8': 'B',
          'short': 'h', 'int16': 'h', 'ushort': 'H', 'uint16': 'H',
          'int': 'i', 'int32': 'i', 'uint': 'I', 'uint32': 'I',
          'float': 'f', 'float32': 'f', 'double': 'd', 'float64': 'd'}


def read_ply(data):
    end = data.index(b'end_header')
    end = data.index(b'\n', end) + 1
    header = data[:end].decode('latin-1').splitlines()
    fmt = None
    elems = []
    for line in header:
        t = line.split()
        if not t:
            continue
        if t[0] == 'format':
            fmt = t[1]
        elif t[0] == 'element':
            elems.append([t[1], int(t[2]), []])
        elif t[0] == 'property':
            if t[1] == 'list':
                elems[-1][2].append((t[4], 'list', t[2], t[3]))
            else:
                elems[-1][2].append((t[2], t[1]))
    verts, faces = [], []
    if fmt == 'ascii':
        toks = iter(data[end:].decode('latin-1').split())
        for name, n, props in elems:
            for _ in range(n):
                rec = {}
                for p in props:
                    if p[1] == 'list':
                        k = int(next(toks))
                        rec[p[0]] = [int(float(next(toks))) for _ in range(k)]
                    else:
                        rec[p[0]] = float(next(toks))
                if name == 'vertex':
                    verts.append((rec['x'], rec['y'], rec['z']))
                elif name == 'face':
                    faces.append(tuple(rec.get('vertex_indices', rec.get('vertex_index', []))))
        return verts, faces
    e = '<' if fmt == 'binary_little_endian' else '>'
    off = end
    for name, n, props in elems:
        if all(p[1] != 'list' for p in props):
            st = struct.Struct(e + ''.join(_PLY_T[p[1]] for p in props))
            names = [p[0] for p in props]
            ix, iy, iz = (names.index('x'), names.index('y'), names.index('z')) if name == 'vertex' else (0, 0, 0)
            for rec in st.iter_unpack(data[off:off + st.size * n]):
                if name == 'vertex':
                    verts.append((rec[ix], rec[iy], rec[iz]))
            off += st.size * n
            continue
        for _ in range(n):
            rec = {}
            for p in props:
                if p[1] == 'list':
                    cs = struct.Struct(e + _PLY_T[p[2]])
                    k = cs.unpack_from(data, off)[0]
                    off += cs.size
                    its = struct.Struct(e + _PLY_T[p[3]] * k)
                    rec[p[0]] = its.unpack_from(data, off)
                    off += its.size
                else:
                    s = struct.Struct(e + _PLY_T[p[1]])
                    rec[p[0]] = s.unpack_from(data, off)[0]
                    off += s.size
            if name == 'vertex':
                verts.append((rec['x'], rec['y'], rec['z']))
            elif name == 'face':
                faces.append(tuple(rec.get('vertex_indices', rec.get('vertex_index', ()))))
    return verts, faces


def lzf_decompress(src, out_len):
    out = bytearray()
    i, n = 0, len(src)
    while i < n:
        ctrl = src[i]
        i += 1
        if ctrl < 32:
            out += src[i:i + ctrl + 1]
            i += ctrl + 1
        else:
            ln = ctrl >> 5
            ref = len(out) - ((ctrl & 0x1f) << 8) - 1
            if ln == 7:
                ln += src[i]
                i += 1
            ref -= src[i]
            i += 1
            ln += 2
            for _ in range(ln):
                out.append(out[ref])
                ref += 1
    if len(out) != out_len:
        raise ValueError('LZF size mismatch %d != %d' % (len(out), out_len))
    return bytes(out)


def read_pcd(data):
    hdr = {}
    off = 0
    while True:
        nl = data.index(b'\n', off)
        line = data[off:nl].decode('latin-1').strip()
        off = nl + 1
        if not line or line.startswith('#'):
            continue
        t = line.split()
        hdr[t[0]] = t[1:]
        if t[0] == 'DATA':
            break
    fields, sizes, types = hdr['FIELDS'], [int(x) for x in hdr['SIZE']], hdr['TYPE']
    counts = [int(x) for x in hdr.get('COUNT', ['1'] * len(fields))]
    npts = int(hdr['POINTS'][0])
    mode = hdr['DATA'][0]
    code = {('F', 4): 'f', ('F', 8): 'd', ('U', 1): 'B', ('U', 2): 'H', ('U', 4): 'I',
            ('I', 1): 'b', ('I', 2): 'h', ('I', 4): 'i'}
    xi = [fields.index(a) for a in 'xyz']
    verts = []
    if mode == 'ascii':
        col = []
        c = 0
        for f, k in zip(fields, counts):
            col.append(c)
            c += k
        for line in data[off:].decode('latin-1').splitlines():
            t = line.split()
            if len(t) < c:
                continue
            v = tuple(float(t[col[j]]) for j in xi)
            verts.append(v)
    elif mode == 'binary':
        st = struct.Struct('<' + ''.join(code[(ty, sz)] * k for ty, sz, k in zip(types, sizes, counts)))
        col = []
        c = 0
        for k in counts:
            col.append(c)
            c += k
        for rec in st.iter_unpack(data[off:off + st.size * npts]):
            verts.append((rec[col[xi[0]]], rec[col[xi[1]]], rec[col[xi[2]]]))
    elif mode == 'binary_compressed':
        csize, usize = struct.unpack_from('<II', data, off)
        raw = lzf_decompress(data[off + 8:off + 8 + csize], usize)
        # field-major layout: all x, then all y, ...
        starts = []
        p = 0
        for sz, k in zip(sizes, counts):
            starts.append(p)
            p += sz * k * npts
        cols = []
        for j in xi:
            fmt = '<%d%s' % (npts, code[(types[j], sizes[j])])
            cols.append(struct.unpack_from(fmt, raw, starts[j]))
        verts = list(zip(*cols))
    else:
        raise ValueError('PCD DATA %s' % mode)
    import math
    verts = [v for v in verts if all(math.isfinite(c) for c in v)]
    return verts, []


def read_xyz(data):
    verts = []
    for line in data.decode('latin-1').splitlines():
        t = line.replace(',', ' ').split()
        if len(t) >= 3:
            try:
                verts.append((float(t[0]), float(t[1]), float(t[2])))
            except ValueError:
                pass
    return verts, []


def read_any(path):
    data = _open(path)
    p = path.lower()
    if p.endswith('.gz'):
        p = p[:-3]
    ext = p.rsplit('.', 1)[-1]
    if ext == 'stl':
        return read_stl(data)
    if ext == 'off':
        return read_off(data)
    if ext == 'obj':
        return read_obj(data)
    if ext == 'ply':
        return read_ply(data)
    if ext == 'pcd':
        return read_pcd(data)
    return read_xyz(data)


# ---------------------------------------------------------------- helpers
def to_triangles(verts, faces):
    tris = []
    for f in faces:
        for k in range(1, len(f) - 1):
            tris.append((verts[f[0]], verts[f[k]], verts[f[k + 1]]))
    return tris


def write_stl(path, tris, scale=1.0, name=b'converted by meshtool.py'):
    out = bytearray(name[:80].ljust(80, b' '))
    out += struct.pack('<I', len(tris))
    pk = struct.Struct('<12fH')
    for a, b, c in tris:
        ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        vx, vy, vz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        ln = (nx * nx + ny * ny + nz * nz) ** 0.5 or 1.0
        out += pk.pack(nx / ln, ny / ln, nz / ln,
                       a[0] * scale, a[1] * scale, a[2] * scale,
                       b[0] * scale, b[1] * scale, b[2] * scale,
                       c[0] * scale, c[1] * scale, c[2] * scale, 0)
    with open(path, 'wb') as f:
        f.write(out)


def write_ply_points(path, verts, scale=1.0, comment='converted by meshtool.py'):
    hdr = ('ply\nformat binary_little_endian 1.0\ncomment %s\n'
           'element vertex %d\nproperty float x\nproperty float y\n'
           'property float z\nend_header\n' % (comment, len(verts)))
    out = bytearray(hdr.encode())
    pk = struct.Struct('<3f')
    for v in verts:
        out += pk.pack(v[0] * scale, v[1] * scale, v[2] * scale)
    with open(path, 'wb') as f:
        f.write(out)


def write_xyz(path, verts, scale=1.0):
    with open(path, 'w') as f:
        for v in verts:
            f.write('%.6f %.6f %.6f\n' % (v[0] * scale, v[1] * scale, v[2] * scale))


def detect_format(path):
    data = _open(path)
    p = path.lower()
    ext = p[:-3].rsplit('.', 1)[-1] if p.endswith('.gz') else p.rsplit('.', 1)[-1]
    if ext == 'stl':
        if len(data) >= 84 and 84 + 50 * struct.unpack_from('<I', data, 80)[0] == len(data):
            return 'STL binary' + (' (header starts with "solid")' if data[:5].lower() == b'solid' else '')
        return 'STL ascii' if data else 'STL (empty file)'
    if ext == 'ply':
        for line in data[:4096].split(b'\n'):
            if line.startswith(b'format'):
                return 'PLY ' + line.split()[1].decode()
        return 'PLY ?'
    return ext.upper() + ' text'


def info(path):
    verts, faces = read_any(path)
    if verts is None:  # STL triangle soup
        tris = faces
    else:
        tris = to_triangles(verts, faces)
    pts = [p for t in tris for p in t] if tris else verts
    if not pts:
        return dict(file=path, tris=0, points=0)
    lo = [min(p[i] for p in pts) for i in range(3)]
    hi = [max(p[i] for p in pts) for i in range(3)]
    res = dict(file=path, tris=len(tris), points=(len(verts) if verts is not None else 3 * len(tris)),
               bbox=[round(hi[i] - lo[i], 4) for i in range(3)],
               lo=[round(x, 4) for x in lo])
    if tris:
        # weld by exact coordinates, then count undirected edge uses
        idx = {}
        edges = {}
        degen = 0
        for t in tris:
            ids = [idx.setdefault(p, len(idx)) for p in t]
            if len(set(ids)) < 3:
                degen += 1
                continue
            for k in range(3):
                a, b = ids[k], ids[(k + 1) % 3]
                e = (a, b) if a < b else (b, a)
                edges[e] = edges.get(e, 0) + 1
        bnd = sum(1 for c in edges.values() if c == 1)
        nm = sum(1 for c in edges.values() if c > 2)
        res.update(welded_verts=len(idx), edges=len(edges), boundary_edges=bnd,
                   nonmanifold_edges=nm, degenerate_tris=degen,
                   closed=(bnd == 0 and nm == 0 and degen == 0))
    return res


def main(argv):
    if len(argv) >= 2 and argv[1] == 'info':
        import json
        for p in argv[2:]:
            try:
                print(json.dumps(info(p)))
            except Exception as ex:  # noqa
                print(json.dumps(dict(file=p, error=repr(ex))))
            sys.stdout.flush()
        return 0
    if len(argv) >= 4 and argv[1] in ('tostl', 'toply', 'toxyz'):
        scale = 1.0
        if '--scale' in argv:
            scale = float(argv[argv.index('--scale') + 1])
        verts, faces = read_any(argv[2])
        if argv[1] == 'tostl':
            tris = faces if verts is None else to_triangles(verts, faces)
            write_stl(argv[3], tris, scale)
        elif argv[1] == 'toply':
            write_ply_points(argv[3], verts, scale)
        else:
            write_xyz(argv[3], verts, scale)
        return 0
    print(__doc__)
    return 2


if __name__ == '__main__':
    sys.exit(main(sys.argv))
MESHTOOL_EOF

# ----------------------------------------------------------------------------
# Pinned versions (Debian 12 bookworm main / PyPI). If a pinned Debian version
# has left the archive, the current candidate is used and its version recorded.
declare -A APTVER=(
  [libcgal-demo]=5.5.1-2
  [netgen-doc]=6.2.2006+really6.2.1905+dfsg-5.1
  [openfoam-examples]=1912.200626-1
  [gmsh-doc]=4.8.4+ds2-3
  [prusa-slicer]=2.5.0+dfsg-4
  [admesh]=0.98.4-2
  [openscad-testing-data]=2021.01-6
  [python3-pcl]=0.3.0~rc1+dfsg-14+b2
)
declare -A APTLIC=(
  [libcgal-demo]="CGAL LICENSE: files without own notice CC0-1.0 (models originate from third-party repositories, see notes)"
  [netgen-doc]="LGPL-2+"
  [openfoam-examples]="GPL-3+"
  [gmsh-doc]="GPL-2+ with Gmsh exception"
  [prusa-slicer]="AGPL-3"
  [admesh]="GPL-2+"
  [openscad-testing-data]="GPL-2+ with CGAL exception"
  [python3-pcl]="BSD-3-Clause (debian/copyright Files: *; data from PCL tutorials)"
)
PIP_SPEC="pymeshlab==2025.7.post1"
PIP_LIC="GPL-3.0 (PyPI metadata License: GPL3)"
PIP_ARGS=(--no-deps --only-binary=:all: --python-version 3.11 --platform manylinux_2_35_x86_64)

CGAL=usr/share/doc/libcgal-dev/data.tar.gz
PML=pymeshlab-2025.7.post1.data/purelib/pymeshlab/tests/sample_meshes
OF=usr/share/doc/openfoam-examples/examples
GM=usr/share/doc/gmsh-doc
OS=usr/share/openscad/testdata
PCLD=usr/share/doc/python3-pcl/examples/pcldata/tutorials

# out | source | package | path in package ("outer::inner" = member of a tarball in the package) | action | units | note
ITEMS=$(cat <<'EOF'
mesh-hinge.stl|apt|netgen-doc|usr/share/doc/netgen/examples/hinge.stl|copy|mm|hinge leaf, 2 knuckles with through bores, 3 holes, chamfers
mesh-part1.stl|apt|netgen-doc|usr/share/doc/netgen/examples/part1.stl|copy|unitless (6x5x3)|sloped block with one through hole
mesh-flange.stl|apt|openfoam-examples|$OF/resources/geometry/flange.stl.gz|gunzip|m (52 mm part)|flange with bosses, bores, bolt holes; coordinates in METRES
mesh-lever.stl|apt|gmsh-doc|$GM/converters/stl_to_cartesian/lever.stl.gz|gunzip|mm|thin lever plate with bosses and holes; BINARY STL whose header starts with 'solid'!
mesh-t13-housing.stl|apt|gmsh-doc|$GM/doc/gmsh/tutorial/t13_data.stl.gz|gunzip|mm|rounded housing with central bore/pocket (gmsh tutorial t13)
mesh-m3x10-screw.stl|apt|prusa-slicer|usr/share/PrusaSlicer/shapes/M3x10_screw.stl|copy|mm|socket-head screw with modelled thread (helical, fine detail)
mesh-torus.stl|apt|prusa-slicer|usr/share/PrusaSlicer/shapes/torus.stl|copy|mm|torus (genus 1)
mesh-block-inch.stl|apt|admesh|usr/share/doc/admesh/examples/block.stl|copy|inch (100 mm cube)|ASCII STL with UPPER-CASE keywords; 3.937 in = 100 mm cube
mesh-fandisk.stl|apt|libcgal-demo|$CGAL::data/meshes/fandisk.off|off2stl|unitless (unit box)|fandisk: sharp feature lines + curved freeform (Hoppe)
mesh-pinion.stl|apt|libcgal-demo|$CGAL::data/meshes/pinion.off|off2stl|unitless (unit box)|spur gear / pinion with bore
mesh-cheese.stl|apt|libcgal-demo|$CGAL::data/meshes/cheese.off|off2stl|unitless (0.1 box)|cube pierced by many round through holes, thin walls
mesh-couplingdown.stl|apt|libcgal-demo|$CGAL::data/meshes/couplingdown.off|off2stl|unitless (unit box)|coupling disc: deep pocket, bolt holes, off-centre bore
mesh-rotor.stl|apt|libcgal-demo|$CGAL::data/meshes/rotor.off|off2stl|unitless (unit box)|thin-walled ring with boss
mesh-joint.stl|apt|libcgal-demo|$CGAL::data/meshes/joint.off|off2stl|unitless (unit box)|clevis/joint: cross bores, undercut under the cylinder
mesh-oblong.stl|apt|libcgal-demo|$CGAL::data/meshes/oblong.off|off2stl|likely mm (78x58x58)|block with circular pocket, slots and holes
mesh-anchor.stl|apt|libcgal-demo|$CGAL::data/meshes/anchor.off|off2stl|unitless (unit box)|angle bracket with holes and a lug (undercut)
mesh-spool.stl|apt|libcgal-demo|$CGAL::data/meshes/spool.off|off2stl|unitless (unit box)|spool: two flanges, narrow deep groove, bore
mesh-turbine.stl|apt|libcgal-demo|$CGAL::data/meshes/turbine.off|off2stl|unitless (unit box)|thin curved bell with bolt flange
mesh-bunny.stl|apt|libcgal-demo|$CGAL::data/meshes/bunny00.off|off2stl|unitless (unit box)|Stanford bunny, closed remesh (freeform, non-mechanical)
mesh-armadillo.stl|apt|libcgal-demo|$CGAL::data/meshes/armadillo.off|off2stl|unitless (~150 box)|Stanford armadillo, closed (freeform, thin limbs)
scan-face000.ply|pip|pymeshlab|$PML/rangemaps/face000.ply|copy|mm (scanner frame, z about -0.8 m)|REAL range map (MeshLab sample rangemaps) of a head; camera element = 640x480 sensor, 7.4 um pixels, f 14.4 mm (Minolta-Vivid-like laser triangulation); grid-triangulated, holes, outliers; PLY has an extra 'camera' element before 'vertex'
scan-face000-points.ply|pip|pymeshlab|$PML/rangemaps/face000.ply|ply2pts|mm (scanner frame)|same range map, vertices only (binary PLY x,y,z float)
scan-face000.xyz|pip|pymeshlab|$PML/rangemaps/face000.ply|ply2xyz|mm (scanner frame)|same range map as XYZ text
scan-table-lms400.ply|apt|python3-pcl|$PCLD/table_scene_lms400.pcd|pcd2ply|m (sensor frame)|REAL SICK LMS400 laser scan of a table scene (PCL tutorial data; PCD fields incl. intensity/distance/scan id); converted from PCD binary_compressed
scan-kinect-milk-clorox.ply|apt|python3-pcl|$PCLD/correspondence_grouping/milk_cartoon_all_small_clorox.pcd|pcd2ply|m (camera frame)|REAL Kinect-style RGB-D frame 640x480 (NaN-invalid pixels dropped), objects on a table
scan-stereo-table-mug.ply|apt|python3-pcl|$PCLD/table_scene_mug_stereo_textured.pcd|pcd2ply|m (camera frame)|REAL textured-stereo depth frame 640x480 (NaNs dropped) of a mug on a table
native/couplingdown.off|apt|libcgal-demo|$CGAL::data/meshes/couplingdown.off|copy|unitless (unit box)|mesh-couplingdown.stl as CGAL ships it (ASCII OFF), read by depthmill natively
native/mech-holes-shark.off|apt|libcgal-demo|$CGAL::data/meshes/mech-holes-shark.off|copy|unitless|bad/open-mech-holes-shark.stl as CGAL ships it (ASCII OFF)
native/table_scene_mug_stereo_textured.pcd|apt|python3-pcl|$PCLD/table_scene_mug_stereo_textured.pcd|copy|m (camera frame)|scan-stereo-table-mug.ply as PCL ships it (PCD binary_compressed, organised 640x480, NaN pixels)
native/table_scene_lms400.pcd|apt|python3-pcl|$PCLD/table_scene_lms400.pcd|copy|m (sensor frame)|scan-table-lms400.ply as PCL ships it (PCD binary_compressed, intensity)
native/milk_cartoon_all_small_clorox.pcd|apt|python3-pcl|$PCLD/correspondence_grouping/milk_cartoon_all_small_clorox.pcd|copy|m (camera frame)|scan-kinect-milk-clorox.ply as PCL ships it (PCD binary_compressed, organised, NaN pixels)
bad/binary-with-solid-header.stl|apt|openscad-testing-data|$OS/scad/3D/features/import_bin_solid.stl|copy|unitless|BINARY STL whose 80-byte header starts with 'solid' (must not be parsed as ASCII)
bad/invalid-vertex.stl|apt|openscad-testing-data|$OS/stl/invalidvertex.stl|copy|-|ASCII STL with a non-numeric vertex coordinate ('vertex 0 0 blah')
bad/unparseable.stl|apt|openscad-testing-data|$OS/stl/unparseable.stl|copy|-|ASCII STL with a corrupted vertex line (control byte + padding) and junk after endloop/endfacet/endsolid
bad/empty.stl|apt|openscad-testing-data|$OS/stl/empty.stl|copy|-|0-byte file
bad/empty-solid.stl|apt|openscad-testing-data|$OS/stl/empty2.stl|copy|-|ASCII 'solid ... endsolid' with no facets
bad/too-many-vertices.stl|apt|openscad-testing-data|$OS/stl/toomanyvertices.stl|copy|-|ASCII STL with one facet loop carrying 4 vertices (line 92)
bad/back-to-back.stl|apt|openscad-testing-data|$OS/scad/bugs/issue1580-back-to-back.stl|copy|-|two solids sharing a face: non-manifold edges
bad/zero-area-triangle.stl|apt|openscad-testing-data|$OS/scad/bugs/issue1580-zero-area-triangle.stl|copy|-|closed mesh containing a zero-area triangle (0,0,0)-(0,0,5)-(0,0,10)
bad/open-mech-holes-shark.stl|apt|libcgal-demo|$CGAL::data/meshes/mech-holes-shark.off|off2stl|unitless|open surface (304 boundary edges): holes cut in a freeform part
bad/wigley-hull-nonmanifold.stl|apt|openfoam-examples|$OF/resources/geometry/wigley.stl.gz|gunzip|m|open ship hull with 4 non-manifold edges and 392 boundary edges
EOF
)
ITEMS=$(echo "$ITEMS" | sed -e "s#\$CGAL#$CGAL#g" -e "s#\$PML#$PML#g" -e "s#\$OF#$OF#g" -e "s#\$GM#$GM#g" -e "s#\$OS#$OS#g" -e "s#\$PCLD#$PCLD#g")

# ----------------------------------------------------------------------------
APT_UPDATED=0
ensure_apt_lists() {
  if [ "$APT_UPDATED" = 0 ] && ! apt-cache show libcgal-demo >/dev/null 2>&1; then
    echo "+ apt-get update" >&2; apt-get update -qq >&2
  fi
  APT_UPDATED=1
}

deb_of() {  # echo path of the .deb for package $1, downloading it if needed
  local pkg=$1 f
  f=$(ls "$CACHE/debs/${pkg}_"*.deb 2>/dev/null | head -1 || true)
  if [ -z "$f" ]; then
    ensure_apt_lists
    echo "+ apt-get download $pkg=${APTVER[$pkg]}" >&2
    ( cd "$CACHE/debs" && { apt-get download -q "$pkg=${APTVER[$pkg]}" >&2 2>/dev/null \
        || { echo "  pinned version unavailable, using current candidate" >&2; apt-get download -q "$pkg" >&2; }; } )
    f=$(ls "$CACHE/debs/${pkg}_"*.deb | head -1)
  fi
  echo "$f"
}

whl_of() {
  local f
  f=$(ls "$CACHE/pip/"*.whl 2>/dev/null | head -1 || true)
  if [ -z "$f" ]; then
    local PIP
    if "$PY" -m pip --version >/dev/null 2>&1; then PIP=("$PY" -m pip)
    elif command -v pip3 >/dev/null; then PIP=(pip3)
    elif command -v pip >/dev/null; then PIP=(pip)
    else echo "pip not found (apt-get install python3-pip)" >&2; return 1; fi
    echo "+ pip download $PIP_SPEC" >&2
    "${PIP[@]}" download -q "${PIP_ARGS[@]}" "$PIP_SPEC" -d "$CACHE/pip" >&2
    f=$(ls "$CACHE/pip/"*.whl | head -1)
  fi
  echo "$f"
}

extract() {  # extract SRC PKG PATH -> echo local path of the member
  local src=$1 pkg=$2 path=$3 outer inner base
  if [ "$src" = pip ]; then
    local whl; whl=$(whl_of) || return 1
    base="$CACHE/x/pip"
    if [ ! -f "$base/$path" ]; then
      "$PY" - "$whl" "$path" "$base" <<'PYEOF'
import sys, zipfile
zipfile.ZipFile(sys.argv[1]).extract(sys.argv[2], sys.argv[3])
PYEOF
    fi
    echo "$base/$path"; return
  fi
  local deb; deb=$(deb_of "$pkg")
  base="$CACHE/x/$pkg"; mkdir -p "$base"
  outer=${path%%::*}; inner=""
  [[ "$path" == *::* ]] && inner=${path#*::}
  if [ ! -f "$base/$outer" ]; then
    dpkg-deb --fsys-tarfile "$deb" | tar -x -C "$base" "./$outer"
  fi
  if [ -n "$inner" ]; then
    if [ ! -f "$base/inner/$inner" ]; then
      mkdir -p "$base/inner"; tar -xzf "$base/$outer" -C "$base/inner" "$inner"
    fi
    echo "$base/inner/$inner"
  else
    echo "$base/$outer"
  fi
}

version_of() {  # $1=src $2=pkg
  if [ "$1" = pip ]; then echo "${PIP_SPEC#*==}"; else dpkg-deb -f "$(deb_of "$2")" Version; fi
}

META="$DEST/.sources.tsv"
touch "$META"
N_NEW=0
while IFS='|' read -r out src pkg path action units note; do
  [ -z "$out" ] && continue
  if [ -n "${ONLY:-}" ] && [[ " $ONLY " != *" $out "* ]]; then continue; fi
  target="$DEST/$out"
  if [ -s "$target" ] || { [ -e "$target" ] && [ "$action" = copy ] && grep -q "^$out	" "$META"; }; then
    continue
  fi
  echo "* $out  <-  $src:$pkg:$path" >&2
  inp=$(extract "$src" "$pkg" "$path")
  tmp="$target.part"
  case "$action" in
    copy)    cp "$inp" "$tmp" ;;
    gunzip)  gzip -dc "$inp" > "$tmp" ;;
    off2stl) "$PY" "$TOOL" tostl "$inp" "$tmp" ;;
    pcd2ply|ply2pts) "$PY" "$TOOL" toply "$inp" "$tmp" ;;
    ply2xyz) "$PY" "$TOOL" toxyz "$inp" "$tmp" ;;
    *) echo "unknown action $action" >&2; exit 1 ;;
  esac
  mv "$tmp" "$target"
  ver=$(version_of "$src" "$pkg")
  grep -v "^$out	" "$META" > "$META.tmp" || true
  printf '%s\t%s\n' "$out" "$ver" >> "$META.tmp"
  mv "$META.tmp" "$META"
  N_NEW=$((N_NEW + 1))
done <<< "$ITEMS"

# ----------------------------------------------------------------------------
echo "* writing $DEST/SOURCES.md" >&2
: > "$CACHE/items.tsv"
while IFS='|' read -r out src pkg path action units note; do
  [ -z "$out" ] && continue
  if [ "$src" = pip ]; then lic=$PIP_LIC; else lic=${APTLIC[$pkg]}; fi
  printf '%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\n' "$out" "$src" "$pkg" "$path" "$action" "$lic" "$units" "$note" >> "$CACHE/items.tsv"
done <<< "$ITEMS"
"$PY" - "$TOOL" "$DEST" "$CACHE/items.tsv" <<'PYEOF'
import hashlib, importlib.util, os, sys
spec = importlib.util.spec_from_file_location('meshtool', sys.argv[1])
mt = importlib.util.module_from_spec(spec); spec.loader.exec_module(mt)
dest = sys.argv[2]
vers = dict(l.rstrip('\n').split('\t')[:2] for l in open(os.path.join(dest, '.sources.tsv')) if l.strip())
rows = []
for l in open(sys.argv[3]):
    r = l.rstrip('\n').split('\t')
    if r[0] in vers:
        rows.append([r[0], r[1], r[2], vers[r[0]]] + r[3:])
rows.sort(key=lambda r: (r[0].startswith('bad/'), not r[0].startswith('mesh-'), r[0]))
out = ['# Test data sources', '',
       'Generated by fetch.sh. Triangle/point counts, bounding box and edge checks computed by its',
       'embedded meshtool.py (STL vertices welded by exact coordinates; "closed" = every edge shared by',
       'exactly two triangles, no degenerate triangles; vertices = distinct positions). Paths are inside the .deb data tree or the wheel;',
       '"A::B" means member B of tarball A inside the package.', '',
       '| file | source | package | version | path in package | licence | units | format | tris | vertices / points | bbox (x y z) | closed | size (bytes) | sha256 (first 16) | notes |',
       '|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|']
for out_name, src, pkg, ver, path, action, lic, units, note in rows:
    p = os.path.join(dest, out_name)
    if not os.path.exists(p):
        continue
    size = os.path.getsize(p)
    sha = hashlib.sha256(open(p, 'rb').read()).hexdigest()[:16]
    try:
        fmt = mt.detect_format(p)
    except Exception as ex:
        fmt = '?'
    try:
        i = mt.info(p)
        tris = i.get('tris', 0)
        pts = i.get('welded_verts', i.get('points', 0))
        bbox = ' x '.join('%g' % b for b in i['bbox']) if 'bbox' in i else '-'
        if 'closed' in i:
            closed = 'yes' if i['closed'] else 'no (boundary %d, non-manifold %d, degenerate %d)' % (
                i['boundary_edges'], i['nonmanifold_edges'], i['degenerate_tris'])
        else:
            closed = '-'
    except Exception as ex:
        tris, pts, bbox, closed = '-', '-', '-', 'unreadable: %s' % type(ex).__name__
    out.append('| %s | %s | %s | %s | `%s` | %s | %s | %s | %s | %s | %s | %s | %d | %s | %s |' % (
        out_name, src, pkg, ver, path, lic, units, fmt, tris, pts, bbox, closed, size, sha, note))
out += ['', 'CGAL data notes: the CGAL LICENSE puts files without their own notice under CC0-1.0, but several',
        'models come from third-party repositories (Stanford 3D Scanning Repository: bunny, armadillo -- research',
        'use; fandisk: H. Hoppe; others from AIM@SHAPE-era collections). Treat them as test data, not redistributable assets.', '']
open(os.path.join(dest, 'SOURCES.md'), 'w').write('\n'.join(out))
PYEOF

T1=$(date +%s)
echo "done: $N_NEW new file(s) in $DEST, $((T1 - T0)) s" >&2

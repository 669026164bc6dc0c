"""Meshes for the reference tracer: the OBJ and PLY loaders, the shader ball, transforms.

    Mesh                        vertices (V, 3), faces (F, 3) int, normals (V, 3) or None
    load_obj(path)              .obj: v, vn, f (polygons are fanned; per-corner normals kept)
    load_ply(path)              .ply, ascii or binary_little_endian: vertex x y z [nx ny nz],
                                face lists (fanned)
    transform_mesh(mesh, ..)    scale (a number or 3), then rotate_z (degrees), then translate
    SHADERBALL                  the shader ball as analytic pieces of revolution (accel.intersect_lathe)
    shaderball_mesh()           the same ball as a triangle mesh

A broken file raises FlowBSDFError naming it. Scene files (scene.py) place meshes and the ball
in their scenes.
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError


@dataclass
class Mesh:
    vertices: np.ndarray             # (V, 3)
    faces: np.ndarray                # (F, 3) int
    normals: np.ndarray = None       # (V, 3) or None


def unit(v):
    """Rows of v scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0)


_R, _C, _RG, _ZG0, _ZG1 = 0.7, 1.05, 0.62, 0.98, 1.12
_Z_NECK = _C - np.sqrt(_R * _R - 0.2 * 0.2)


def _rz(z):
    return float(np.sqrt(_R * _R - (z - _C) ** 2))


# The shader ball as analytic pieces (accel.intersect_lathe): exact and fast to intersect.
SHADERBALL = (
    ("disk", 0.0, 0.0, 0.55),                 # bottom
    ("cylinder", 0.55, 0.0, 0.12),            # base side
    ("disk", 0.12, 0.2, 0.55),                # base top
    ("cylinder", 0.2, 0.12, _Z_NECK),         # stem
    ("sphere", _C, _R, _Z_NECK, _ZG0),        # lower ball
    ("disk", _ZG0, _RG, _rz(_ZG0)),           # groove floor
    ("cylinder", _RG, _ZG0, _ZG1),            # groove wall
    ("disk", _ZG1, _RG, _rz(_ZG1)),           # groove ceiling
    ("sphere", _C, _R, _ZG1, _C + _R),        # upper ball
)


def shaderball_mesh(n_phi=64, rings=14):
    """A shader-ball-like surface of revolution about z: a round base, a stem and a ball
    (radius 0.7, centre z = 1.05) with a shallow groove around it. Analytic normals per
    smooth piece (creases stay sharp)."""
    R, C = _R, _C

    def arc(z0, z1, k):
        a0, a1 = np.arcsin((z0 - C) / R), np.arcsin((z1 - C) / R)
        a = np.linspace(a0, a1, k)
        return np.stack([R * np.cos(a), C + R * np.sin(a)], axis=1), np.stack([np.cos(a), np.sin(a)], axis=1)

    def line(p0, p1, k=2):
        t = np.linspace(0, 1, k)[:, None]
        pts = (1 - t) * np.asarray(p0, float) + t * np.asarray(p1, float)
        dr, dz = p1[0] - p0[0], p1[1] - p0[1]
        nrm = np.array([dz, -dr]) / np.hypot(dr, dz)
        return pts, np.repeat(nrm[None, :], k, axis=0)

    z_neck, zg0, zg1, rg = _Z_NECK, _ZG0, _ZG1, _RG
    rz = lambda z: np.sqrt(R * R - (z - C) ** 2)    # noqa: E731
    pieces = [
        line((0.0, 0.0), (0.55, 0.0)),            # bottom (faces down)
        line((0.55, 0.0), (0.55, 0.12)),          # base side
        line((0.55, 0.12), (0.2, 0.12), 3),       # base top
        line((0.2, 0.12), (0.2, z_neck), 3),      # stem
        arc(z_neck, zg0, rings),                  # lower ball
        line((rz(zg0), zg0), (rg, zg0)),          # groove floor (faces down)
        line((rg, zg0), (rg, zg1), 3),            # groove wall
        line((rg, zg1), (rz(zg1), zg1)),          # groove ceiling (faces up)
        arc(zg1, C + R - 1e-9, rings),            # upper ball
    ]
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    cp, sp = np.cos(phi), np.sin(phi)
    verts, norms, faces = [], [], []
    base = 0
    for pts, nr in pieces:
        k = len(pts)
        v = np.stack([pts[:, :1] * cp, pts[:, :1] * sp, np.repeat(pts[:, 1:2], n_phi, 1)], axis=-1)
        nv = np.stack([nr[:, :1] * cp, nr[:, :1] * sp, np.repeat(nr[:, 1:2], n_phi, 1)], axis=-1)
        verts.append(v.reshape(-1, 3))
        norms.append(nv.reshape(-1, 3))
        i = np.arange(k - 1)[:, None]
        j = np.arange(n_phi)[None, :]
        a = base + i * n_phi + j
        b = base + i * n_phi + (j + 1) % n_phi
        c, d = a + n_phi, b + n_phi
        quads = np.stack([a, b, d, c], axis=-1).reshape(-1, 4)
        faces.append(np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]))
        base += k * n_phi
    v, n, f = np.concatenate(verts), np.concatenate(norms), np.concatenate(faces)
    # drop degenerate triangles (at the axis)
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return Mesh(v, f[area > 1e-12], n)


def load_obj(path):
    path = Path(path)
    if not path.is_file():
        raise FlowBSDFError("mesh file not found", path)
    v, vn, faces, fnorm = [], [], [], []
    try:
        for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if parts[0] == "v":
                v.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vn":
                vn.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                if len(parts) < 4:
                    raise ValueError("a face needs at least 3 vertices")
                refs = [p.split("/") for p in parts[1:]]
                vi = [_obj_index(r[0], len(v)) for r in refs]
                ni = [_obj_index(r[2], len(vn)) if len(r) > 2 and r[2] else -1 for r in refs]
                for k in range(1, len(vi) - 1):
                    faces.append([vi[0], vi[k], vi[k + 1]])
                    fnorm.append([ni[0], ni[k], ni[k + 1]])
    except (ValueError, IndexError) as e:
        raise FlowBSDFError(f"line {lineno}: {e}", path) from None
    if not faces:
        raise FlowBSDFError("OBJ file has no faces", path)
    v, faces, fnorm = np.array(v, float), np.array(faces), np.array(fnorm)
    if faces.max() >= len(v) or faces.min() < 0:
        raise FlowBSDFError("a face refers to a vertex that does not exist", path)
    if vn and np.all(fnorm >= 0):
        if fnorm.max() >= len(vn):
            raise FlowBSDFError("a face refers to a normal that does not exist", path)
        # unroll: each face corner gets its own vertex so per-corner normals survive
        vn = np.array(vn, float)
        return Mesh(v[faces.ravel()], np.arange(faces.size).reshape(-1, 3), unit(vn[fnorm.ravel()]))
    return Mesh(v, faces, None)


def _obj_index(s, n):
    i = int(s)
    return i - 1 if i > 0 else n + i


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def load_ply(path):
    path = Path(path)
    if not path.is_file():
        raise FlowBSDFError("mesh file not found", path)
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise FlowBSDFError("not a PLY file (no ply / end_header)", path)
    body = data[data.index(b"\n", end) + 1:]
    fmt, elements = None, []
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        p = line.split()
        if not p:
            continue
        if p[0] == "format":
            fmt = p[1]
        elif p[0] == "element":
            elements.append((p[1], int(p[2]), []))
        elif p[0] == "property" and elements:
            elements[-1][2].append(p[1:])
    if fmt not in ("ascii", "binary_little_endian"):
        raise FlowBSDFError(f"PLY format {fmt!r} not supported (ascii or binary_little_endian)", path)
    try:
        verts, faces = _ply_body(body, fmt, elements)
    except (ValueError, IndexError, KeyError) as e:
        raise FlowBSDFError(f"broken PLY data ({e})", path) from None
    if verts is None or faces is None or len(faces) == 0:
        raise FlowBSDFError("PLY file needs vertex x, y, z and a face element", path)
    v = np.stack([verts[k] for k in "xyz"], axis=1).astype(float)
    n = np.stack([verts[k] for k in ("nx", "ny", "nz")], axis=1).astype(float) \
        if all(k in verts for k in ("nx", "ny", "nz")) else None
    f = np.array(faces)
    if f.max() >= len(v) or f.min() < 0:
        raise FlowBSDFError("a face refers to a vertex that does not exist", path)
    return Mesh(v, f, None if n is None else unit(n))


def _ply_body(body, fmt, elements):
    verts = faces = None
    if fmt == "ascii":
        tokens = body.decode("ascii").split()
        pos = 0
        for name, count, props in elements:
            rows = []
            for _ in range(count):
                row = {}
                for prop in props:
                    if prop[0] == "list":
                        k = int(tokens[pos])
                        row[prop[3]] = [int(x) for x in tokens[pos + 1:pos + 1 + k]]
                        pos += 1 + k
                    else:
                        row[prop[1]] = float(tokens[pos])
                        pos += 1
                rows.append(row)
            if name == "vertex":
                verts = {p[1]: np.array([r[p[1]] for r in rows]) for p in props if p[0] != "list"}
            elif name == "face":
                faces = _fan([r[props[0][3]] for r in rows])
        return verts, faces
    pos = 0
    for name, count, props in elements:
        if all(p[0] != "list" for p in props):
            dt = np.dtype([(p[1], "<" + _PLY_TYPES[p[0]]) for p in props])
            arr = np.frombuffer(body, dt, count, pos)
            pos += count * dt.itemsize
            if name == "vertex":
                verts = {k: arr[k] for k in arr.dtype.names}
        else:
            polys = []
            for _ in range(count):
                row = None
                for p in props:
                    if p[0] == "list":
                        ct, it = np.dtype("<" + _PLY_TYPES[p[1]]), np.dtype("<" + _PLY_TYPES[p[2]])
                        k = int(np.frombuffer(body, ct, 1, pos)[0])
                        pos += ct.itemsize
                        vals = np.frombuffer(body, it, k, pos)
                        pos += k * it.itemsize
                        if row is None:
                            row = vals.tolist()
                    else:
                        pos += np.dtype(_PLY_TYPES[p[0]]).itemsize
                polys.append(row)
            if name == "face":
                faces = _fan(polys)
    return verts, faces


def _fan(polys):
    out = []
    for p in polys:
        if len(p) < 3:
            raise ValueError("a face needs at least 3 vertices")
        out += [[p[0], p[k], p[k + 1]] for k in range(1, len(p) - 1)]
    return out


def transform_mesh(mesh, scale=1.0, rotate_z=0.0, translate=(0, 0, 0)):
    s = np.broadcast_to(np.asarray(scale, float), (3,))
    a = np.radians(rotate_z)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    v = (mesh.vertices * s) @ R.T + np.asarray(translate, float)
    n = None if mesh.normals is None else unit((mesh.normals / s) @ R.T)
    return Mesh(v, mesh.faces, n)

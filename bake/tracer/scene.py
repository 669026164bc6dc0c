"""Scenes for the reference tracer: the file format and the built-in scenes (meshes: meshes.py).

A scene file is TOML (`.toml`) or JSON (`.json`) with the same structure. World space is
z-up, lengths in any unit, relative paths resolve against the scene file's folder:

    [camera]
    position = [0, -4.5, 1.6]
    look_at  = [0, 0, 0.8]
    up       = [0, 0, 1]          # default [0, 0, 1]
    fov      = 30                 # degrees across the larger image side (Blender's "auto" fit)
    width    = 256
    height   = 256

    [materials.ball]              # a material of the manifest: sampled with --sampler
    manifest = "paper_white"

    [materials.floor]             # inline analytic model, keys as in bake/materials/analytic.py
    model = "lambert"
    albedo = 0.5
    sampler = "cosine"            # inline only: cosine | ggx | ideal | render (= follow --sampler);
                                  # default cosine for lambert, ggx (a fitted lobe) otherwise

    [[shape]]                     # type: mesh | shaderball | sphere | plane
    type = "mesh"
    file = "object.obj"           # .obj (v, vn, f; polygons are fanned) or .ply (ascii or
    material = "ball"             # binary_little_endian; vertex x y z [nx ny nz], face lists)
    translate = [0, 0, 0]         # mesh: scale (number or 3), then rotate_z (deg), then
    scale = 1.0                   # translate; shaderball (analytic, height 1.75, on z = 0):
    rotate_z = 0.0                # scale (a number) and translate only
    tangent = [1, 0, 0]           # any shape: reference direction of the tangent (x) axis for
                                  # anisotropic materials, projected onto the tangent plane

    [[shape]]
    type = "sphere"
    center = [0, 0, 1]
    radius = 1
    material = "ball"

    [[shape]]
    type = "plane"                # infinite, or a square of edge `size` centred at `point`
    point = [0, 0, 0]
    normal = [0, 0, 1]
    size = 20
    material = "floor"

    [[light]]
    type = "environment"          # exactly one of: file (.exr/.hdr, equirectangular, Blender's
    file = "studio.exr"           # mapping), sky = {sun_elevation, sun_azimuth, sun_size,
    strength = 1.0                # sun_strength, zenith, horizon, ground} (procedural, all
    rotate_z = 0.0                # optional) or constant = [r, g, b]

    [[light]]                     # Blender's lamps, Cycles' radiometry (bake/tracer/lights.py);
    type = "point"                # strength = Blender's color * energy * 2^exposure
    position = [2, -2, 4]
    strength = [500, 500, 500]    # W; or intensity = [40, 40, 40] (W/sr, = strength / 4 pi)
    radius = 0.0                  # default 0: a delta light; > 0: hit by BSDF rays (MIS)
    soft_falloff = true           # Blender's Soft Falloff (default): a disk facing the shading
                                  # point; false: a sphere
    camera = true                 # seen by camera rays (any lamp; default true)

    [[light]]
    type = "spot"                 # strength, radius, soft_falloff, camera as for point
    position = [0, 0, 3]
    direction = [0, 0, -1]        # the cone's axis; or frame = [[..], [..], [..]]: the lamp's
                                  # world-from-local 3x3 (rows, object scale included), cone about -Z
    size = 45                     # full cone angle, degrees
    blend = 0.15
    strength = [500, 500, 500]

    [[light]]
    type = "sun"
    direction = [0, 0.5, -1]      # where the light travels (Blender: the lamp's -Z)
    strength = [3, 3, 3]          # irradiance, W/m^2
    angle = 0.0                   # full angle, degrees; > 0: a cone hit by BSDF rays (MIS)

    [[light]]
    type = "area"                 # one-sided, emits along -(axis_u x axis_v) (Blender: local -Z)
    position = [0, 0, 3]          # centre
    axis_u = [1, 0, 0]            # full extents, perpendicular (Blender: size * scale along
    axis_v = [0, 1, 0]            # local X and Y)
    shape = "rectangle"           # or "ellipse" (square and disk are the equal-sided cases)
    strength = [100, 100, 100]    # W; or radiance = [..] (before the spread factor)
    spread = 180                  # degrees

    [render]                      # optional
    max_depth = 12                # path length limit (Russian roulette from depth 3)

Surfaces are two-sided (the shading normal is flipped towards the viewer); at most one
environment. Lamps are not geometry (as in Cycles): they cast no shadow and rays go on through
them. Shading normals: sphere and plane exact, meshes interpolate vertex normals
(face normals when the file has none); directions on the wrong side of the geometric
surface contribute nothing.

Built-in scenes (`builtin:NAME`, no files needed): `shaderball-env` (a shader-ball-like
procedural mesh under a soft procedural sky), `shaderball-ambient` (the same ball under a
constant white environment, the softest light: what noise remains comes from BSDF sampling
and the ball's own occlusion) and `shaderball-point` (the same ball on a grey floor lit by
one point light, black environment). `builtin_scene(name, material=...)`
puts a manifest material (or a Material object) on the ball.
"""
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from .accel import TriangleBVH, intersect_lathe, intersect_planes, intersect_spheres
from .lights import AreaLight, Environment, PointLight, SpotLight, SunLight, read_image, sky_image
from .meshes import SHADERBALL, load_obj, load_ply, transform_mesh, unit

INLINE_SAMPLERS = ("cosine", "ggx", "ideal", "render")
BUILTINS = ("shaderball-env", "shaderball-ambient", "shaderball-point")


# --------------------------------------------------------------------------- data

@dataclass
class Camera:
    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    fov: float = 30.0
    width: int = 128
    height: int = 128

    def rays(self, px, py, jitter):
        """Rays through pixel (px, py) (row 0 at the top) offset by jitter in [0, 1)²."""
        f = self.look_at - self.position
        f = f / np.linalg.norm(f)
        r = np.cross(f, self.up)
        r = r / np.linalg.norm(r)
        u = np.cross(r, f)
        half = np.tan(np.radians(self.fov) / 2) / max(self.width, self.height)
        x = (px + jitter[:, 0]) * 2 - self.width
        y = self.height - (py + jitter[:, 1]) * 2
        d = f[None, :] + half * (x[:, None] * r[None, :] + y[:, None] * u[None, :])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.position, d.shape).copy(), d


@dataclass
class SceneMaterial:
    name: str
    material: object                 # a bake Material: the true BSDF, always what is evaluated
    learned: bool                    # True: sampled with the render's sampler
    sampler: str = "render"          # inline materials: their own sampler unless "render"
    entry: object = None             # the manifest entry (manifest materials)


class Hit:
    """Surface data of the nearest hits of a batch of rays (valid where `kind` > 0)."""
    NONE, TRIANGLE, SPHERE, PLANE, LATHE = 0, 1, 2, 3, 4


class Scene:
    def __init__(self, camera, materials, lights, path="<scene>", max_depth=12):
        self.camera, self.materials, self.lights = camera, materials, lights
        self.path, self.max_depth = str(path), int(max_depth)
        self.env = next((l for l in lights if isinstance(l, Environment)), None)
        # lamps BSDF rays can hit (found along each ray by the integrator, not by intersect())
        self.lamps = [l for l in lights if not l.delta and not isinstance(l, Environment)]
        self._tris = []          # (v0, v1, v2, n0, n1, n2, mat, tangent) lists per mesh
        self.spheres, self.planes, self.lathes = [], [], []
        self.bvh = None

    # ---- building
    def add_mesh(self, mesh, material, tangent=(1, 0, 0)):
        v, f = mesh.vertices, mesh.faces
        n = mesh.normals
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        fn = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        if n is None:
            ns = [fn, fn, fn]
        else:
            ns = [n[f[:, k]] for k in range(3)]
        self._tris.append((v[f[:, 0]], v[f[:, 1]], v[f[:, 2]], *ns, np.full(len(f), material),
                           np.broadcast_to(np.asarray(tangent, float), (len(f), 3))))
        self.bvh = None

    def add_lathe(self, pieces, material, translate=(0, 0, 0), scale=1.0, tangent=(1, 0, 0)):
        """An analytic surface of revolution about z (see accel.intersect_lathe), uniformly
        scaled then translated."""
        self.lathes.append((pieces, np.asarray(translate, float), float(scale), material,
                            np.asarray(tangent, float)))

    def add_sphere(self, center, radius, material, tangent=(1, 0, 0)):
        self.spheres.append((np.asarray(center, float), float(radius), material, np.asarray(tangent, float)))

    def add_plane(self, point, normal, material, size=np.inf, tangent=(1, 0, 0)):
        n = np.asarray(normal, float)
        n = n / np.linalg.norm(n)
        a = _any_perp(n)
        self.planes.append((np.asarray(point, float), n, (a, np.cross(n, a)), float(size) / 2, material,
                            np.asarray(tangent, float)))

    def finish(self):
        if self._tris:
            cols = [np.concatenate([t[k] for t in self._tris]) for k in range(8)]
            self.tv0, self.tv1, self.tv2, self.tn0, self.tn1, self.tn2, self.tmat, self.ttan = cols
            self.bvh = TriangleBVH(self.tv0, self.tv1, self.tv2)
        return self

    @property
    def n_triangles(self):
        return 0 if self.bvh is None else len(self.tv0)

    # ---- queries
    def _nearest(self, o, d, t_best, any_hit=False):
        tri = sph = pl = None
        if self.bvh is not None:
            tri, b1, b2 = self.bvh.intersect(o, d, t_best, any_hit=any_hit)
        else:
            b1 = b2 = None
        lat = lat_n = None
        if self.lathes:
            lat, lat_n = np.full(len(o), -1), np.zeros((len(o), 3))
            for k, (pieces, T, s, _, _) in enumerate(self.lathes):
                tb = t_best / s
                pid, nm = intersect_lathe((o - T) / s, d, pieces, tb)
                h = pid >= 0
                t_best[h] = tb[h] * s
                lat[h], lat_n[h] = k, nm[h]
        if self.spheres:
            sph = intersect_spheres(o, d, [s[0] for s in self.spheres], [s[1] for s in self.spheres], t_best)
        if self.planes:
            pl = intersect_planes(o, d, [p[0] for p in self.planes], [p[1] for p in self.planes],
                                  [p[2] for p in self.planes], [p[3] for p in self.planes], t_best)
        return tri, b1, b2, (lat, lat_n), sph, pl

    def occluded(self, o, d, tmax):
        """True where something lies along o + t d for 0 < t < tmax (lamps never block)."""
        t_best = np.array(tmax, float, copy=True)
        t0 = t_best.copy()
        self._nearest(o, d, t_best, any_hit=True)
        return t_best < t0

    def intersect(self, o, d):
        """Nearest hit: dict with t, kind, p, ng, ns, tangent, mat, light (arrays over rays)."""
        n = len(o)
        t = np.full(n, np.inf)
        tri, b1, b2, (lat, lat_n), sph, pl = self._nearest(o, d, t)
        # later kinds overwrite t only where nearer, so the last index set wins: resolve in order
        kind = np.zeros(n, np.int64)
        idx = np.full(n, -1)
        for k, ids in ((Hit.TRIANGLE, tri), (Hit.LATHE, lat), (Hit.SPHERE, sph), (Hit.PLANE, pl)):
            if ids is not None:
                sel = ids >= 0
                kind[sel], idx[sel] = k, ids[sel]
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        ng = np.zeros((n, 3))
        ns = np.zeros((n, 3))
        tan = np.zeros((n, 3))
        mat = np.full(n, -1)
        m = kind == Hit.TRIANGLE
        if m.any():
            i = idx[m]
            ng[m] = np.cross(self.tv1[i] - self.tv0[i], self.tv2[i] - self.tv0[i])
            w1, w2 = b1[m][:, None], b2[m][:, None]
            ns[m] = (1 - w1 - w2) * self.tn0[i] + w1 * self.tn1[i] + w2 * self.tn2[i]
            tan[m], mat[m] = self.ttan[i], self.tmat[i]
        for k, (_, _, _, mt, tg) in enumerate(self.lathes):
            m = (kind == Hit.LATHE) & (idx == k)
            ng[m] = ns[m] = lat_n[m]
            tan[m], mat[m] = tg, mt
        for k, (c, r, mt, tg) in enumerate(self.spheres):
            m = (kind == Hit.SPHERE) & (idx == k)
            ng[m] = ns[m] = p[m] - c
            tan[m], mat[m] = tg, mt
        for k, (pt, nrm, _, _, mt, tg) in enumerate(self.planes):
            m = (kind == Hit.PLANE) & (idx == k)
            ng[m] = ns[m] = nrm
            tan[m], mat[m] = tg, mt
        ng = unit(ng)
        ns = unit(ns)
        return {"t": t, "kind": kind, "index": idx, "p": p, "ng": ng, "ns": ns, "tangent": tan, "mat": mat}


def _any_perp(n):
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = a - n * (a @ n)
    return a / np.linalg.norm(a)


# --------------------------------------------------------------------------- parsing

def _bad(path, problem):
    raise FlowBSDFError(problem, path)


def _vec(path, where, value, n=3, positive=False):
    try:
        arr = np.broadcast_to(np.asarray(value, float), (n,)).copy() if np.ndim(value) == 0 \
            else np.asarray(value, float)
    except (TypeError, ValueError):
        _bad(path, f"{where}: expected {n} numbers, got {value!r}")
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        _bad(path, f"{where}: expected {n} finite numbers, got {value!r}")
    if positive and np.any(arr < 0):
        _bad(path, f"{where}: values must be >= 0, got {value!r}")
    return arr


def _num(path, where, value, lo=None):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        _bad(path, f"{where}: expected a number, got {value!r}")
    if lo is not None and value <= lo:
        _bad(path, f"{where}: must be > {lo}, got {value!r}")
    return float(value)


def _keys(path, where, table, allowed, required=()):
    if not isinstance(table, dict):
        _bad(path, f"{where} must be a table")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        _bad(path, f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")
    for k in required:
        if k not in table:
            _bad(path, f"{where}: missing key {k!r}")


def load_scene(spec, manifest=None, material=None):
    """A Scene from a file path or `builtin:NAME`. manifest: a bake Manifest (bake/plumbing/manifest.py),
    or a function that reads one (called only when the scene names a manifest material), needed
    when the scene names manifest materials. material: for built-ins, the manifest name or
    Material put on the ball."""
    if isinstance(spec, str) and spec.startswith("builtin:"):
        return builtin_scene(spec[len("builtin:"):], material=material, manifest=manifest)
    path = Path(spec)
    if not path.is_file():
        raise FlowBSDFError("scene file not found", path)
    text = path.read_bytes()
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text.decode("utf-8"))
        elif path.suffix.lower() == ".toml":
            data = tomllib.loads(text.decode("utf-8"))
        else:
            raise FlowBSDFError("scene files end in .toml or .json", path)
    except UnicodeDecodeError:
        raise FlowBSDFError("scene file is not UTF-8 text", path) from None
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as e:
        raise FlowBSDFError(f"not valid {path.suffix[1:].upper()}: {e}", path) from None
    return scene_from_dict(data, path, manifest=manifest)


def _manifest(manifest, path):
    """The Manifest the scene's manifest materials come from (see load_scene)."""
    if manifest is None:
        raise FlowBSDFError("the scene names a manifest material, but no manifest was given", path)
    return manifest() if callable(manifest) else manifest


def _material(path, name, spec, manifest_holder):
    where = f"materials.{name}"
    if not isinstance(spec, dict):
        _bad(path, f"{where} must be a table")
    if "manifest" in spec:
        _keys(path, where, spec, {"manifest"})
        mname = spec["manifest"]
        manifest = manifest_holder()
        chosen = [e for e in manifest.materials if e.name == mname]
        if not chosen:
            _bad(path, f"{where}: no material {mname!r} in the manifest {manifest.path} "
                       f"(have: {', '.join(e.name for e in manifest.materials)})")
        entry = chosen[0]
        if entry.missing():
            _bad(path, f"{where}: the source file of manifest material {mname!r} is absent "
                       f"({entry.source_path()})")
        return SceneMaterial(name, entry.open(), learned=True, entry=entry)
    spec = dict(spec)
    sampler = spec.pop("sampler", None)
    if sampler is not None and sampler not in INLINE_SAMPLERS:
        _bad(path, f"{where}: sampler must be one of {', '.join(INLINE_SAMPLERS)}, not {sampler!r}")
    if "model" not in spec:
        _bad(path, f"{where}: needs 'manifest = NAME' or an analytic 'model'")
    from ..materials.analytic import from_spec
    try:
        mat = from_spec({**spec, "kind": "analytic"}, _where=where)
    except FlowBSDFError as e:
        _bad(path, e.problem)
    if sampler is None:
        sampler = "cosine" if spec["model"] == "lambert" else "ggx"
    return SceneMaterial(name, mat, learned=sampler == "render", sampler=sampler)


def scene_from_dict(data, path="<scene>", manifest=None):
    path = Path(path)
    _keys(path, "top level", data, {"camera", "materials", "shape", "light", "render"},
          ("camera", "materials", "shape"))
    cam = data["camera"]
    _keys(path, "camera", cam, {"position", "look_at", "up", "fov", "width", "height"},
          ("position", "look_at"))
    width, height = cam.get("width", 128), cam.get("height", 128)
    for k, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 16384:
            _bad(path, f"camera.{k}: expected a whole number of pixels in 1..16384, got {v!r}")
    fov = _num(path, "camera.fov", cam.get("fov", 30.0), lo=0)
    if fov >= 179:
        _bad(path, f"camera.fov: must be below 179 degrees, got {fov}")
    camera = Camera(_vec(path, "camera.position", cam["position"]), _vec(path, "camera.look_at", cam["look_at"]),
                    _vec(path, "camera.up", cam.get("up", [0, 0, 1])), fov, width, height)
    f = camera.look_at - camera.position
    if np.linalg.norm(f) == 0 or np.linalg.norm(np.cross(f, camera.up)) < 1e-9 * np.linalg.norm(f):
        _bad(path, "camera: look_at must differ from position and not be parallel to up")

    mats = data["materials"]
    if not isinstance(mats, dict) or not mats:
        _bad(path, "materials: needs at least one [materials.NAME] table")
    holder = {}

    def manifest_holder():
        if "m" not in holder:
            holder["m"] = _manifest(manifest, path)
        return holder["m"]

    materials = [_material(path, name, spec, manifest_holder) for name, spec in mats.items()]
    index = {m.name: i for i, m in enumerate(materials)}

    lights = []
    light_list = data.get("light", [])
    if not isinstance(light_list, list):
        _bad(path, "light: use [[light]] entries")
    for i, ls in enumerate(light_list, 1):
        lights.append(_light(path, f"light #{i}", ls))
    if sum(isinstance(l, Environment) for l in lights) > 1:
        _bad(path, "at most one environment light")
    render = data.get("render", {})
    _keys(path, "render", render, {"max_depth"})
    max_depth = render.get("max_depth", 12)
    if isinstance(max_depth, bool) or not isinstance(max_depth, int) or max_depth < 1:
        _bad(path, f"render.max_depth: expected a whole number >= 1, got {max_depth!r}")
    scene = Scene(camera, materials, lights, path=path, max_depth=max_depth)

    shapes = data["shape"]
    if not isinstance(shapes, list) or not shapes:
        _bad(path, "shape: needs at least one [[shape]] entry")
    for i, sh in enumerate(shapes, 1):
        _shape(path, f"shape #{i}", sh, scene, index)
    return scene.finish()


def _shape(path, where, sh, scene, index):
    if not isinstance(sh, dict):
        _bad(path, f"{where} must be a table")
    kind = sh.get("type")
    common = {"type", "material", "tangent"}
    allowed = {"mesh": {"file", "translate", "scale", "rotate_z"}, "shaderball": {"translate", "scale"},
               "sphere": {"center", "radius"}, "plane": {"point", "normal", "size"}}
    if kind not in allowed:
        _bad(path, f"{where}: type must be one of {', '.join(allowed)}, not {kind!r}")
    required = {"mesh": ("file",), "shaderball": (), "sphere": ("center", "radius"), "plane": ("point", "normal")}
    _keys(path, f"{where} ({kind})", sh, common | allowed[kind], ("material",) + required[kind])
    mname = sh["material"]
    if mname not in index:
        _bad(path, f"{where}: material {mname!r} is not defined under [materials] "
                   f"(have: {', '.join(index)})")
    mat = index[mname]
    tangent = _vec(path, f"{where}.tangent", sh.get("tangent", [1, 0, 0]))
    if kind == "shaderball":
        scale = _num(path, f"{where}.scale", sh.get("scale", 1.0), lo=0)
        scene.add_lathe(SHADERBALL, mat, _vec(path, f"{where}.translate", sh.get("translate", [0, 0, 0])),
                        scale, tangent)
    elif kind == "mesh":
        if True:
            file = Path(sh["file"]) if Path(sh["file"]).is_absolute() else path.parent / sh["file"]
            suffix = file.suffix.lower()
            if suffix == ".obj":
                mesh = load_obj(file)
            elif suffix == ".ply":
                mesh = load_ply(file)
            else:
                _bad(path, f"{where}: mesh files must be .obj or .ply, not {file.name!r}")
        scale = sh.get("scale", 1.0)
        scale = _vec(path, f"{where}.scale", scale)
        if np.any(scale <= 0):
            _bad(path, f"{where}.scale: must be > 0")
        mesh = transform_mesh(mesh, scale, _num(path, f"{where}.rotate_z", sh.get("rotate_z", 0.0)),
                              _vec(path, f"{where}.translate", sh.get("translate", [0, 0, 0])))
        scene.add_mesh(mesh, mat, tangent)
    elif kind == "sphere":
        scene.add_sphere(_vec(path, f"{where}.center", sh["center"]), _num(path, f"{where}.radius", sh["radius"], lo=0),
                         mat, tangent)
    else:
        n = _vec(path, f"{where}.normal", sh["normal"])
        if np.linalg.norm(n) == 0:
            _bad(path, f"{where}.normal: must not be zero")
        size = _num(path, f"{where}.size", sh["size"], lo=0) if "size" in sh else np.inf
        scene.add_plane(_vec(path, f"{where}.point", sh["point"]), n, mat, size, tangent)


def _light(path, where, ls):
    if not isinstance(ls, dict):
        _bad(path, f"{where} must be a table")
    kind = ls.get("type")
    if kind == "environment":
        _keys(path, where, ls, {"type", "file", "sky", "constant", "strength", "rotate_z"})
        given = [k for k in ("file", "sky", "constant") if k in ls]
        if len(given) != 1:
            _bad(path, f"{where}: an environment needs exactly one of file, sky, constant")
        strength = _num(path, f"{where}.strength", ls.get("strength", 1.0))
        if strength < 0:
            _bad(path, f"{where}.strength: must be >= 0")
        if "file" in ls:
            file = Path(ls["file"]) if Path(ls["file"]).is_absolute() else path.parent / ls["file"]
            image = read_image(file)
        elif "sky" in ls:
            sky = ls["sky"]
            keys = {"sun_elevation", "sun_azimuth", "sun_size", "sun_strength", "zenith", "horizon", "ground"}
            _keys(path, f"{where}.sky", sky, keys)
            args = {}
            for k, v in sky.items():
                args[k] = _vec(path, f"{where}.sky.{k}", v, positive=True) if k in ("zenith", "horizon", "ground") \
                    else _num(path, f"{where}.sky.{k}", v)
            if args.get("sun_size", 1) <= 0 or args.get("sun_strength", 0) < 0:
                _bad(path, f"{where}.sky: sun_size must be > 0 and sun_strength >= 0")
            image = sky_image(**args)
        else:
            image = _vec(path, f"{where}.constant", ls["constant"], positive=True)[None, None, :]
        return Environment(image, strength, _num(path, f"{where}.rotate_z", ls.get("rotate_z", 0.0)))
    if kind == "quad":
        _bad(path, f"{where}: type 'quad' was replaced by 'area' (Blender's area lamp: it casts no shadow "
                   "and rays go on through it): position = corner + (edge1 + edge2) / 2, axis_u = edge2, "
                   "axis_v = edge1, radiance as before")
    if kind not in LAMP_KEYS:
        _bad(path, f"{where}: type must be environment, {', '.join(LAMP_KEYS)}, not {kind!r}")
    required = {"point": ("position",), "spot": ("position", "size", "blend"), "sun": ("direction",),
                "area": ("position", "axis_u", "axis_v")}[kind]
    _keys(path, where, ls, LAMP_KEYS[kind] | {"type", "camera"}, required)
    camera = ls.get("camera", True)
    if not isinstance(camera, bool):
        _bad(path, f"{where}.camera: expected true or false, got {camera!r}")

    def num(key, default, lo, hi, lo_closed):
        """ls[key] (or default) within (lo, hi], or [lo, hi] when lo_closed."""
        x = _num(path, f"{where}.{key}", ls.get(key, default))
        if x < lo or (x == lo and not lo_closed) or x > hi:
            _bad(path, f"{where}.{key}: must be in {'[' if lo_closed else '('}{lo}, {hi}], got {x!r}")
        return x

    def vec(key):
        return _vec(path, f"{where}.{key}", ls[key])

    power = _one_of(path, where, ls, ("strength", "intensity") if kind == "point" else
                    ("strength", "radiance") if kind == "area" else ("strength",))
    if kind == "area":
        u, v = vec("axis_u"), vec("axis_v")
        if np.linalg.norm(np.cross(u, v)) == 0 or abs(u @ v) > 1e-6 * np.linalg.norm(u) * np.linalg.norm(v):
            _bad(path, f"{where}: axis_u and axis_v must be perpendicular and not zero")
        shape = ls.get("shape", "rectangle")
        if shape not in ("rectangle", "ellipse"):
            _bad(path, f"{where}.shape: must be rectangle or ellipse, not {shape!r}")
        return AreaLight(vec("position"), u, v, ellipse=shape == "ellipse", camera=camera,
                         spread_deg=num("spread", 180.0, 0, 180, False), **power)
    if kind == "sun":
        return SunLight(_direction(path, where, ls), angle_deg=num("angle", 0.0, 0, 180, True), camera=camera,
                        **power)
    soft = ls.get("soft_falloff", True)
    if not isinstance(soft, bool):
        _bad(path, f"{where}.soft_falloff: expected true or false, got {soft!r}")
    point = dict(radius=num("radius", 0.0, 0, np.inf, True), soft_falloff=soft, camera=camera, **power)
    if kind == "point":
        return PointLight(vec("position"), **point)
    if ("direction" in ls) == ("frame" in ls):
        _bad(path, f"{where}: a spot needs exactly one of direction, frame")
    if "frame" in ls:
        try:
            frame = np.asarray(ls["frame"], float)
        except (TypeError, ValueError):
            frame = None
        if frame is None or frame.shape != (3, 3) or not np.all(np.isfinite(frame)) \
                or abs(np.linalg.det(frame)) < 1e-12:
            _bad(path, f"{where}.frame: expected an invertible 3x3 matrix (3 rows of 3 numbers)")
    else:
        axis = _direction(path, where, ls)
        frame = np.column_stack([*_perpendiculars(axis), -axis])
    return SpotLight(vec("position"), frame=frame, size_deg=num("size", None, 0, 180, False),
                     blend=num("blend", None, 0, 1, True), **point)


LAMP_KEYS = {
    "point": {"position", "strength", "intensity", "radius", "soft_falloff"},
    "spot": {"position", "strength", "radius", "soft_falloff", "direction", "frame", "size", "blend"},
    "sun": {"direction", "strength", "angle"},
    "area": {"position", "axis_u", "axis_v", "shape", "strength", "radiance", "spread"},
}


def _one_of(path, where, ls, keys):
    """{key: rgb} for the one of `keys` the lamp gives (values >= 0)."""
    given = [k for k in keys if k in ls]
    if len(given) != 1:
        _bad(path, f"{where}: needs exactly one of {', '.join(keys)}")
    return {given[0]: _vec(path, f"{where}.{given[0]}", ls[given[0]], positive=True)}


def _direction(path, where, ls):
    d = _vec(path, f"{where}.direction", ls["direction"])
    if np.linalg.norm(d) == 0:
        _bad(path, f"{where}.direction: must not be zero")
    return d / np.linalg.norm(d)


def _perpendiculars(n):
    a = _any_perp(n)
    return a, np.cross(n, a)


# --------------------------------------------------------------------------- built-ins

def builtin_scene(name, material=None, manifest=None, width=128, height=128):
    """The paper-like setups. material: a manifest name, a Material, or None (the
    manifest's 'red_plastic' if there, else an inline plastic)."""
    if name not in BUILTINS:
        raise FlowBSDFError(f"unknown built-in scene {name!r} (have: {', '.join(BUILTINS)})")
    camera = Camera(np.array([0.0, -4.2, 1.9]), np.array([0.0, 0.0, 0.72]), fov=30.0, width=width, height=height)
    ball = _builtin_material(material, manifest)
    if name == "shaderball-env":
        lights = [Environment(sky_image())]
        mats = [ball]
    elif name == "shaderball-ambient":
        lights = [Environment(np.ones((8, 16, 3)))]
        mats = [ball]
    else:
        lights = [PointLight([2.0, -2.5, 4.0], intensity=[30.0, 30.0, 30.0])]
        from ..materials.analytic import from_spec
        mats = [ball, SceneMaterial("floor", from_spec({"model": "lambert", "albedo": 0.5}),
                                    learned=False, sampler="cosine")]
    scene = Scene(camera, mats, lights, path=f"builtin:{name}")
    scene.add_lathe(SHADERBALL, 0)
    if name == "shaderball-point":
        scene.add_plane([0, 0, 0], [0, 0, 1], 1, size=12.0)
    return scene.finish()


def _builtin_material(material, manifest):
    from ..materials.base import Material
    if isinstance(material, Material):
        return SceneMaterial(getattr(material, "name", "ball"), material, learned=True)
    if isinstance(material, SceneMaterial):
        return material
    m = _manifest(manifest, None)
    name = material or "red_plastic"
    chosen = [e for e in m.materials if e.name == name]
    if not chosen:
        raise FlowBSDFError(f"no material {name!r} in the manifest (have: "
                            f"{', '.join(e.name for e in m.materials)})", m.path)
    entry = chosen[0]
    if entry.missing():
        raise FlowBSDFError(f"the source of material {name!r} is absent ({entry.source_path()})", m.path)
    return SceneMaterial(name, entry.open(), learned=True, entry=entry)

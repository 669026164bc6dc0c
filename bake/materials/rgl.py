"""RGL measured BSDFs (Dupuy & Jakob 2018) read from `.bsdf` tensor files, with numpy only.

`read_tensor_file(path)` parses the file strictly and, by default, checks that it holds a
complete RGB RGL material. The layout (Mitsuba's tensor_file, little-endian):

    b"tensor_file" and a NUL byte, version (2 bytes: 1, 0), uint32 number of fields,
    then per field: uint16 name length, the name (UTF-8), uint16 ndim, uint8 dtype code
    (DTYPES), uint64 offset of its data, ndim x uint64 shape; then each field's data
    (C order) at its offset.

`RGLMaterial(path).eval(wi, wo)` reproduces Mitsuba 3's `measured` plugin (RGB variant)
divided by cos(theta_o); see the class docstring for the algorithm.

One file of ~760 lines on purpose: the format reader, the evaluator that must match Mitsuba's
`measured` line for line, and the warp the carried blend samples along share their index
arithmetic; split, a reader would have to hold three files side by side to check one formula.
"""
import hashlib
import os
import struct
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from ..maths.geometry import atan2
from .base import Material, as_dirs

MAGIC = b"tensor_file\0"
VERSION = (1, 0)
# dtype code -> numpy dtype (little-endian)
DTYPES = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8",
          9: "<f2", 10: "<f4", 11: "<f8"}
MAX_NDIM = 8
MAX_ELEMENTS = 2 ** 31
# Fields an RGB RGL material must hold (what Mitsuba's `measured` plugin reads, less the
# free-text description, which eval does not need).
RGL_FIELDS = ("theta_i", "phi_i", "ndf", "sigma", "vndf", "luminance", "rgb", "jacobian")
CHUNK = 1 << 14  # eval works in chunks of this many pairs (keeps temporaries in cache)
# The shared RGL data set the manifest, the tests and the acceptance scripts use: <name>.bsdf
# in shared_dir().
SHARED_FILES = [
    "paper_white_rgb", "colodur_napoli_4f_rgb", "satin_rosaline_rgb", "cm_military_green_rgb",
    "cc_nothern_aurora_rgb", "vch_golden_yellow_rgb", "irid_flake_paint1_rgb",
    "cc_green_malachite_rgb", "ilm_solo_m_68_rgb", "chm_mint_rgb",
]


def shared_dir():
    """Where the shared RGL files live: $FLOWBSDF_RGL_DIR, else ../shared/data/rgl beside the
    repository (as manifest.toml's sources say)."""
    return Path(os.environ.get("FLOWBSDF_RGL_DIR", Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"))


def write_tensor_file(path, fields):
    """Write {name: array} in the tensor_file layout (the module's docstring; data 8-byte aligned
    after the table): synthetic files for tests and the stress suite."""
    codes = {np.dtype(v): k for k, v in DTYPES.items()}
    fields = {k: np.ascontiguousarray(v) for k, v in fields.items()}
    table_size = 18 + sum(2 + len(k.encode()) + 11 + 8 * v.ndim for k, v in fields.items())
    offset = (table_size + 7) // 8 * 8
    table, data = bytearray(), bytearray()
    for name, v in fields.items():
        table += struct.pack("<H", len(name.encode())) + name.encode()
        table += struct.pack("<HBQ", v.ndim, codes[v.dtype], offset + len(data))
        table += struct.pack(f"<{v.ndim}Q", *v.shape)
        data += v.tobytes() + b"\0" * (-v.nbytes % 8)
    head = b"tensor_file\0" + bytes([1, 0]) + struct.pack("<I", len(fields)) + bytes(table)
    Path(path).write_bytes(head + b"\0" * (offset - len(head)) + bytes(data))
    return Path(path)


def read_tensor_file(path, rgl=True):
    """Parse an RGL tensor file into {field name: read-only numpy array}.

    Every malformed input raises FlowBSDFError(problem, path). With `rgl=True` (the
    default) the fields must also form a valid RGB RGL material (names, dtypes, shapes
    consistent with each other, increasing angle tables, normalizable distributions).
    """
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as e:
        raise FlowBSDFError(f"cannot read file: {e.strerror or e}", path) from None
    size = len(buf)
    if size == 0:
        raise FlowBSDFError("empty file (0 bytes); expected an RGL tensor file", path)
    if buf[:len(MAGIC)] != MAGIC[:min(size, len(MAGIC))]:
        raise FlowBSDFError(
            f"not an RGL tensor file: bad magic {buf[:len(MAGIC)]!r} (expected {MAGIC!r})", path)
    if size < 18:
        raise FlowBSDFError(f"truncated header: the file has only {size} bytes", path)
    version = (buf[12], buf[13])
    if version != VERSION:
        raise FlowBSDFError(
            f"unsupported tensor file version {version[0]}.{version[1]} (this reader knows 1.0)", path)
    (n_fields,) = struct.unpack_from("<I", buf, 14)
    pos = 18
    # Each field entry needs at least 2 + 2 + 1 + 8 = 13 bytes (plus its name and shape).
    if n_fields * 13 > size - pos:
        raise FlowBSDFError(
            f"truncated field table: the header announces {n_fields} fields, more than "
            f"{size - pos} remaining bytes can describe", path)

    def take(fmt, what):
        nonlocal pos
        need = struct.calcsize(fmt)
        if pos + need > size:
            raise FlowBSDFError(f"truncated field table (file ends inside {what})", path)
        values = struct.unpack_from(fmt, buf, pos)
        pos += need
        return values

    entries = []
    for k in range(n_fields):
        (name_len,) = take("<H", f"the name length of field #{k}")
        if name_len == 0:
            raise FlowBSDFError(f"field #{k} has an empty name", path)
        if pos + name_len > size:
            raise FlowBSDFError(f"truncated field table (file ends inside the name of field #{k})", path)
        try:
            name = buf[pos:pos + name_len].decode("utf-8")
        except UnicodeDecodeError:
            raise FlowBSDFError(f"field #{k} has a name that is not valid UTF-8", path) from None
        pos += name_len
        ndim, code, offset = take("<HBQ", f"the entry of field {name!r}")
        if ndim > MAX_NDIM:
            raise FlowBSDFError(f"field {name!r} has an absurd ndim {ndim} (at most {MAX_NDIM})", path)
        if code not in DTYPES:
            raise FlowBSDFError(f"field {name!r} has an unknown dtype code {code} (known: 1-11)", path)
        shape = take(f"<{ndim}Q", f"the shape of field {name!r}") if ndim else ()
        if any(name == e[0] for e in entries):
            raise FlowBSDFError(f"field {name!r} appears twice", path)
        entries.append((name, code, offset, shape))
    header_end = pos

    fields = {}
    for name, code, offset, shape in entries:
        count = 1
        for s in shape:
            count *= s  # python ints: no overflow
        if count > MAX_ELEMENTS:
            raise FlowBSDFError(
                f"field {name!r} has an absurd shape {tuple(shape)} ({count} elements, "
                f"more than 2**31)", path)
        dtype = np.dtype(DTYPES[code])
        nbytes = count * dtype.itemsize
        if offset < header_end:
            raise FlowBSDFError(
                f"field {name!r} has its data at offset {offset}, inside the header "
                f"(which ends at {header_end})", path)
        if offset + nbytes > size:
            raise FlowBSDFError(
                f"truncated data: field {name!r} {tuple(shape)} needs bytes {offset}..{offset + nbytes} "
                f"but the file ends at {size} (data past end of file)", path)
        array = np.frombuffer(buf, dtype=dtype, count=count, offset=offset).reshape(shape)
        if dtype.kind == "f" and count and not np.isfinite(array).all():
            bad = int(np.count_nonzero(~np.isfinite(array)))
            raise FlowBSDFError(f"field {name!r} holds {bad} NaN or infinite values", path)
        fields[name] = array
    if rgl:
        _check_rgl(fields, path)
    return fields


def _check_rgl(f, path):
    """Raise FlowBSDFError unless the fields form an RGB RGL material Mitsuba would load."""
    missing = [k for k in RGL_FIELDS if k not in f]
    if "rgb" in missing and "spectra" in f:
        raise FlowBSDFError(
            "spectral RGL file (field 'spectra', no 'rgb'): FlowBSDF reads the RGB version of "
            "the material (the *_rgb.bsdf download)", path)
    if missing:
        raise FlowBSDFError(f"missing required field(s) {', '.join(missing)} (not an RGL material?)", path)

    def expect(name, ndim, dtype="float32"):
        a = f[name]
        if a.dtype.name != dtype:
            raise FlowBSDFError(f"field {name!r} has dtype {a.dtype.name}, expected {dtype}", path)
        if a.ndim != ndim:
            raise FlowBSDFError(
                f"inconsistent shape: field {name!r} has shape {a.shape}, expected {ndim} dimensions", path)
        return a.shape

    (n_theta,) = expect("theta_i", 1)
    (n_phi,) = expect("phi_i", 1)
    if n_theta < 1 or n_phi < 1:
        raise FlowBSDFError("inconsistent shape: theta_i and phi_i must not be empty", path)
    for name in ("theta_i", "phi_i"):
        if np.any(np.diff(f[name]) <= 0):
            raise FlowBSDFError(f"field {name!r} must be strictly increasing, got {f[name].tolist()}", path)
    if n_phi > 2:
        # Mitsuba mirrors wi into the measured range by the symmetry 2 pi / span (1, 2 or 4);
        # any other span has no such symmetry and would be evaluated wrongly.
        span = float(f["phi_i"][-1]) - float(f["phi_i"][0])
        if int(np.rint(2 * np.pi / span)) not in (1, 2, 4):
            raise FlowBSDFError(f"field 'phi_i' spans {span:.4g} rad: an anisotropic RGL file covers the "
                                "whole, half or quarter circle", path)
    for name in ("ndf", "sigma"):
        shape = expect(name, 2)
        if min(shape) < 2:
            raise FlowBSDFError(f"inconsistent shape: field {name!r} {shape} needs at least 2 x 2 entries", path)
    shape = expect("vndf", 4)
    if shape[:2] != (n_phi, n_theta) or min(shape[2:]) < 2:
        raise FlowBSDFError(
            f"inconsistent shape: vndf {shape} should be ({n_phi}, {n_theta}, >=2, >=2) "
            f"to match phi_i and theta_i", path)
    lum = expect("luminance", 4)
    if lum[:2] != (n_phi, n_theta) or lum[2] != lum[3] or lum[2] < 2:
        raise FlowBSDFError(
            f"inconsistent shape: luminance {lum} should be ({n_phi}, {n_theta}, n, n) with n >= 2", path)
    rgb = expect("rgb", 5)
    if rgb != (n_phi, n_theta, 3, lum[2], lum[3]):
        raise FlowBSDFError(
            f"inconsistent shape: rgb {rgb} should be ({n_phi}, {n_theta}, 3, {lum[2]}, {lum[3]}) "
            f"to match luminance {lum}", path)
    if f["jacobian"].dtype != np.uint8 or f["jacobian"].shape != (1,):
        raise FlowBSDFError(
            f"field 'jacobian' should be one uint8, got {f['jacobian'].dtype.name} {f['jacobian'].shape}", path)
    if np.any(f["sigma"] <= 0):
        raise FlowBSDFError("field 'sigma' (projected area) holds zero or negative values", path)
    for name in ("vndf", "luminance"):
        a = f[name].astype(np.float64)
        # Integral of the bilinear interpolant of every (phi_i, theta_i) slice.
        total = (a[..., :-1, :-1] + a[..., 1:, :-1] + a[..., :-1, 1:] + a[..., 1:, 1:]).sum((-1, -2))
        if np.any(total <= 0):
            bad = np.argwhere(total <= 0)[0]
            raise FlowBSDFError(
                f"field {name!r} slice (phi_i #{bad[0]}, theta_i #{bad[1]}) integrates to zero or "
                f"less: it cannot be normalized", path)


def _continuous_warp_table(data):
    """Per-patch table of a continuous Marginal2D warp, slice by slice.

    data: (S, ny, nx) float32. Returns (S * (ny-1) * (nx-1), 9) float64 rows
    [v00, v10, v01, v11, cdf(y, x), cdf(y+1, x), cdf_row(y), cdf_row(y+1), marginal(y)]
    for the patch at (y, x): corner densities, conditional CDF at the patch's left edge on
    its two rows, the two rows' totals, and the marginal CDF at its lower row. Everything
    is normalized so that the bilinear interpolant integrates to 1 over the index square,
    rounding to float32 where Mitsuba stores float32.
    """
    data = np.asarray(data, dtype=np.float32)
    s, ny, nx = data.shape
    d64 = data.astype(np.float64)
    cond = np.zeros((s, ny, nx), np.float64)
    cond[:, :, 1:] = np.cumsum(0.5 * (d64[:, :, :-1] + d64[:, :, 1:]), axis=2)
    cond = cond.astype(np.float32)
    rows = cond[:, :, -1].astype(np.float64)
    marg = np.zeros((s, ny), np.float64)
    marg[:, 1:] = np.cumsum(0.5 * (rows[:, :-1] + rows[:, 1:]), axis=1)
    marg = marg.astype(np.float32)
    norm = (np.float32(1) / marg[:, -1])[:, None]
    cond = (cond * norm[:, :, None]).astype(np.float64)
    marg = (marg * norm).astype(np.float64)
    dn = (data * norm[:, :, None]).astype(np.float64)
    t = np.empty((s, ny - 1, nx - 1, 9))
    t[..., 0] = dn[:, :-1, :-1]
    t[..., 1] = dn[:, :-1, 1:]
    t[..., 2] = dn[:, 1:, :-1]
    t[..., 3] = dn[:, 1:, 1:]
    t[..., 4] = cond[:, :-1, :-1]
    t[..., 5] = cond[:, 1:, :-1]
    t[..., 6] = cond[:, :-1, -1][:, :, None]
    t[..., 7] = cond[:, 1:, -1][:, :, None]
    t[..., 8] = marg[:, :-1][:, :, None]
    return t.reshape(-1, 9)


def _warp_to_s(t, fx, fy):
    """The continuous Marginal2D warp's inverse at (fx, fy) within patches whose rows of
    _continuous_warp_table are t (N, 9): (s x, s y, zero rows, the warp's density there in index
    units: d s / d(x, y) over the index square)."""
    v00, v10, v01, v11, cc0, cc1, r0, r1, m0 = t.T
    gy = 1.0 - fy
    row_total = gy * r0 + fy * r1
    zero = row_total == 0  # a zero row: 0/0 (see RGLMaterial's docstring)
    if zero.any():
        row_total = np.where(zero, 1.0, row_total)
    c0 = gy * v00 + fy * v01
    c1 = gy * v10 + fy * v11
    sx = (fx * (c0 + 0.5 * fx * (c1 - c0)) + gy * cc0 + fy * cc1) / row_total
    sy = fy * (r0 + 0.5 * fy * (r1 - r0)) + m0
    return sx, sy, zero, (1.0 - fx) * c0 + fx * c1


def _corner_table(data):
    """(S, ny, nx, C) -> (S * (ny-1) * (nx-1), 4 * C): corners v00, v10, v01, v11 of every patch."""
    d = np.asarray(data, dtype=np.float64)
    s, ny, nx, c = d.shape
    t = np.stack([d[:, :-1, :-1], d[:, :-1, 1:], d[:, 1:, :-1], d[:, 1:, 1:]], axis=3)
    return np.ascontiguousarray(t.reshape(-1, 4 * c))


def _patch(u, n):
    """Clamp u to [0,1], find its patch among n-1 and the position in it (Mitsuba's rule)."""
    x = np.minimum(np.maximum(u, 0.0), 1.0) * (n - 1)
    i = np.minimum(x.astype(np.intp), n - 2)
    return i, x - i


def _bilinear_weights(fx, fy):
    """(N, 4) weights of the corners v00, v10, v01, v11."""
    gx, gy = 1.0 - fx, 1.0 - fy
    return np.stack([gx * gy, fx * gy, gx * fy, fx * fy], axis=1)


def _interval(values, x):
    """Mitsuba's find_interval: the largest i in [0, n-2] with values[i] < x."""
    if len(values) > 16:
        return np.clip(np.searchsorted(values, x, side="left") - 1, 0, len(values) - 2)
    i = np.zeros(np.shape(x), np.intp)
    for v in values[1:-1]:
        i += x > v
    return i


def _param_weights(values, x):
    """Linear interpolation in a parameter table: [(index, weight), ...] (Mitsuba's rule)."""
    if len(values) == 1:
        return [(0, 1.0)]
    i = _interval(values, x)
    p0, p1 = np.take(values, i), np.take(values, i + 1)
    w1 = np.minimum(np.maximum((x - p0) / (p1 - p0), 0.0), 1.0)
    return [(i, 1.0 - w1), (i + 1, w1)]


def _elevation(x, y, z):
    """Polar angle of unit vectors, accurate near the pole (as Mitsuba computes it)."""
    dist = np.sqrt(x * x + y * y + (z - 1.0) ** 2)
    return 2.0 * np.arcsin(np.minimum(0.5 * dist, 1.0))


def _theta2u(theta):
    return np.sqrt(theta * (2.0 / np.pi))


def _phi2u(phi):
    return (phi + np.pi) * (0.5 / np.pi)


def _grid_lookup(grid, ux, uy):
    """Bilinear, unnormalized lookup of a 2D table at unit-square coordinates
    (what Mitsuba's Marginal2D<0> eval returns with normalize=false)."""
    ny, nx = grid.shape
    px, fx = _patch(ux, nx)
    py, fy = _patch(uy, ny)
    flat = grid.ravel()
    i = py * nx + px
    gx = 1.0 - fx
    return ((1.0 - fy) * (gx * np.take(flat, i) + fx * np.take(flat, i + 1))
            + fy * (gx * np.take(flat, i + nx) + fx * np.take(flat, i + nx + 1)))


class RGLMaterial(Material):
    """An RGL measured BSDF; `eval` matches Mitsuba 3's `measured` plugin (RGB) / cos(theta_o).

    eval(wi, wo), for unit vectors in the local frame:
      1. zero unless wi.z > 0 and wo.z > 0;
      2. anisotropic files whose phi_i table covers 1/2 or 1/4 of the circle: mirror wi
         and wo so that wi lands in the measured range (Mitsuba's "reduction");
      3. half vector m = normalize(wi + wo); polar angles by the stable 2 asin(|d - z|/2);
         unit-square coordinates u = (sqrt(2 theta / pi), (phi + pi) / 2 pi), where the
         azimuth of m is taken relative to phi_i for isotropic files, and wrapped to [0, 1);
      4. s = vndf.invert(u_m): the inverse of the continuous Marginal2D warp (bilinear
         density, CDFs integrated exactly), its tables linearly interpolated across
         (phi_i, theta_i); the per-slice normalizations and CDFs are precomputed;
      5. rgb = bilinear lookup of the `rgb` table at s, interpolated across (phi_i, theta_i);
      6. if the file's jacobian flag is set: rgb *= ndf(u_m) / (4 sigma(u_wi)) (bilinear,
         unnormalized lookups);
      7. f = rgb / cos(theta_o) (Mitsuba's eval includes the cosine, ours does not).
    A single incident direction (wi of shape (3,)) takes a faster path that interpolates
    the tables for that wi once.

    Negative values: the `rgb` tables of 7 of the 10 shared files hold negative entries
    (down to -0.62 on chm_mint, 21 % of its entries; `luminance` of ilm_solo_m_68 dips to
    -4e-10). They are not just noise: chm_mint's red channel is negative across its whole
    specular peak (f about -120 at 30 deg; a saturated mint outside the RGB gamut), while
    its luminance stays positive. Like Mitsuba, eval returns them as the data says
    (samplers clamp through `Material.target`).

    Zero rows: at theta_i = 90 deg the `vndf` tables of the shared files are zero for the
    half-vector azimuths facing away from wi (rows 0-31 and 96-127 of 128). Where the
    interpolated row of the warp is zero everywhere, the inverse CDF is 0/0 and Mitsuba
    returns NaN; eval returns 0 there (no microfacets, no reflection). With the shared
    files this does not arise for wi.z > 0: below 90 deg the neighbouring slice keeps the
    rows positive, and for wi within 1e-7 rad of grazing (weight 1 on the 90 deg slice)
    the reachable half vectors (relative azimuth within +-90 deg) avoid the zero rows.

    Isotropic files (one phi_i entry): `sigma` is looked up at the absolute azimuth of wi,
    as in Mitsuba (the shared files hold two equal rows, so this does not matter). Mitsuba
    3.9.1 leaves its `m_reduction` member uninitialized for isotropic files: some runs rotate
    wi and wo by 180 deg when wi.y > 0, which changes only that sigma lookup. We never
    rotate. Files with two phi_i entries are treated like Mitsuba does (relative azimuth of
    m, tables interpolated across phi_i) and are not `isotropic`.

    Directions are assumed to be unit vectors (as in Mitsuba); they are not renormalized.
    """

    def __init__(self, path):
        self.path = Path(path)
        f = read_tensor_file(self.path)
        self.name = self.path.stem
        self.description = bytes(f["description"]).decode("utf-8", "replace") \
            if "description" in f and f["description"].dtype == np.uint8 else ""
        self.theta_i = f["theta_i"].astype(np.float64)
        self.phi_i = f["phi_i"].astype(np.float64)
        n_phi, n_theta = len(self.phi_i), len(self.theta_i)
        self.isotropic = n_phi == 1
        # Mitsuba treats up to two phi_i entries as isotropic (azimuth of m relative to wi).
        self._relative_phi = n_phi <= 2
        self._reduction = 1
        if not self._relative_phi:
            self._reduction = int(np.rint(2 * np.pi / (f["phi_i"][-1] - f["phi_i"][0])))
        self._jacobian = bool(f["jacobian"][0])
        self._slices = n_phi * n_theta

        vndf = f["vndf"]
        self._vndf_shape = vndf.shape[2:]  # (n phi_m, n theta_m)
        self._vndf = _continuous_warp_table(vndf.reshape(self._slices, *self._vndf_shape))
        rgb = f["rgb"]
        self._rgb_shape = rgb.shape[3:]
        self._rgb = _corner_table(np.moveaxis(rgb.reshape(self._slices, 3, *self._rgb_shape), 1, -1))
        self._ndf = f["ndf"].astype(np.float64)
        self._sigma = f["sigma"].astype(np.float64)
        self._incidents = {}       # _incident per wi (its bytes), read-only once made
        self._vndf_file = vndf
        self._stored_warp = self._stored_table = None      # made on first use (carried tables)
        with open(self.path, "rb") as fh:
            self._sha256 = hashlib.sha256(fh.read()).hexdigest()

    def fingerprint(self):
        return self._sha256

    @property
    def measured_theta_i(self):
        return self.theta_i

    @property
    def phi_period(self):
        """pi when wi is mirrored into a half or quarter circle (both flip under a rotation by pi)."""
        return np.pi if self._reduction in (2, 4) else 2.0 * np.pi

    def eval(self, wi, wo):
        single = np.ndim(wi) == 1
        wi, wo = as_dirs(wi, wo)
        n = len(wo)
        out = np.zeros((n, 3))
        incident = None
        if single and n >= 1024:
            if wi[0, 2] <= 0:
                return out
            key = wi[0].tobytes()
            incident = self._incidents.get(key)
            if incident is None:
                incident = self._incident(wi[0])
                if len(self._incidents) >= 16:      # the baker evaluates one wi ~20 times in a row
                    self._incidents.clear()
                self._incidents[key] = incident
            fast = self._eval_c(wo, incident)
            if fast is not None:
                return fast
        for start in range(0, n, CHUNK):
            sl = slice(start, min(start + CHUNK, n))
            out[sl] = self._eval_chunk(wi[sl], wo[sl], incident)
        return out

    @property
    def stored_warp(self):
        """The file's `vndf` warp data as a sampler that carries directions along the file's
        coordinates (WarpedCoords stored=True) keeps it: float16, each slice over its maximum (the
        warp normalizes every slice, so the scale changes nothing), a nonzero value at least
        float16's smallest (the warp's support stays the file's). (S, ny, nx) float16: half the
        bytes of the file's float32, the same carry (measured on chm_mint's 2 MB tables: rv within
        1 % of float32's at seven incident angles)."""
        if self._stored_warp is None:
            vndf = self._vndf_file.reshape(self._slices, *self._vndf_shape).astype(np.float64)
            top = vndf.reshape(self._slices, -1).max(axis=1)
            rel = vndf / np.where(top > 0, top, 1.0)[:, None, None]
            tiny = np.finfo(np.float16).smallest_subnormal
            self._stored_warp = np.where(rel > 0, np.maximum(rel, float(tiny)), 0.0).astype(np.float16)
        return self._stored_warp

    @property
    def warp_nbytes(self):
        """The bytes of stored_warp: what a carrying sampler reads besides its tables."""
        return 2 * self._slices * self._vndf_shape[0] * self._vndf_shape[1]

    def _stored_warp_table(self):
        """_continuous_warp_table of stored_warp, (S, patches, 9)."""
        if self._stored_table is None:
            self._stored_table = _continuous_warp_table(self.stored_warp.astype(np.float32)).reshape(
                self._slices, -1, 9)
        return self._stored_table

    def _eval_c(self, wo, incident):
        """eval for one wi in C (bake/maths/_tables_c.c ft_rgl_eval: the numpy _eval_chunk
        transcribed, to a few ulps), or None without the C library."""
        from ..maths import fasttables
        signs = incident["signs"] or (1.0, 1.0)
        params = np.array([*incident["wi"], *signs, incident["theta_i"], incident["phi_i"],
                           float(self._relative_phi), float(self._jacobian), incident["sigma"]], np.float64)
        return fasttables.rgl_eval(params, incident["vndf"], self._vndf_shape, incident["rgb"], self._rgb_shape,
                                   self._ndf, wo)

    def _mirror(self, wix, wiy):
        """Signs for the x and y components (Mitsuba's symmetry reduction), or None."""
        if self._reduction < 2:
            return None
        sy = np.where(np.signbit(wiy), 1.0, -1.0)
        sx = np.where(np.signbit(wix), 1.0, -1.0) if self._reduction == 4 else sy
        return sx, sy

    def _combos(self, phi_i, theta_i):
        """[(slice index, weight)] over the (phi_i, theta_i) grid (scalars or arrays)."""
        n_theta = len(self.theta_i)
        return [(ip * n_theta + it, wp * wt)
                for ip, wp in _param_weights(self.phi_i, phi_i)
                for it, wt in _param_weights(self.theta_i, theta_i)]

    def _incident(self, w):
        """Everything that depends on wi alone, for one wi: interpolated tables."""
        w = np.array(w, dtype=np.float64)
        signs = self._mirror(w[0], w[1])
        if signs is not None:
            w[0] *= signs[0]
            w[1] *= signs[1]
        theta_i = float(_elevation(w[0], w[1], w[2]))
        phi_i = float(np.arctan2(w[1], w[0]))
        vndf = self._vndf.reshape(self._slices, -1, 9)
        rgb = self._rgb.reshape(self._slices, -1, 12)
        vt = rt = None
        for s, wt in self._combos(phi_i, theta_i):
            vt = vndf[s] * wt if vt is None else vt + vndf[s] * wt
            rt = rgb[s] * wt if rt is None else rt + rgb[s] * wt
        sigma = float(_grid_lookup(self._sigma, _theta2u(theta_i), _phi2u(phi_i)))
        return dict(wi=w, signs=signs, theta_i=theta_i, phi_i=phi_i, vndf=vt, rgb=rt, sigma=sigma)

    def _eval_chunk(self, wi, wo, incident):
        out = np.zeros((len(wo), 3))
        active = wo[:, 2] > 0
        if incident is None:
            active &= wi[:, 2] > 0
        if not active.all():
            if not active.any():
                return out
            wo = wo[active]
            if incident is None:
                wi = wi[active]
        wox, woy, woz = wo[:, 0], wo[:, 1], wo[:, 2]
        if incident is None:
            wix, wiy, wiz = wi[:, 0], wi[:, 1], wi[:, 2]
            signs = self._mirror(wix, wiy)
            if signs is not None:
                wix, wiy = wix * signs[0], wiy * signs[1]
        else:
            wix, wiy, wiz = incident["wi"]
            signs = incident["signs"]
        if signs is not None:
            wox, woy = wox * signs[0], woy * signs[1]

        # 3. Half vector and unit-square coordinates.
        mx, my, mz = wix + wox, wiy + woy, wiz + woz
        inv = 1.0 / np.sqrt(mx * mx + my * my + mz * mz)
        mx, my, mz = mx * inv, my * inv, mz * inv
        if incident is None:
            theta_i = _elevation(wix, wiy, wiz)
            phi_i = atan2(wiy, wix)
        else:
            theta_i, phi_i = incident["theta_i"], incident["phi_i"]
        um_x = _theta2u(_elevation(mx, my, mz))
        phi_m = atan2(my, mx)
        um_y = _phi2u(phi_m - phi_i if self._relative_phi else phi_m)
        um_y -= np.floor(um_y)

        # 4. Invert the VNDF warp at u_m.
        ny, nx = self._vndf_shape
        px, fx = _patch(um_x, nx)
        py, fy = _patch(um_y, ny)
        patch = py * (nx - 1) + px
        if incident is None:
            combos = self._combos(phi_i, theta_i)
            t = self._gather(self._vndf, combos, patch, (nx - 1) * (ny - 1))
        else:
            t = np.take(incident["vndf"], patch, axis=0)
        sx, sy, zero, _ = _warp_to_s(t, fx, fy)

        # 5. RGB at the warped position.
        ry, rx = self._rgb_shape
        qx, hx = _patch(sx, rx)
        qy, hy = _patch(sy, ry)
        patch = qy * (rx - 1) + qx
        if incident is None:
            g = self._gather(self._rgb, combos, patch, (rx - 1) * (ry - 1))
        else:
            g = np.take(incident["rgb"], patch, axis=0)
        rgb = np.einsum("nk,nkc->nc", _bilinear_weights(hx, hy), g.reshape(-1, 4, 3))

        # 6. NDF / (4 sigma), 7. no cosine.
        scale = 1.0 / woz
        if self._jacobian:
            if incident is None:
                sigma = _grid_lookup(self._sigma, _theta2u(theta_i), _phi2u(phi_i))
            else:
                sigma = incident["sigma"]
            scale *= _grid_lookup(self._ndf, um_x, um_y) / (4.0 * sigma)
        if zero.any():
            scale[zero] = 0.0
        rgb *= scale[:, None]
        out[active] = rgb
        return out

    @staticmethod
    def _gather(table, combos, patch, npatch):
        """Rows of a per-slice table at `patch`, interpolated across slices."""
        acc = None
        for s, w in combos:
            rows = np.take(table, s * npatch + patch, axis=0)
            if not (np.isscalar(w) and w == 1.0):
                rows *= np.asarray(w)[..., None]
            acc = rows if acc is None else acc.__iadd__(rows)
        return acc


class WarpedCoords:
    """An isotropic RGL file's own coordinates s in [0, 1]², where eval reads its `rgb` table
    (step 4), both ways, with d omega_o / d s, for one incident direction per sample (wi (N, 3) or
    one (3,)).

    The file blends its measured theta_i slices at fixed s (rgb and the warp's tables alike), so a
    feature of f·cos that moves with theta_i over wo or the half vector stays put over s: blending
    two incident angles' targets over s loses far less between them (scripts/blend_probe.py).
    from_s inverts the warp: the marginal row by its CDF, then the column within the row, each
    position within its patch the root of the bilinear density's quadratic CDF; to_s is eval's
    step 4. The half vector follows from u_m = (sqrt(2 theta_h / pi), (phi_h - phi_i + pi) / 2 pi)
    and wo = reflect(wi, h): d omega_o / d s = 4 (wi . h) sin theta_h (pi u_x) (2 pi) / p(u_m), p
    the warp's density. Some s give no direction above the horizon (h facing away from wi, or
    wo below it): from_s returns them with wo_z <= 0 and jac 0. A sample's patches are its two
    theta_i slices' blended as eval blends them (_incident), patch by patch as they are read.

    stored=True: the warp of the file's stored_warp (float16), what a carrying sampler keeps.
    backend "auto": the C fast path where it loads (fasttables.warp_to_s / warp_from_s, the same
    formulas to a few ulps), "numpy": this reference only.

    horizon=True: s_x over its value at the horizon in the row s_y (s'_x = 1 is the horizon at
    every wi; wi.h > 0 wherever wo is above it), so that directions carried at fixed s' from
    one wi to another stay above the horizon; d omega / d s' = d omega / d s times that value.
    Along the half vector's azimuth delta from wi's, the horizon is at theta_h =
    atan2(cos theta_i, -sin theta_i cos delta) / 2 (2 cos theta_h (wi . h) = cos theta_i).
    """

    def __init__(self, material, horizon=False, stored=False, backend="auto"):
        if not material.isotropic:
            raise FlowBSDFError("WarpedCoords: isotropic RGL files only")
        self.horizon, self.backend = horizon, backend
        self.ny, self.nx = material._vndf_shape
        table = material._stored_warp_table() if stored else material._vndf.reshape(material._slices, -1, 9)
        self.tables = np.ascontiguousarray(table.reshape(material._slices, self.ny - 1, self.nx - 1, 9))
        self.theta_i = np.ascontiguousarray(material.theta_i, np.float64)

    def _incident(self, wi, n):
        """Per sample: wi (n, 3), its phi_i, and a function (py, px) -> the blended patches' rows."""
        wi = np.broadcast_to(np.asarray(wi, np.float64), (n, 3))
        weights = _param_weights(self.theta_i, _elevation(wi[:, 0], wi[:, 1], wi[:, 2]))
        (s0, w0), (s1, w1) = weights if len(weights) == 2 else (weights[0], (0, 0.0))
        w0, w1 = (np.broadcast_to(np.asarray(w, np.float64), (n,))[:, None] for w in (w0, w1))

        def patch(py, px):
            return self.tables[s0, py, px] * w0 + self.tables[s1, py, px] * w1
        return wi, atan2(wi[:, 1], wi[:, 0]), patch

    def _jac(self, wi, u_x, h, density):
        """d omega_o / d s at half vectors h (u_m x = u_x), the warp's density (index units) there."""
        theta_h = u_x * u_x * (0.5 * np.pi)
        cos_ih = h[:, 0] * wi[:, 0] + h[:, 1] * wi[:, 1] + h[:, 2] * wi[:, 2]
        d_omega_d_u = 4.0 * np.abs(cos_ih) * np.sin(theta_h) * (np.pi * u_x) * (2.0 * np.pi)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(density > 0, d_omega_d_u / (density * (self.nx - 1) * (self.ny - 1)), np.inf)

    def _rim(self, wi, patch, py, fy):
        """s_x at the horizon in rows (py, fy): 1 without `horizon`."""
        if not self.horizon:
            return np.ones_like(fy)
        cos_i = wi[:, 2]
        sin_i = np.sqrt(np.maximum(1.0 - cos_i * cos_i, 0.0))
        delta = ((py + fy) / (self.ny - 1)) * (2.0 * np.pi) - np.pi
        theta_h = 0.5 * atan2(cos_i, -sin_i * np.cos(delta))
        px, fx = _patch(_theta2u(theta_h), self.nx)
        rim = _warp_to_s(patch(py, px), fx, fy)[0]
        return np.clip(rim, 1e-300, 1.0)

    def to_s(self, wi, wo):
        """(s (N, 2), d omega_o / d s: inf where the warp has no density)."""
        wo = np.atleast_2d(np.asarray(wo, np.float64))
        if self.backend == "auto":
            from ..maths import fasttables
            fast = fasttables.warp_to_s(self, wi, wo)
            if fast is not None:
                return fast
        wi, phi_i, patch = self._incident(wi, len(wo))
        h = wi + wo
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        u_x = _theta2u(_elevation(h[:, 0], h[:, 1], h[:, 2]))
        u_y = _phi2u(atan2(h[:, 1], h[:, 0]) - phi_i)
        u_y -= np.floor(u_y)
        px, fx = _patch(u_x, self.nx)
        py, fy = _patch(u_y, self.ny)
        sx, sy, zero, density = _warp_to_s(patch(py, px), fx, fy)
        rim = self._rim(wi, patch, py, fy)
        # sx / rim exceeds 1 only by rounding, for wo on the horizon itself
        return (np.stack([np.minimum(sx / rim, 1.0), sy], axis=-1),
                self._jac(wi, u_x, h, np.where(zero, 0.0, density)) * rim)

    @staticmethod
    def _root(slope_half, start, d):
        """x in [0, 1] with start x + slope_half x² = d, stably (d >= 0)."""
        root = np.sqrt(np.maximum(start * start + 4.0 * slope_half * d, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.clip(np.nan_to_num(2.0 * d / (start + root)), 0.0, 1.0)

    @staticmethod
    def _last_at_most(n, value, x):
        """Per sample, the last i in [0, n - 1] with value(i) <= x (0 when none): a bisection over
        values that rise with i (the same index as counting them)."""
        lo = np.zeros(len(x), np.intp)
        hi = np.where(value(lo) <= x, n, 0)
        while np.any(busy := hi - lo > 1):
            mid = (lo + hi) // 2
            below = busy & (value(mid) <= x)
            lo = np.where(below, mid, lo)
            hi = np.where(busy & ~below, mid, hi)
        return lo

    def from_s(self, wi, s):
        """(wo (N, 3), d omega_o / d s); s that reach no direction: wo_z <= 0, jac 0."""
        s = np.atleast_2d(np.asarray(s, np.float64))
        if self.backend == "auto":
            from ..maths import fasttables
            fast = fasttables.warp_from_s(self, wi, s)
            if fast is not None:
                return fast
        wi, phi_i, patch = self._incident(wi, len(s))
        first = np.zeros(len(s), np.intp)
        py = self._last_at_most(self.ny - 1, lambda i: patch(i, first)[:, 8], s[:, 1])
        row = patch(py, first)
        r0, r1 = row[:, 6], row[:, 7]
        fy = self._root(0.5 * (r1 - r0), r0, s[:, 1] - row[:, 8])
        gy = 1.0 - fy
        rim = self._rim(wi, patch, py, fy)
        target = s[:, 0] * rim * (gy * r0 + fy * r1)

        def start(px):          # the conditional CDF at patch px's left edge
            v = patch(py, px)
            return gy * v[:, 4] + fy * v[:, 5]
        px = self._last_at_most(self.nx - 1, start, target)
        v = patch(py, px)
        c0, c1 = gy * v[:, 0] + fy * v[:, 2], gy * v[:, 1] + fy * v[:, 3]
        fx = self._root(0.5 * (c1 - c0), c0, target - (gy * v[:, 4] + fy * v[:, 5]))
        u_x, u_y = (px + fx) / (self.nx - 1), (py + fy) / (self.ny - 1)
        theta_h, phi_h = u_x * u_x * (0.5 * np.pi), u_y * (2.0 * np.pi) - np.pi + phi_i
        h = np.stack([np.sin(theta_h) * np.cos(phi_h), np.sin(theta_h) * np.sin(phi_h), np.cos(theta_h)], axis=-1)
        cos_ih = h[:, 0] * wi[:, 0] + h[:, 1] * wi[:, 1] + h[:, 2] * wi[:, 2]
        wo = 2.0 * cos_ih[:, None] * h - wi
        reached = (cos_ih > 0) & (wo[:, 2] > 0)
        wo[~reached, 2] = np.minimum(wo[~reached, 2], 0.0)
        jac = self._jac(wi, u_x, h, (1.0 - fx) * c0 + fx * c1) * rim
        return wo, np.where(reached & np.isfinite(jac), jac, 0.0)

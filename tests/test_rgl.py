"""RGL `.bsdf` reader and RGLMaterial: strict parsing, eval against Mitsuba 3's `measured`
plugin, negative values and zero rows. (Reciprocity is not expected of measured data.)"""
import hashlib
import struct

import numpy as np
import pytest

from bake.errors import FlowBSDFError
from bake.maths.geometry import luminance, normalize, reflect, spherical_dir
from bake.materials import open_material
from bake.materials.rgl import RGLMaterial, read_tensor_file, write_tensor_file  # noqa: F401 (test_bad_inputs imports it from here)
from conftest import RGL_FILES

# ---------------------------------------------------------------- helpers

def synthetic_fields(phi_i=(0.0,), n_theta=5, n_vndf=16, n_rgb=8, seed=0):
    """A small random RGB RGL material (positive vndf, rgb partly negative)."""
    rng = np.random.default_rng(seed)
    n_phi = len(phi_i)
    f32 = np.float32
    sigma_row = rng.uniform(0.2, 1.0, n_vndf)
    return {
        "description": np.frombuffer(b"synthetic test material", np.uint8),
        "phi_i": np.asarray(phi_i, f32),
        "theta_i": np.linspace(0, np.pi / 2, n_theta).astype(f32),
        # Equal rows: Mitsuba 3.9.1 may rotate isotropic inputs (uninitialized m_reduction),
        # which only changes the sigma lookup when its rows differ.
        "sigma": np.stack([sigma_row, sigma_row]).astype(f32),
        "ndf": rng.uniform(0.0, 3.0, (2, n_vndf)).astype(f32),
        "vndf": rng.uniform(0.1, 1.0, (n_phi, n_theta, n_vndf, n_vndf)).astype(f32),
        "luminance": rng.uniform(0.1, 1.0, (n_phi, n_theta, n_rgb, n_rgb)).astype(f32),
        "rgb": rng.uniform(-0.2, 1.0, (n_phi, n_theta, 3, n_rgb, n_rgb)).astype(f32),
        "jacobian": np.array([1], np.uint8),
    }


def field_entries(buf):
    """{name: byte positions of its ndim, dtype, offset and shape} in a tensor file header."""
    (n,) = struct.unpack_from("<I", buf, 14)
    pos, out = 18, {}
    for _ in range(n):
        (length,) = struct.unpack_from("<H", buf, pos)
        name = buf[pos + 2:pos + 2 + length].decode()
        pos += 2 + length
        ndim, code, offset = struct.unpack_from("<HBQ", buf, pos)
        out[name] = dict(ndim_at=pos, code_at=pos + 2, offset_at=pos + 3, shape_at=pos + 11,
                         ndim=ndim, offset=offset)
        pos += 11 + 8 * ndim
    return out, pos


def relative_error(ours, ref):
    """Per pair: max channel error over the largest channel magnitude of the reference."""
    scale = np.abs(ref).max(axis=1)
    err = np.abs(ours - ref).max(axis=1)
    return np.where(scale > 0, err / np.where(scale > 0, scale, 1.0), np.where(err > 0, np.inf, 0.0))


def random_pairs(n, rng, max_theta_deg=89.0):
    """wi up to max_theta_deg (some exactly there); wo: 1/3 uniform, 2/3 near the mirror direction."""
    theta = np.radians(rng.uniform(0.0, max_theta_deg, n))
    theta[:n // 20] = np.radians(max_theta_deg)
    wi = spherical_dir(theta, rng.uniform(-np.pi, np.pi, n))
    wo = spherical_dir(np.arccos(rng.uniform(0.0, 1.0, n)), rng.uniform(-np.pi, np.pi, n))
    k = n // 3
    spread = rng.choice([0.003, 0.02, 0.1], n - k)[:, None]
    near = wi[k:] * [-1.0, -1.0, 1.0] + rng.normal(0.0, 1.0, (n - k, 3)) * spread
    near[:, 2] = np.abs(near[:, 2]) + 1e-3
    wo[k:] = normalize(near)
    return wi, wo


@pytest.fixture(scope="module")
def mi():
    mitsuba = pytest.importorskip("mitsuba")
    mitsuba.set_variant("scalar_rgb")
    return mitsuba


def mitsuba_f(mi, path, wi, wo):
    """Mitsuba's measured eval divided by cos(theta_o): f without the cosine."""
    bsdf = mi.load_dict({"type": "measured", "filename": str(path)})
    ctx, si = mi.BSDFContext(), mi.SurfaceInteraction3f()
    out = np.empty((len(wo), 3))
    for k in range(len(wo)):
        si.wi = mi.Vector3f(*wi[k])
        out[k] = np.array(bsdf.eval(ctx, si, mi.Vector3f(*wo[k])))
    return out / wo[:, 2:3]


# ---------------------------------------------------------------- (a) vs Mitsuba

@pytest.mark.parametrize("name", RGL_FILES)
def test_eval_matches_mitsuba(name, rgl, mi):
    path = rgl(name)
    mat = RGLMaterial(path)
    wi, wo = random_pairs(2000, np.random.default_rng(sum(name.encode())))
    ref = mitsuba_f(mi, path, wi, wo)
    ours = mat.eval(wi, wo)
    assert ours.shape == (2000, 3) and ours.dtype == np.float64
    assert np.isfinite(ours).all()
    assert (np.abs(ref).max(axis=1) > 0).mean() > 0.5  # the test is not vacuous
    err = relative_error(ours, ref)
    assert np.median(err) < 1e-4, f"{name}: median relative error {np.median(err):.3g}"
    assert np.quantile(err, 0.99) < 1e-3, f"{name}: 99th percentile {np.quantile(err, 0.99):.3g}"


@pytest.mark.parametrize("phi_i", [
    (0.0,),                                    # isotropic
    tuple(np.linspace(-np.pi, 0.0, 5)),        # half circle measured: mirror by y
    tuple(np.linspace(-np.pi, -np.pi / 2, 4)),  # quarter: mirror by x and y
    tuple(np.linspace(-np.pi, np.pi, 9)),      # full circle
], ids=["isotropic", "aniso-half", "aniso-quarter", "aniso-full"])
def test_synthetic_matches_mitsuba(phi_i, tmp_path, mi):
    path = write_tensor_file(tmp_path / "synthetic.bsdf", synthetic_fields(phi_i))
    mat = RGLMaterial(path)
    assert mat.isotropic == (len(phi_i) == 1)
    rng = np.random.default_rng(7)
    wi = spherical_dir(np.arccos(rng.uniform(0.02, 1, 400)), rng.uniform(-np.pi, np.pi, 400))
    wo = spherical_dir(np.arccos(rng.uniform(0.02, 1, 400)), rng.uniform(-np.pi, np.pi, 400))
    err = relative_error(mat.eval(wi, wo), mitsuba_f(mi, path, wi, wo))
    assert np.median(err) < 1e-5 and err.max() < 1e-3


# ---------------------------------------------------------------- basic behaviour

def test_material_basics(rgl):
    path = rgl("chm_mint_rgb")
    mat = open_material(path)
    assert isinstance(mat, RGLMaterial)
    assert mat.name == "chm_mint_rgb" and mat.isotropic
    assert mat.fingerprint() == hashlib.sha256(path.read_bytes()).hexdigest()
    fields = read_tensor_file(path)
    assert fields["vndf"].shape == (1, 8, 128, 128) and fields["rgb"].shape == (1, 8, 3, 32, 32)

    rng = np.random.default_rng(1)
    wi, wo = random_pairs(3000, rng)
    # One wi as (3,) (the fast path that interpolates the tables once) equals it repeated; with
    # >= 1024 directions it runs in C, whose libm asin/atan2 round differently from numpy's:
    # ~1e-9 relative on this sharp file (test_c_eval_matches_numpy: the numpy path alone).
    one = mat.eval(wi[0], wo)
    np.testing.assert_allclose(one, mat.eval(np.repeat(wi[:1], len(wo), 0), wo), rtol=1e-8, atol=0)
    np.testing.assert_allclose(mat.eval(wi[0], wo[:5]), one[:5], rtol=1e-12, atol=0)
    # Zero below the surface, on either side.
    below = wo * [1, 1, -1]
    assert not mat.eval(wi, below).any()
    assert not mat.eval(wi * [1, 1, -1], wo).any()
    assert not mat.eval(wi[0] * [1, 1, -1], wo).any()
    # Rotating both directions about the normal changes nothing (isotropic file).
    rot = np.array([[0.6, -0.8, 0], [0.8, 0.6, 0], [0, 0, 1]])
    np.testing.assert_allclose(mat.eval(wi @ rot.T, wo @ rot.T), mat.eval(wi, wo), rtol=1e-6, atol=1e-9)


def test_specular_peak_is_bright(rgl):
    """chm_mint is chrome-like: f at the mirror direction dwarfs f away from it.

    Its red channel is strongly negative at the peak (about -120 at 30 deg, Mitsuba agrees):
    the saturated mint lies outside the RGB gamut. Luminance stays positive."""
    mat = RGLMaterial(rgl("chm_mint_rgb"))
    wi = spherical_dir(np.radians(30.0), 0.0)
    peak = mat.eval(wi, wi * [-1, -1, 1])[0]
    off = mat.eval(wi, spherical_dir(np.radians(60.0), np.pi))[0]
    assert peak[0] < -50 and peak[1:].min() > 100 * np.abs(off).max()
    assert luminance(peak) > 100 * np.abs(off).max()


# ---------------------------------------------------------------- (b) malformed files

def _set(buf, at, fmt, value):
    out = bytearray(buf)
    struct.pack_into(fmt, out, at, value)
    return bytes(out)


def _malformed(buf):
    entries, header_end = field_entries(buf)
    vndf, rgb = entries["vndf"], entries["rgb"]
    return {
        "empty": (b"", "empty"),
        "cut-in-magic": (buf[:6], "truncated"),
        "cut-in-header": (buf[:16], "truncated"),
        "cut-in-table": (buf[:40], "truncated"),
        "cut-end-of-table": (buf[:header_end - 3], "truncated"),
        "cut-in-data": (buf[:vndf["offset"] + 1000], "truncated"),
        "cut-last-byte": (buf[:-1], "truncated"),
        "png": (b"\x89PNG\r\n\x1a\n" + bytes(200), "magic"),
        "bad-magic": (b"tensor_fil3\0" + buf[12:], "magic"),
        "version-2": (buf[:12] + bytes([2, 0]) + buf[14:], "version"),
        "field-count": (_set(buf, 14, "<I", 0xFFFFFFFF), "truncated"),
        "dtype-code": (_set(buf, vndf["code_at"], "<B", 42), "dtype"),
        "ndim": (_set(buf, vndf["ndim_at"], "<H", 300), "ndim"),
        "huge-shape": (_set(buf, vndf["shape_at"], "<Q", 2 ** 40), "absurd"),
        "past-end": (_set(buf, rgb["shape_at"], "<Q", 2), "past end"),
        "offset-in-header": (_set(buf, vndf["offset_at"], "<Q", 20), "header"),
        "nan": (_set(buf, vndf["offset"] + 4 * 12345, "<f", float("nan")), "nan"),
        "inf": (_set(buf, rgb["offset"] + 4 * 77, "<f", float("inf")), "infinite"),
        "shape-mismatch": (_set(buf, rgb["shape_at"] + 8, "<Q", 7), "inconsistent"),
        "theta-uint32": (_set(buf, entries["theta_i"]["code_at"], "<B", 5), "dtype"),
    }


MALFORMED = ["empty", "cut-in-magic", "cut-in-header", "cut-in-table", "cut-end-of-table",
             "cut-in-data", "cut-last-byte", "png", "bad-magic", "version-2", "field-count",
             "dtype-code", "ndim", "huge-shape", "past-end", "offset-in-header", "nan", "inf",
             "shape-mismatch", "theta-uint32"]


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_file(case, rgl, tmp_path):
    data, word = _malformed(rgl("paper_white_rgb").read_bytes())[case]
    path = tmp_path / f"bad_{case}.bsdf"
    path.write_bytes(data)
    for load in (read_tensor_file, RGLMaterial, open_material):
        with pytest.raises(FlowBSDFError) as info:
            load(path)
        message = str(info.value)
        assert path.name in message and word in message.lower(), message
        assert info.value.path == str(path)


def _without(name):
    f = synthetic_fields()
    del f[name]
    return f


def _with(**changes):
    f = synthetic_fields()
    f.update(changes)
    return f


def _spectral():
    f = synthetic_fields()
    f["spectra"] = np.repeat(f.pop("rgb"), 2, axis=2)[:, :, :5]
    f["wavelengths"] = np.linspace(400, 700, 5).astype(np.float32)
    return f


def _zero_slice():
    f = synthetic_fields()
    f["vndf"][0, 2] = 0.0
    return f


STRUCTURE = {
    "missing-vndf": (lambda: _without("vndf"), "missing"),
    "missing-rgb": (lambda: _without("rgb"), "missing"),
    "missing-theta_i": (lambda: _without("theta_i"), "missing"),
    "spectral": (_spectral, "spectral"),
    "rgb-resolution": (lambda: _with(rgb=np.ones((1, 5, 3, 6, 6), np.float32)), "inconsistent"),
    "luminance-not-square": (lambda: _with(luminance=np.ones((1, 5, 8, 9), np.float32)), "inconsistent"),
    "vndf-theta-count": (lambda: _with(vndf=np.ones((1, 4, 16, 16), np.float32)), "inconsistent"),
    "vndf-float64": (lambda: _with(vndf=np.ones((1, 5, 16, 16))), "dtype"),
    "theta-decreasing": (lambda: _with(theta_i=np.linspace(1.5, 0, 5).astype(np.float32)), "increasing"),
    "zero-vndf-slice": (_zero_slice, "zero"),
    "zero-sigma": (lambda: _with(sigma=np.zeros((2, 16), np.float32)), "sigma"),
    "jacobian-type": (lambda: _with(jacobian=np.array([1.0], np.float32)), "jacobian"),
}


@pytest.mark.parametrize("case", list(STRUCTURE))
def test_not_an_rgl_material(case, tmp_path):
    make, word = STRUCTURE[case]
    path = write_tensor_file(tmp_path / f"{case}.bsdf", make())
    with pytest.raises(FlowBSDFError) as info:
        RGLMaterial(path)
    assert path.name in str(info.value) and word in str(info.value).lower(), str(info.value)
    read_tensor_file(path, rgl=False)  # a well-formed tensor file all the same


def test_synthetic_file_loads(tmp_path):
    path = write_tensor_file(tmp_path / "ok.bsdf", synthetic_fields())
    mat = RGLMaterial(path)
    assert mat.name == "ok" and mat.isotropic and mat.description == "synthetic test material"


# ---------------------------------------------------------------- (c) negative values, zero rows

def test_negative_data_passes_through(tmp_path, mi_optional):
    """Constant tables: f = rgb * ndf / (4 sigma) / cos(theta_o), negative as the data says."""
    f = synthetic_fields()
    f["rgb"][:] = np.array([-0.5, 0.1, -1.0], np.float32)[:, None, None]
    f["ndf"][:] = 2.0
    f["sigma"][:] = 1.0
    path = write_tensor_file(tmp_path / "negative.bsdf", f)
    mat = RGLMaterial(path)
    rng = np.random.default_rng(3)
    wi, wo = random_pairs(300, rng)
    value = mat.eval(wi, wo)
    expected = np.array([-0.5, 0.1, -1.0], np.float32).astype(float) * 2.0 / 4.0 / wo[:, 2:3]
    np.testing.assert_allclose(value, expected, rtol=1e-12)
    assert not mat.target(wi, wo).any()  # luminance < 0: samplers see zero
    if mi_optional is not None:
        np.testing.assert_allclose(mitsuba_f(mi_optional, path, wi[:50], wo[:50]), expected[:50], rtol=1e-5)


def test_real_negative_values_match_mitsuba(rgl, mi):
    """chm_mint's rgb table holds negative entries; eval returns them as Mitsuba does."""
    path = rgl("chm_mint_rgb")
    mat = RGLMaterial(path)
    wi, wo = random_pairs(20000, np.random.default_rng(11))
    value = mat.eval(wi, wo)
    negative = np.nonzero((value < 0).any(axis=1))[0][:300]
    assert len(negative) >= 50
    ref = mitsuba_f(mi, path, wi[negative], wo[negative])
    assert ((ref < 0) == (value[negative] < 0)).mean() > 0.99
    assert np.median(relative_error(value[negative], ref)) < 1e-4
    assert (mat.target(wi, wo) >= 0).all()


@pytest.fixture
def mi_optional():
    try:
        import mitsuba
    except ImportError:
        return None
    mitsuba.set_variant("scalar_rgb")
    return mitsuba


def test_zero_vndf_rows(tmp_path, mi_optional):
    """Where the interpolated VNDF row is zero the warp is 0/0: eval returns 0 (Mitsuba: NaN)."""
    f = synthetic_fields()
    f["vndf"][:, :, :4, :] = 0.0  # rows 0-3 of 16: half-vector azimuth ~ opposite wi
    path = write_tensor_file(tmp_path / "zero_rows.bsdf", f)
    mat = RGLMaterial(path)
    rng = np.random.default_rng(5)
    n = 200
    phi_i = rng.uniform(-np.pi, np.pi, n)
    wi = spherical_dir(np.radians(rng.uniform(0, 40, n)), phi_i)
    # Half vectors whose azimuth relative to wi falls in rows 0-1 (u < 1/15).
    m = spherical_dir(np.radians(rng.uniform(2, 15, n)), phi_i - np.pi + rng.uniform(0.05, 0.35, n))
    wo = reflect(wi, m)
    assert (wo[:, 2] > 0).all()
    value = mat.eval(wi, wo)
    assert np.isfinite(value).all() and not value.any()
    # Elsewhere the same file gives ordinary, finite, mostly nonzero values.
    wi2, wo2 = random_pairs(500, rng)
    other = mat.eval(wi2, wo2)
    assert np.isfinite(other).all() and (other != 0).any(axis=1).mean() > 0.5
    if mi_optional is not None:
        ref = mitsuba_f(mi_optional, path, wi[:20], wo[:20])
        assert (np.isnan(ref) | (ref == 0)).all()


@pytest.mark.parametrize("name", RGL_FILES)
def test_real_files_finite_at_grazing(name, rgl):
    """The shared files' zero VNDF rows (theta_i = 90 deg) never yield NaN, even at grazing wi."""
    mat = RGLMaterial(rgl(name))
    rng = np.random.default_rng(2)
    n = 4000
    wi = spherical_dir(np.pi / 2 - 10.0 ** rng.uniform(-9, -1, n), rng.uniform(-np.pi, np.pi, n))
    wo = spherical_dir(np.arccos(rng.uniform(0, 1, n)), rng.uniform(-np.pi, np.pi, n))
    assert np.isfinite(mat.eval(wi, wo)).all()


# ---------------------------------------------------------------- (d) the C eval (one wi per call)

@pytest.mark.parametrize("phi_i", [(0.0,), (0.0, np.pi), tuple(np.linspace(0, np.pi / 2, 3))])
def test_c_eval_matches_numpy(phi_i, tmp_path):
    """eval with one wi and >= 1024 directions runs ft_rgl_eval (the baker's hot loop): the same
    values as the numpy transcription to ~1e-9 (libm's asin/atan2 round differently from
    numpy's), zero rows and directions below the horizon included; isotropic, two-entry and
    symmetry-reduced phi_i files."""
    from bake.maths import fasttables
    if fasttables.load() is None:
        pytest.skip(fasttables.REASON)
    f = synthetic_fields(phi_i=phi_i)
    f["vndf"][:, :, :3, :] = 0.0       # zero rows: eval 0
    mat = RGLMaterial(write_tensor_file(tmp_path / "m.bsdf", f))
    rng = np.random.default_rng(2)
    for theta, phi in [(0.0, 0.0), (0.4, 2.5), (1.2, -0.7), (np.radians(89.0), 1.0)]:
        wi = spherical_dir(theta, phi)
        wo = spherical_dir(np.arccos(rng.uniform(-0.2, 1.0, 4000)), rng.uniform(-np.pi, np.pi, 4000))
        wo[:1000] = normalize(wi * [-1.0, -1.0, 1.0] + rng.normal(0.0, 0.02, (1000, 3)))
        fast = mat._eval_c(wo, mat._incident(wi))
        assert fast is not None
        ref = mat._eval_chunk(wi[None], wo, mat._incident(wi))
        np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=0)
        assert (fast[wo[:, 2] <= 0] == 0).all() and (ref == 0).all(axis=1).any() and (ref != 0).any()
        np.testing.assert_array_equal(mat.eval(wi, wo), fast)      # eval takes the C path


def test_c_eval_split_across_threads_is_one_call(tmp_path, monkeypatch):
    """The baker's C eval runs in a slice per core (fasttables._split): the same bytes as one
    call over all the directions, with uneven slices."""
    from bake.io import threads
    from bake.maths import fasttables
    if fasttables.load() is None:
        pytest.skip(fasttables.REASON)
    mat = RGLMaterial(write_tensor_file(tmp_path / "m.bsdf", synthetic_fields(phi_i=(0.0, np.pi))))
    rng = np.random.default_rng(5)
    wi = spherical_dir(0.9, 0.4)
    wo = spherical_dir(np.arccos(rng.uniform(-0.2, 1.0, 5001)), rng.uniform(-np.pi, np.pi, 5001))
    monkeypatch.setattr(threads, "workers", lambda: 1)
    one = mat._eval_c(wo, mat._incident(wi))
    monkeypatch.setattr(threads, "workers", lambda: 3)
    monkeypatch.setattr(fasttables, "MIN_SHARE", 1000)
    calls = []
    lib = fasttables.load()
    monkeypatch.setattr(fasttables, "_lib", type("Spy", (), {"ft_rgl_eval": lambda self, n, *a: calls.append(n) or
                                                             lib.ft_rgl_eval(n, *a)})())
    split = mat._eval_c(wo, mat._incident(wi))
    assert sorted(calls) == [1667, 1667, 1667] and np.array_equal(split, one) and (one != 0).any()


def test_c_eval_matches_numpy_on_a_real_file(rgl):
    from bake.maths import fasttables
    if fasttables.load() is None:
        pytest.skip(fasttables.REASON)
    mat = RGLMaterial(rgl("chm_mint_rgb"))
    wi, wo = random_pairs(3000, np.random.default_rng(4))
    for w in wi[:5]:
        fast = mat.eval(w, wo)
        np.testing.assert_allclose(fast, mat._eval_chunk(w[None], wo, mat._incident(w)), rtol=1e-8, atol=0)


def test_single_wi_eval_reuses_its_incident_tables_per_wi(tmp_path):
    """eval with one wi keeps that wi's interpolated tables (RGLMaterial._incidents): a material
    that evaluated other wi in between gives, bit for bit, what a fresh one gives."""
    path = write_tensor_file(tmp_path / "synthetic.bsdf", synthetic_fields((0.0,)))
    rng = np.random.default_rng(2)
    wo = normalize(rng.normal(size=(2048, 3)) * [1, 1, 0] + [0, 0, 1.5])
    wis = [spherical_dir(np.radians(t), 0.3) for t in (10.0, 50.0, 80.0)]
    used = open_material(path)
    for _ in range(2):
        for k, wi in enumerate(wis):
            np.testing.assert_array_equal(used.eval(wi, wo), open_material(path).eval(wi, wo))
    assert len(used._incidents) == 3
    for t in range(20):         # bounded
        used.eval(spherical_dir(np.radians(t), 0.0), wo)
    assert len(used._incidents) <= 16


@pytest.mark.parametrize("horizon", [False, True])
def test_warped_coords_are_where_eval_reads_rgb_both_ways(horizon, tmp_path):
    """WarpedCoords at one wi: to_s is where eval reads the rgb table (a file whose rgb is s_x
    itself, ndf 1 and sigma 1/4, evaluates to s_x / cos theta_o; with `horizon`, s_x over its
    value at the horizon), from_s inverts it (s back to 1e-9 where a direction is reached), the
    Jacobian d omega / d s agrees with finite differences, and over s it covers the hemisphere:
    the integral of the reached part is 2 pi. With `horizon` every s reaches a direction above
    the horizon (this file's warp has no zero rows) and s_x = 1 is the horizon."""
    from bake.materials.rgl import WarpedCoords
    f = synthetic_fields(n_vndf=16, n_rgb=8)
    n_rgb = f["rgb"].shape[-1]
    f["rgb"][:] = (np.arange(n_rgb) / (n_rgb - 1))[None, None, None, None, :]    # rgb(s) = s_x
    f["ndf"][:] = 1.0
    f["sigma"][:] = 0.25
    mat = RGLMaterial(write_tensor_file(tmp_path / "ramp.bsdf", f))
    rng = np.random.default_rng(5)
    side = 256
    grid = (np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2) + 0.5) / side
    for theta in np.radians([0.3, 30.0, 60.0, 85.0]):
        wi = spherical_dir(theta, 0.7)
        warp = WarpedCoords(mat, horizon=horizon)
        wo = spherical_dir(np.arccos(rng.uniform(0.02, 1.0, 3000)), rng.uniform(-np.pi, np.pi, 3000))
        s, jac = warp.to_s(wi, wo)
        s_file = WarpedCoords(mat).to_s(wi, wo)[0]
        np.testing.assert_allclose(mat.eval(wi, wo)[:, 0] * wo[:, 2], s_file[:, 0], rtol=1e-6, atol=1e-7)
        np.testing.assert_array_equal(s[:, 1], s_file[:, 1])        # the row is the file's
        if horizon:     # s_x over its value at the rim (<= 1)
            assert np.all(s[:, 0] >= s_file[:, 0] - 1e-12) and np.any(s[:, 0] > s_file[:, 0] * 1.01)
        back, jac_back = warp.from_s(wi, s)
        np.testing.assert_allclose(back, wo, atol=1e-7)
        np.testing.assert_allclose(jac_back, jac, rtol=1e-7)
        # d omega / d s = 1 / |det d s / d omega| on the tangent plane of wo
        t1 = normalize(np.cross(wo, [0.0, 0.0, 1.0]))
        t2 = np.cross(wo, t1)
        eps = 1e-6
        d1 = (warp.to_s(wi, normalize(wo + eps * t1))[0] - warp.to_s(wi, normalize(wo - eps * t1))[0]) / (2 * eps)
        d2 = (warp.to_s(wi, normalize(wo + eps * t2))[0] - warp.to_s(wi, normalize(wo - eps * t2))[0]) / (2 * eps)
        np.testing.assert_allclose(1.0 / np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]), jac, rtol=1e-4)
        wo_grid, jac_grid = warp.from_s(wi, grid)
        reached = jac_grid > 0
        assert (wo_grid[reached, 2] > 0).all() and (wo_grid[~reached, 2] <= 0).all()
        s_back = warp.to_s(wi, wo_grid[reached])[0]
        assert np.max(np.abs(s_back - grid[reached])) < 1e-9
        assert abs(np.mean(jac_grid) / (2 * np.pi) - 1.0) < 0.01
        if horizon:
            assert reached.all()
            rim_wo = warp.from_s(wi, np.stack([np.full(64, 1.0 - 1e-12), np.linspace(0.01, 0.99, 64)], -1))[0]
            np.testing.assert_allclose(rim_wo[:, 2], 0.0, atol=1e-5)


def test_stored_warp_is_half_the_bytes_and_the_files_coordinates(tmp_path):
    """stored_warp keeps the file's vndf in float16 over each slice's maximum: half the bytes, the
    same support (a value too small for float16 stays nonzero), and coordinates within float16's
    rounding of the file's (s to 2e-3 at four incident angles)."""
    from bake.materials.rgl import WarpedCoords
    f = synthetic_fields(n_vndf=16, n_rgb=8)
    f["vndf"][0, 1, 3, 3] = 1e-30 * f["vndf"][0, 1].max()     # below float16's smallest, over the maximum
    f["vndf"][0, 2, 5, :] = 0.0
    mat = RGLMaterial(write_tensor_file(tmp_path / "w.bsdf", f))
    stored = mat.stored_warp
    assert stored.dtype == np.float16 and mat.warp_nbytes == stored.nbytes == f["vndf"].nbytes // 2
    np.testing.assert_array_equal(stored > 0, f["vndf"].reshape(stored.shape) > 0)
    rng = np.random.default_rng(2)
    for theta in np.radians([0.0, 35.0, 70.0, 88.0]):
        wi = spherical_dir(theta, -0.4)
        wo = spherical_dir(np.arccos(rng.uniform(0.02, 1.0, 2000)), rng.uniform(-np.pi, np.pi, 2000))
        s_file = WarpedCoords(mat, horizon=True).to_s(wi, wo)[0]
        s_stored = WarpedCoords(mat, horizon=True, stored=True).to_s(wi, wo)[0]
        assert 0 < np.max(np.abs(s_stored - s_file)) < 2e-3

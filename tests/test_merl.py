"""MERL BRDF reading, evaluation and writing (bake/materials/merl.py)."""
import functools
import hashlib
import math

import numpy as np
import pytest

from bake.errors import FlowBSDFError
from bake.maths.geometry import spherical_dir
from bake.materials import open_material
from bake.materials.analytic import Lambert, Microfacet, RoughPlastic
from bake.materials.base import Material
from bake.materials.merl import (
    DIMS, FILE_BYTES, N_BINS, SCALE, MERLMaterial, bin_centres, bin_index, half_diff, half_diff_to_dirs,
    read_merl, write_merl,
)


def random_dirs(rng, n, max_theta_deg=90.0):
    z = rng.uniform(math.cos(math.radians(max_theta_deg)), 1.0, n)
    return spherical_dir(np.arccos(z), rng.uniform(-np.pi, np.pi, n))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """MERL files tabulated from a coloured GGX conductor and a rough plastic (written once)."""
    root = tmp_path_factory.mktemp("merl")
    mats = {"ggx": Microfacet("ggx", 0.3, fresnel="schlick", f0=[0.9, 0.6, 0.3]),
            "plastic": RoughPlastic([0.6, 0.3, 0.1], 0.2, 1.5)}
    return {key: (mat, write_merl(root / f"{key}.binary", mat)) for key, mat in mats.items()}


@functools.lru_cache(maxsize=1)
def centre_configs():
    """(wi, wo) at every bin centre (phi_h = 0), with the bin's indices, both directions above the horizon."""
    th, td, pd = bin_centres()
    I, J, K = np.meshgrid(np.arange(90), np.arange(90), np.arange(180), indexing="ij")
    wi, wo = half_diff_to_dirs(th[I.ravel()], td[J.ravel()], pd[K.ravel()])
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    return wi[up], wo[up], (I.ravel()[up], J.ravel()[up], K.ravel()[up])


# --------------------------------------------------------------------------- coordinates

def _rotate(v, axis, angle):
    """Rodrigues' rotation of one vector about a unit axis."""
    v, axis = np.asarray(v, float), np.asarray(axis, float)
    return (v * math.cos(angle) + axis * np.dot(axis, v) * (1 - math.cos(angle))
            + np.cross(axis, v) * math.sin(angle))


def test_half_diff_matches_the_reference_construction():
    """Against a one-pair-at-a-time construction: rotate wi by -phi_h about z, then by -theta_h about y."""
    rng = np.random.default_rng(1)
    wi, wo = random_dirs(rng, 300), random_dirs(rng, 300)
    th, td, pd = half_diff(wi, wo)
    for n in range(len(wi)):
        h = (wi[n] + wo[n]) / np.linalg.norm(wi[n] + wo[n])
        theta_h, phi_h = math.acos(h[2]), math.atan2(h[1], h[0])
        d = _rotate(_rotate(wi[n], [0, 0, 1], -phi_h), [0, 1, 0], -theta_h)
        assert th[n] == pytest.approx(theta_h, abs=1e-9)
        assert td[n] == pytest.approx(math.acos(np.clip(d[2], -1, 1)), abs=1e-9)
        delta = (pd[n] - math.atan2(d[1], d[0]) + np.pi) % (2 * np.pi) - np.pi
        assert abs(delta) < 1e-9


def test_half_diff_round_trip_and_reciprocity():
    rng = np.random.default_rng(2)
    th = rng.uniform(0, 0.5 * np.pi, 1000)
    td = rng.uniform(0, 0.5 * np.pi, 1000)
    pd = rng.uniform(-np.pi, np.pi, 1000)
    wi, wo = half_diff_to_dirs(th, td, pd)
    np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(wo, axis=1), 1, atol=1e-14)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    np.testing.assert_allclose(h[:, 1], 0, atol=1e-14)       # phi_h = 0
    a, b, c = half_diff(wi, wo)
    np.testing.assert_allclose(a, th, atol=1e-12)
    np.testing.assert_allclose(b, td, atol=1e-12)
    np.testing.assert_allclose(np.mod(c - pd + np.pi, 2 * np.pi) - np.pi, 0, atol=1e-12)
    # Swapping wi and wo turns phi_d by pi: the same bin after folding modulo pi.
    a2, b2, c2 = half_diff(wo, wi)
    np.testing.assert_allclose(b2, b, atol=1e-12)
    np.testing.assert_allclose(np.mod(c2 - c, 2 * np.pi), np.pi, atol=1e-12)


def test_bin_index_reference_mapping():
    deg = np.radians
    i, j, k = bin_index(np.array([0.0, 1e-9, 0.5 * np.pi, deg(45.0)]),
                        np.array([0.0, deg(1.5), 0.5 * np.pi, deg(89.99)]),
                        np.array([0.0, deg(-0.5), deg(90.5), deg(179.5)]))
    # theta_h is sqrt-mapped: 45 deg -> floor(sqrt(0.5) * 90) = 63.
    assert i.tolist() == [0, 0, 89, 63]
    assert j.tolist() == [0, 1, 89, 89]
    assert k.tolist() == [0, 179, 90, 179]
    th, td, pd = bin_centres()
    ii, jj, kk = np.arange(90), np.arange(90), np.arange(180)
    assert (bin_index(th, td[:90], pd[:90])[0] == ii).all()
    assert (bin_index(th[:1], td, pd[:90])[1] == jj).all()
    assert (bin_index(th[:1], td[:1], pd)[2] == kk).all()
    # Bin edges of theta_h: (i / 90)^2 * pi/2.
    edges = (np.arange(1, 90) / 90.0) ** 2 * 0.5 * np.pi
    assert (bin_index(edges * (1 + 1e-12), 0.0, 0.0)[0] == np.arange(1, 90)).all()
    assert (bin_index(edges * (1 - 1e-12), 0.0, 0.0)[0] == np.arange(0, 89)).all()


# --------------------------------------------------------------------------- round trip

@pytest.mark.parametrize("key", ["ggx", "plastic"])
def test_round_trip_at_bin_centres_is_exact(files, key):
    mat, path = files[key]
    merl = MERLMaterial(path)
    assert path.stat().st_size == FILE_BYTES
    wi, wo, (i, j, k) = centre_configs()
    # The file holds f / scale at every centre; the centres below the horizon are marked invalid.
    raw, _ = read_merl(path)
    below = np.ones(DIMS, bool)
    below[i, j, k] = False
    assert np.all(raw[:, below] < 0) and np.all(raw[:, ~below] >= 0)
    # Evaluating the file at (a random eighth of) the centres gives the material's values back.
    pick = np.random.default_rng(0).random(len(wi)) < 0.125
    wi, wo, i, j, k = wi[pick], wo[pick], i[pick], j[pick], k[pick]
    expect = mat.eval(wi, wo)
    np.testing.assert_allclose(raw[:, i, j, k].T * SCALE, expect, rtol=1e-14)
    np.testing.assert_allclose(merl.eval(wi, wo), expect, rtol=1e-14, atol=0)
    # Same through the linear lookup: at a centre the interpolation weights are (1, 0).
    lin = MERLMaterial(path, lookup="linear")
    np.testing.assert_allclose(lin.eval(wi, wo), expect, rtol=1e-12, atol=0)


@pytest.mark.parametrize("key", ["ggx", "plastic"])
def test_random_directions_within_discretization_error(files, key):
    mat, path = files[key]
    rng = np.random.default_rng(3)
    wi, wo = random_dirs(rng, 20000, 80), random_dirs(rng, 20000, 80)
    f = mat.eval(wi, wo)
    scale = np.maximum(f, 1e-3 * f.max(axis=0))
    # Bins are 1 degree (theta_d, phi_d) and up to 2 degrees (theta_h): nearest lookup errs by
    # about the change of f across half a bin, interpolation by far less.
    near = np.abs(MERLMaterial(path).eval(wi, wo) - f) / scale
    lin = np.abs(MERLMaterial(path, lookup="linear").eval(wi, wo) - f) / scale
    assert np.median(near) < 0.02 and np.percentile(near, 95) < 0.06
    assert np.median(lin) < 2e-3 and np.percentile(lin, 95) < 5e-3
    # MERL data are reciprocal.
    np.testing.assert_allclose(MERLMaterial(path, lookup="linear").eval(wo, wi),
                               MERLMaterial(path, lookup="linear").eval(wi, wo), rtol=1e-9)


def test_rewriting_a_merl_material_keeps_its_data(files, tmp_path):
    _, path = files["plastic"]
    merl = MERLMaterial(path)
    again = write_merl(tmp_path / "again.binary", merl)
    a, _ = read_merl(path)
    b, _ = read_merl(again)
    np.testing.assert_allclose(b, a, rtol=1e-14, atol=0)


def test_merl_material_basics(files):
    _, path = files["ggx"]
    m = MERLMaterial(path)
    assert m.isotropic and m.name == "ggx" and repr(m) == "<MERLMaterial ggx>"
    assert m.fingerprint() == hashlib.sha256(path.read_bytes()).hexdigest()
    assert MERLMaterial(path, lookup="linear").fingerprint() != m.fingerprint()
    assert m.table().shape == (3,) + DIMS
    wi = np.array([0.0, 0.6, 0.8])
    below = np.array([[0.0, 0.6, -0.8], [0.6, 0.0, 0.8]])
    f = m.eval(wi, below)                                   # wi (3,) against wo (N,3)
    assert f.shape == (2, 3) and np.all(f[0] == 0) and np.all(f[1] > 0)
    assert np.all(m.eval(below[0], below) == 0)
    with pytest.raises(FlowBSDFError, match="lookup"):
        MERLMaterial(path, lookup="cubic")


# --------------------------------------------------------------------------- invalid entries

def test_invalid_entries_read_as_zero(files, tmp_path):
    _, path = files["plastic"]
    raw, _ = read_merl(path)
    wi = spherical_dir(np.radians(30), 0.3)
    wo = spherical_dir(np.radians(50), 2.0)
    i, j, k = (int(x[0]) for x in bin_index(*half_diff(wi, wo)))
    raw = raw.copy()
    raw[:, i, j, k] = -1.0              # all channels missing in this bin
    raw[1, i, j, (k + 3) % 180] = -0.5  # only green missing in another
    bad = tmp_path / "holes.binary"
    bad.write_bytes(np.array(DIMS, "<i4").tobytes() + raw.astype("<f8").tobytes())
    m = MERLMaterial(bad)
    assert m.invalid_fraction > 0.2     # the below-horizon bins, plus the holes
    assert np.all(m.eval(wi, wo) == 0)
    th, td, pd = bin_centres()
    f = m.eval(*half_diff_to_dirs(th[i], td[j], pd[(k + 3) % 180]))[0]
    assert f[1] == 0 and f[0] > 0 and f[2] > 0
    # Linear lookup skips the hole and renormalizes over the valid neighbours.
    lin = MERLMaterial(bad, lookup="linear").eval(wi, wo)[0]
    full = MERLMaterial(path, lookup="linear").eval(wi, wo)[0]
    assert np.all(lin > 0)
    np.testing.assert_allclose(lin, full, rtol=0.05)
    # A neighbourhood with no valid entry reads as 0.
    raw[:] = -1.0
    bad.write_bytes(np.array(DIMS, "<i4").tobytes() + raw.astype("<f8").tobytes())
    assert np.all(MERLMaterial(bad, lookup="linear").eval(wi, wo) == 0)


# --------------------------------------------------------------------------- bad input

def _file(tmp_path, name, header=DIMS, n_values=3 * N_BINS, poke=None, extra=b""):
    values = np.zeros(n_values)
    if poke is not None:
        values[poke[0]] = poke[1]
    path = tmp_path / name
    path.write_bytes(np.array(header, "<i4").tobytes() + values.astype("<f8").tobytes() + extra)
    return path


@pytest.mark.parametrize("make,words", [
    (lambda d: d / "empty.binary", ["header"]),
    (lambda d: _file(d, "dims.binary", header=(90, 90, 360)), ["(90, 90, 360)", "expected"]),
    (lambda d: _file(d, "order.binary", header=(180, 90, 90)), ["(180, 90, 90)"]),
    (lambda d: _file(d, "short.binary", n_values=3 * N_BINS - 1), ["truncated"]),
    (lambda d: _file(d, "long.binary", extra=b"\0"), ["trailing"]),
    (lambda d: _file(d, "nan.binary", poke=(N_BINS + 5, np.nan)), ["NaN", "channel G"]),
    (lambda d: _file(d, "inf.binary", poke=(7, np.inf)), ["infinite"]),
])
def test_bad_files(tmp_path, make, words):
    path = make(tmp_path)
    if not path.exists():
        path.write_bytes(b"")
    with pytest.raises(FlowBSDFError) as e:
        MERLMaterial(path)
    assert str(path) in str(e.value)
    for word in words:
        assert word in str(e.value), str(e.value)


def test_zero_file_is_valid(tmp_path):
    m = MERLMaterial(_file(tmp_path, "black.binary"))
    assert m.invalid_fraction == 0
    assert np.all(m.eval(spherical_dir(0.3, 0.0), random_dirs(np.random.default_rng(0), 10)) == 0)


def test_missing_file(tmp_path):
    with pytest.raises(FlowBSDFError, match="not found"):
        open_material(tmp_path / "nothing.binary")
    with pytest.raises(FlowBSDFError, match="cannot read"):
        MERLMaterial(tmp_path / "nothing.binary")


def test_write_rejects_what_merl_cannot_hold(tmp_path):
    with pytest.raises(FlowBSDFError, match="anisotropic"):
        write_merl(tmp_path / "a.binary", Microfacet("ggx", 0.1, 0.3))

    class Broken(Material):
        name = "broken"

        def eval(self, wi, wo):
            return np.full((len(wo), 3), np.nan)

    with pytest.raises(FlowBSDFError, match="non-finite"):
        write_merl(tmp_path / "b.binary", Broken())
    with pytest.raises(FlowBSDFError, match="Material"):
        write_merl(tmp_path / "c.binary", "ggx")
    assert not any(tmp_path.iterdir())


# --------------------------------------------------------------------------- dispatch

def test_open_material_dispatch(tmp_path):
    path = write_merl(tmp_path / "chalk.binary", Lambert([0.8, 0.7, 0.6]))
    for source, base in [(str(path), None), (path, None), ({"kind": "merl", "path": "chalk.binary"}, tmp_path),
                         ("chalk.binary", tmp_path)]:
        m = open_material(source, base_dir=base)
        assert isinstance(m, MERLMaterial) and m.name == "chalk"
    f = m.eval(spherical_dir(0.2, 0.0), random_dirs(np.random.default_rng(4), 100, 85))
    np.testing.assert_allclose(f, np.tile([0.8 / np.pi, 0.7 / np.pi, 0.6 / np.pi], (100, 1)), rtol=1e-14)

"""Bad-input corpus (issue 8): malformed `.bsdf`, MERL `.binary`, model (`.flow.npz`), table
(`.exr`) and manifest (`.toml`) files, all generated here.

Every one must be answered with bake.errors.FlowBSDFError whose message names the file and
the problem (never a numpy / KeyError / OverflowError / MemoryError traceback), and a bake
that meets one leaves no partial output behind.
"""
import io
import json
import re
import struct
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from bake.errors import FlowBSDFError
from bake.core.flow import load_model
from bake.plumbing.manifest import load_manifest
from bake.materials import open_material
from bake.materials.merl import DIMS, N_BINS
from bake.io.paths import model_path, table_path
from bake.plumbing.pipeline import bake_manifest
from bake.core.table_files import open_tables
from conftest import write_npz
from test_rgl import synthetic_fields, write_tensor_file

ROOT = Path(__file__).resolve().parents[1]
FAST_BAKE = ("{ resolution = 16, tol = 0.5, grid = 64, samples = 1024, first_bins = 2, "
             "ideal_resolution = 32 }")


# ------------------------------------------------------------------------ good files to break

def good_bsdf(path, **kw):
    return write_tensor_file(path, synthetic_fields(**kw))


def merl_bytes(values=None, header=DIMS):
    """A MERL file's bytes: a grey Lambert-ish table unless `values` (3 * N_BINS floats) is given."""
    if values is None:
        values = np.full(3 * N_BINS, 0.3 * 1500 / np.pi)
    return np.array(header, "<i4").tobytes() + np.asarray(values, "<f8").tobytes()


def tiny_model_arrays(seed=0, width=16):
    """A valid isotropic disk flow (numpy only): base 2->w->4, velocity 5->w->2, small weights."""
    rng = np.random.default_rng(seed)
    f = lambda *s: (0.1 * rng.standard_normal(s)).astype(np.float32)   # noqa: E731
    return {"base.W0": f(width, 2), "base.b0": f(width), "base.W1": f(4, width), "base.b1": f(4),
            "vel.W0": f(width, 5), "vel.b0": f(width), "vel.W1": f(2, width), "vel.b1": f(2)}


def tiny_model_meta(**over):
    meta = {"format": "flowbsdf-flow", "version": 1, "domain": "disk", "isotropic": True, "steps": 4,
            "base": {"width": 16, "depth": 2, "log_sigma_range": [-4.0, 1.5], "kappa_max": 32.0},
            "velocity": {"width": 16, "depth": 2, "time_freq": 0, "activation": "silu"}}
    meta.update(over)
    return meta


def npy_header_bytes(shape, dtype="<f4"):
    """The bytes of a .npy member announcing `shape` (no data follows)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def npz_with_member(path, name, raw, meta=None, arrays=None):
    """An .npz holding the good model plus one member `name` with raw bytes."""
    arrays = tiny_model_arrays() if arrays is None else arrays
    with zipfile.ZipFile(path, "w") as z:
        for k, v in arrays.items():
            if k != name.removesuffix(".npy"):
                z.writestr(f"{k}.npy", _npy(v))
        z.writestr("meta.npy", _npy(np.array(json.dumps(meta or tiny_model_meta()))))
        z.writestr(name, raw)
    return path


def _npy(a):
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


@pytest.fixture(scope="module")
def good_tables(tmp_path_factory):
    """A small valid table file (Lambert, ideal source)."""
    from bake.core.ideal import IdealSampler
    from bake.core.tabulate import build_tables
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 0.5})
    tab = build_tables(mat, IdealSampler(mat, resolution=32), np.radians([0.0, 45.0, 89.0]), rows=8, cols=8,
                       grid=48)
    tab.meta["material"] = "matte"
    path = tmp_path_factory.mktemp("tables") / "good.exr"
    tab.save(path)
    return path


def exr_with(path, good, arrays=None, meta=None, drop=(), channel="Y", dtype=np.float32):
    """Rewrite the good table file with some parts / metadata changed (written straight with
    OpenEXR, so that nothing of bake/ cleans it up)."""
    import OpenEXR
    f = OpenEXR.File(str(good))
    parts = {p.name(): p.channels["Y"].pixels for p in f.parts}
    m = json.loads(f.parts[0].header["flowbsdf"])
    if meta is not None:
        m = meta(m) if callable(meta) else meta
    for k, v in (arrays or {}).items():
        parts[k] = v(parts[k]) if callable(v) else v
    out = []
    for i, (name, a) in enumerate((k, v) for k, v in parts.items() if k not in drop):
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "displayWindow": ((0, 0), (0, 0))}
        if i == 0 and m is not ...:
            header["flowbsdf"] = m if isinstance(m, str) else json.dumps(m)
        out.append(OpenEXR.Part(header, {channel: np.ascontiguousarray(a, dtype)}, name=name))
    OpenEXR.File(out).write(str(path))
    return path


# ------------------------------------------------------------------------ the corpus

def _bytes(data):
    return lambda p, g: (p.write_bytes(data), p)[1]


def _bsdf_patch(fn, **kw):
    """A synthetic RGL file with its fields changed by fn(fields) before writing."""
    def make(p, g):
        f = synthetic_fields(**kw)
        fn(f)
        return write_tensor_file(p, f)
    return make


def _bsdf_bytes(fn):
    """A valid synthetic RGL file whose bytes are changed by fn(bytearray) -> bytes."""
    def make(p, g):
        good_bsdf(p)
        p.write_bytes(bytes(fn(bytearray(p.read_bytes()))))
        return p
    return make


def _set(buf, at, fmt, *values):
    struct.pack_into(fmt, buf, at, *values)
    return buf


def _first_shape_at(buf):
    """Byte position of the first field's first shape entry, and of its offset."""
    (length,) = struct.unpack_from("<H", buf, 18)
    pos = 18 + 2 + length
    return pos + 11, pos + 3


PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4
BSDF = [
    ("zero-byte", _bytes(b""), "empty file"),
    ("one-byte", _bytes(b"t"), "truncated header"),
    ("magic-only", _bytes(b"tensor_file\0"), "truncated header"),
    ("foreign-png", _bytes(PNG), "bad magic"),
    ("foreign-text", _bytes(b"# a Wavefront .mtl file\nnewmtl x\n" * 20), "bad magic"),
    ("wrong-version", _bsdf_bytes(lambda b: _set(b, 12, "<BB", 2, 0)), "version 2.0"),
    ("huge-field-count", _bsdf_bytes(lambda b: _set(b, 14, "<I", 0xFFFFFFFF)), "announces 4294967295 fields"),
    ("huge-dimensions", _bsdf_bytes(lambda b: _set(b, _first_shape_at(b)[0], "<Q", 2 ** 62)), "absurd shape"),
    ("huge-offset", _bsdf_bytes(lambda b: _set(b, _first_shape_at(b)[1], "<Q", 2 ** 64 - 1)), "past end of file"),
    ("truncated-half", _bsdf_bytes(lambda b: b[:len(b) // 2]), "truncated"),
    ("truncated-last-data-byte", _bsdf_bytes(lambda b: b[:-8]), "truncated data"),
    ("nan-filled-vndf", _bsdf_patch(lambda f: f["vndf"].fill(np.nan)), "NaN or infinite"),
    ("inf-in-rgb", _bsdf_patch(lambda f: f["rgb"].__setitem__((0, 1, 0, 2, 2), np.inf)), "NaN or infinite"),
    ("missing-vndf", _bsdf_patch(lambda f: f.pop("vndf")), "missing required field"),
    ("theta-not-increasing", _bsdf_patch(lambda f: f["theta_i"].__setitem__(2, 0.0)), "strictly increasing"),
    ("vndf-all-zero", _bsdf_patch(lambda f: f["vndf"].fill(0.0)), "cannot be normalized"),
    ("sigma-zero", _bsdf_patch(lambda f: f["sigma"].fill(0.0)), "sigma"),
    ("rgb-wrong-shape", _bsdf_patch(lambda f: f.__setitem__("rgb", f["rgb"][:, :, :, :4])), "inconsistent shape"),
    ("theta-float64", _bsdf_patch(lambda f: f.__setitem__("theta_i", f["theta_i"].astype(np.float64))),
     "dtype float64"),
    ("empty-theta", _bsdf_patch(lambda f: f.__setitem__("theta_i", np.zeros(0, np.float32))), "inconsistent shape"),
    ("spectral", _bsdf_patch(lambda f: f.__setitem__("spectra", f.pop("rgb"))), "spectral"),
    ("unknown-dtype", _bsdf_bytes(lambda b: _set(b, _first_shape_at(b)[1] - 1, "<B", 77)), "unknown dtype"),
    ("duplicate-field", lambda p, g: _duplicate_field(p), "appears twice"),
    ("phi-range-not-a-fraction", _bsdf_patch(lambda f: None, phi_i=(0.0, 0.5, 2.0)), "phi_i"),
]


def _duplicate_field(p):
    """Two fields named theta_i (written as theta_i and theta_j, then renamed in the header)."""
    f = synthetic_fields()
    f["theta_j"] = f["theta_i"].copy()
    write_tensor_file(p, f)
    buf = p.read_bytes()
    p.write_bytes(buf.replace(b"theta_j", b"theta_i", 1))
    return p


def _merl_values(fn):
    def make(p, g):
        v = np.full(3 * N_BINS, 0.3 * 1500 / np.pi)
        fn(v)
        p.write_bytes(merl_bytes(v))
        return p
    return make


MERL = [
    ("zero-byte", _bytes(b""), "shorter than the 12-byte header"),
    ("header-only-8", _bytes(np.array([90, 90], "<i4").tobytes()), "shorter than the 12-byte header"),
    ("foreign-png", _bytes(PNG), "header dimensions"),
    ("big-endian-header", _bytes(np.array(DIMS, ">i4").tobytes() + bytes(64)), "header dimensions"),
    ("negative-dims", _bytes(np.array([-90, 90, 180], "<i4").tobytes() + bytes(64)), "header dimensions"),
    ("huge-dims", _bytes(np.array([2 ** 31 - 1] * 3, "<i4").tobytes() + bytes(64)), "header dimensions"),
    ("header-only", _bytes(np.array(DIMS, "<i4").tobytes()), "truncated"),
    ("truncated", lambda p, g: (p.write_bytes(merl_bytes()[:-8]), p)[1], "truncated"),
    ("trailing-bytes", lambda p, g: (p.write_bytes(merl_bytes() + b"\0" * 3), p)[1], "trailing bytes"),
    ("nan-filled", _merl_values(lambda v: v.fill(np.nan)), "NaN"),
    ("one-inf", _merl_values(lambda v: v.__setitem__(12345, -np.inf)), "infinite"),
]

MODEL = [
    ("zero-byte", _bytes(b""), "cannot read it as .npz"),
    ("foreign-png", _bytes(PNG), "cannot read it as .npz"),
    ("truncated", lambda p, g: (p.write_bytes(write_npz(p, tiny_model_meta(), tiny_model_arrays()).read_bytes()[:300]),
                                p)[1], "cannot read it as .npz"),
    ("no-meta", lambda p, g: write_npz(p, None, tiny_model_arrays()), "no metadata"),
    ("meta-not-json", lambda p, g: write_npz(p, "{broken", tiny_model_arrays()), "not valid JSON"),
    ("meta-a-list", lambda p, g: write_npz(p, "[1, 2]", tiny_model_arrays()), "format 'list'"),
    ("wrong-format", lambda p, g: write_npz(p, tiny_model_meta(format="other"), tiny_model_arrays()), "format 'other'"),
    ("wrong-version", lambda p, g: write_npz(p, tiny_model_meta(version=7), tiny_model_arrays()), "version 7"),
    ("steps-a-string", lambda p, g: write_npz(p, tiny_model_meta(steps="4"), tiny_model_arrays()), "steps"),
    ("base-missing-range", lambda p, g: write_npz(p, tiny_model_meta(base={"width": 16}), tiny_model_arrays()),
     "malformed model metadata"),
    ("nan-weights", lambda p, g: write_npz(p, tiny_model_meta(), {**tiny_model_arrays(),
                                                                  "vel.W0": np.full((16, 5), np.nan, np.float32)}),
     "non-finite weights"),
    ("nan-in-metadata", lambda p, g: write_npz(p, tiny_model_meta(base={"width": 16, "depth": 2, "log_sigma_range":
                                                                        [float("nan"), 1.5], "kappa_max": 32.0}),
                                               tiny_model_arrays()), "log_sigma_range"),
    ("int-weights", lambda p, g: write_npz(p, tiny_model_meta(), {**tiny_model_arrays(),
                                                                  "vel.b1": np.zeros(2, np.int32)}), "dtype int32"),
    ("wrong-architecture", lambda p, g: write_npz(p, tiny_model_meta(isotropic=False), tiny_model_arrays()),
     "network has shape"),
    ("huge-dimensions", lambda p, g: npz_with_member(p, "vel.W0.npy", npy_header_bytes((10 ** 6, 10 ** 6))),
     "vel.W0"),
    ("huge-steps", lambda p, g: write_npz(p, tiny_model_meta(steps=10 ** 12), tiny_model_arrays()), "steps"),
]


def _meta_edit(**kv):
    def edit(m):
        m = dict(m)
        for k, v in kv.items():
            if v is None:
                m.pop(k, None)
            else:
                m[k] = v
        return m
    return edit


TABLES = [
    ("zero-byte", _bytes(b""), "not a readable"),
    ("foreign-png", _bytes(PNG), "not a readable"),
    ("truncated", lambda p, g: (p.write_bytes(g.read_bytes()[:len(g.read_bytes()) * 2 // 3]), p)[1], "incomplete"),
    ("no-metadata", lambda p, g: exr_with(p, g, meta=...), "no metadata"),
    ("metadata-not-json", lambda p, g: exr_with(p, g, meta="{oops"), "not valid JSON"),
    ("metadata-a-list", lambda p, g: exr_with(p, g, meta="[1, 2, 3]"), "metadata"),
    ("wrong-format-version", lambda p, g: exr_with(p, g, meta=_meta_edit(format_version=99)), "format version 99"),
    ("missing-part", lambda p, g: exr_with(p, g, drop=("weights",)), "missing"),
    ("wrong-rows", lambda p, g: exr_with(p, g, meta=_meta_edit(rows=9)), "do not match"),
    ("huge-rows", lambda p, g: exr_with(p, g, meta=_meta_edit(rows=10 ** 15, cols=10 ** 15)), "do not match"),
    ("nan-filled-mass", lambda p, g: exr_with(p, g, arrays={"mass": lambda a: np.full_like(a, np.nan)}), "NaN"),
    ("negative-mass", lambda p, g: exr_with(p, g, arrays={"mass": lambda a: -a}), "corrupt"),
    ("edges-decreasing", lambda p, g: exr_with(p, g, arrays={"a_edges": lambda a: a[:, ::-1]}), "corrupt"),
    ("half-floats", lambda p, g: exr_with(p, g, dtype=np.float16), "float32"),
    ("other-channel", lambda p, g: exr_with(p, g, channel="R"), "not a readable"),
    ("layouts-out-of-range", lambda p, g: exr_with(p, g, meta=lambda m: {**m, "layouts": m["layouts"][:-1] + [99]}),
     "layouts"),
    ("layouts-floats", lambda p, g: exr_with(p, g, meta=lambda m: {**m, "layouts": [float(k) for k in m["layouts"]]}),
     "layouts"),
    ("layouts-missing", lambda p, g: exr_with(p, g, meta=_meta_edit(layouts=None)), "missing"),
    ("theta-bins-strings", lambda p, g: exr_with(p, g, meta=_meta_edit(theta_bins=["a", "b", "c"])), "theta_bins"),
    ("theta-bins-unsorted", lambda p, g: exr_with(p, g, meta=_meta_edit(theta_bins=[0.0, 1.5, 0.7])), "theta_bins"),
    ("theta-bins-nan", lambda p, g: exr_with(p, g, meta=_meta_edit(theta_bins=[0.0, float("nan"), 1.5])),
     "theta_bins"),
    ("no-theta-bins", lambda p, g: exr_with(p, g, meta=_meta_edit(theta_bins=None)), "missing"),
    # anisotropic files: phi_bins (and phi_period) in the metadata, the arrays K x P bins long
    ("phi-bins-strings", lambda p, g: exr_with(p, g, meta=_meta_edit(phi_bins=["a"])), "phi_bins"),
    ("phi-bins-unsorted", lambda p, g: exr_with(p, g, meta=_meta_edit(phi_bins=[1.0, 0.5])), "phi_bins"),
    ("phi-bins-nan", lambda p, g: exr_with(p, g, meta=_meta_edit(phi_bins=[float("nan")])), "phi_bins"),
    ("phi-bins-beyond-period", lambda p, g: exr_with(p, g, meta=_meta_edit(phi_bins=[0.0, 3.5], phi_period=np.pi)),
     "phi_bins"),
    ("phi-bins-empty", lambda p, g: exr_with(p, g, meta=_meta_edit(phi_bins=[])), "phi_bins"),
    ("phi-period-not-a-divisor", lambda p, g: exr_with(p, g, meta=_meta_edit(phi_bins=[0.0], phi_period=2.0)),
     "phi_period"),
    ("phi-period-string", lambda p, g: exr_with(p, g, meta=_meta_edit(phi_bins=[0.0], phi_period="pi")), "phi_period"),
    ("phi-bins-shapes", lambda p, g: exr_with(p, g, meta=_meta_edit(phi_bins=[0.0, 1.0])), "do not match"),
]


def _toml(text):
    return lambda p, g: (p.write_text(textwrap.dedent(text)), p)[1]


def _toml_material(bake="", extra=""):
    return _toml(f"""
        [[material]]
        name = "matte"
        source = {{ kind = "analytic", model = "lambert", albedo = 0.5 }}
        {bake}
        {extra}
    """)


MANIFEST = [
    ("zero-byte", _bytes(b""), "no [[material]] entries"),
    ("foreign-png", _bytes(PNG), "not UTF-8"),
    ("utf16", _bytes('[[material]]\nname = "x"\n'.encode("utf-16")), "not UTF-8"),
    ("truncated", _toml('[[material]]\nname = "matte"\nsource = { kind = "analytic", model = "lamb'),
     "not valid TOML"),
    ("material-a-string", _toml('material = "x"\n'), "no [[material]] entries"),
    ("unknown-top-key", _toml('version = 2\n[[material]]\nname = "a"\nsource = "a.bsdf"\n'), "unknown key"),
    ("missing-source", _toml('[[material]]\nname = "a"\n'), "needs a 'source'"),
    ("path-traversal-name", _toml('[[material]]\nname = "../../etc/x"\nsource = "a.bsdf"\n'), "needs a 'name'"),
    ("duplicate-names", _toml('[[material]]\nname = "a"\nsource = "a.bsdf"\n[[material]]\nname = "a"\n'
                              'source = "b.bsdf"\n'), "used twice"),
    ("bad-domain", _toml('[[material]]\nname = "a"\nsource = "a.bsdf"\ndomain = "cube"\n'), "domain must be"),
    ("nan-albedo", _toml('[[material]]\nname = "a"\nsource = { kind = "analytic", model = "lambert", albedo = nan }\n'),
     "must be finite"),
    ("source-a-directory", _toml('[[material]]\nname = "a"\nsource = "."\n'), "not found"),
    ("huge-resolution", _toml_material("bake = { resolution = 1000000000 }"), "resolution"),
    ("huge-grid", _toml_material("bake = { grid = 10000000 }"), "grid"),
    ("negative-samples", _toml_material("bake = { samples = -5 }"), "samples"),
    ("string-tol", _toml_material('bake = { tol = "small" }'), "tol"),
    ("nan-tol", _toml_material("bake = { tol = nan }"), "tol"),
    ("bool-first-bins", _toml_material("bake = { first_bins = true }"), "first_bins"),
    ("huge-ideal-resolution", _toml_material("bake = { ideal_resolution = 100000000 }"), "ideal_resolution"),
]

CORPUS = ([("bsdf", *c) for c in BSDF] + [("merl", *c) for c in MERL] + [("model", *c) for c in MODEL]
          + [("tables", *c) for c in TABLES] + [("manifest", *c) for c in MANIFEST])
SUFFIX = {"bsdf": ".bsdf", "merl": ".binary", "model": ".flow.npz", "tables": ".exr", "manifest": ".toml"}


def test_corpus_is_big_enough():
    assert len(CORPUS) >= 50
    assert {kind for kind, *_ in CORPUS} == set(SUFFIX)


def _open(kind, path, out):
    if kind in ("bsdf", "merl"):
        return open_material(path)
    if kind == "model":
        return load_model(path)
    if kind == "tables":
        return open_tables(path)
    m = load_manifest(path)
    return bake_manifest(m, out, log=lambda *_: None)


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


@pytest.mark.parametrize("kind,case,make,problem", CORPUS, ids=[f"{k}-{c}" for k, c, *_ in CORPUS])
def test_bad_input_is_a_clear_error(tmp_path, good_tables, kind, case, make, problem):
    path = make(tmp_path / f"{case}{SUFFIX[kind]}", good_tables)
    out = tmp_path / "out"
    before = _listing(tmp_path)
    with pytest.raises(FlowBSDFError) as info:
        _open(kind, path, out)
    message = str(info.value)
    assert str(path) in message, f"the message does not name the file: {message}"
    assert problem in message, f"the message does not say {problem!r}: {message}"
    assert info.value.__cause__ is None or isinstance(info.value.__cause__, FlowBSDFError)
    # nothing written beside the input, and no partial output
    assert _listing(tmp_path) == before, "files appeared"
    assert not _listing(out) or all(not p.endswith((".exr", ".tmp")) for p in _listing(out))


# ------------------------------------------------------------------------ end to end: bake leaves nothing

def _bake_manifest_for(tmp_path, source_line, with_good=True):
    good = textwrap.dedent("""
        [[material]]
        name = "good"
        source = { kind = "analytic", model = "lambert", albedo = 0.4 }
    """) if with_good else ""
    path = tmp_path / "scene.toml"
    path.write_text(textwrap.dedent(f"""
        [defaults]
        bake = {FAST_BAKE}
        [[material]]
        name = "broken"
        {source_line}
    """) + good)
    return path


BAKE_CASES = ([("bsdf", c) for c in BSDF if c[0] in ("zero-byte", "truncated-half", "nan-filled-vndf",
                                                    "huge-dimensions", "wrong-version")]
              + [("merl", c) for c in MERL if c[0] in ("zero-byte", "truncated", "nan-filled")]
              + [("model", c) for c in MODEL if c[0] in ("zero-byte", "truncated", "nan-weights",
                                                        "huge-dimensions", "nan-in-metadata")])


@pytest.mark.parametrize("kind,case", BAKE_CASES, ids=[f"{k}-{c[0]}" for k, c in BAKE_CASES])
def test_bake_with_a_broken_input_leaves_no_partial_output(tmp_path, good_tables, kind, case):
    name, make, problem = case
    out = tmp_path / "out"
    if kind == "model":
        bad = make(model_path(out, "broken").parent.mkdir(parents=True) or model_path(out, "broken"), good_tables)
        manifest = _bake_manifest_for(tmp_path, 'source = { kind = "analytic", model = "ggx", alpha = 0.3 }\n'
                                      'bake = { source = "flow" }', with_good=False)     # tables from the model
    else:
        bad = make(tmp_path / f"broken{SUFFIX[kind]}", good_tables)
        manifest = _bake_manifest_for(tmp_path, f'source = "{bad.name}"', with_good=False)
    before = _listing(out)
    with pytest.raises(FlowBSDFError) as info:
        bake_manifest(load_manifest(manifest), out, log=lambda *_: None)
    assert str(bad) in str(info.value) and problem in str(info.value)
    assert _listing(out) == before, "the failed bake wrote something"


def test_cli_reports_bad_inputs_without_traceback(tmp_path):
    bad = tmp_path / "broken.bsdf"
    bad.write_bytes(PNG)
    manifest = _bake_manifest_for(tmp_path, f'source = "{bad.name}"')
    env_python = str(ROOT / ".venv" / "bin" / "python")
    python = env_python if Path(env_python).exists() else sys.executable
    r = subprocess.run([python, "-m", "bake.plumbing.cli", "bake", str(manifest), "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert str(bad) in r.stderr and "bad magic" in r.stderr
    out = tmp_path / "out"
    listing = _listing(out)
    # the good material's tables and what the Blender node reads beside them, nothing else
    assert listing[:4] == ["tables", "tables/good.exr", "tables/good.fit.json", "tables/good.match.exr"], listing
    assert len(listing) == 6 and re.fullmatch(r"tables/good\.osl\d+-[0-9a-f]{12}\.exr", listing[4]), listing
    assert re.fullmatch(r"tables/good\.svm\d+-[0-9a-f]{12}\.exr", listing[5]), listing
    open_tables(table_path(out, "good"))


def test_unwritable_output_is_a_clear_error(tmp_path):
    """The tables folder is a file: a FlowBSDFError naming it, not an OSError traceback."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "tables").write_text("in the way")
    manifest = _bake_manifest_for(tmp_path, 'source = { kind = "analytic", model = "lambert", albedo = 0.7 }',
                                  with_good=False)
    with pytest.raises(FlowBSDFError) as info:
        bake_manifest(load_manifest(manifest), out, log=lambda *_: None)
    assert "tables" in str(info.value)
    assert (out / "tables").read_text() == "in the way"
    assert sorted(p.name for p in out.iterdir()) == ["tables"]

"""The C fast path of Tables (bake/maths/_tables_c.c), loaded with ctypes; never required.

    AVAILABLE   True when the C library is loaded
    REASON      one line: where it was loaded from, or why not (then Tables uses numpy)
                (both are set on first use, by load(): importing bake never runs a compiler)
    sample(tables, wi, u), pdf(tables, wi, wo), invert(tables, wi, wo), eval(tables, wi, wo)
                the Tables (and MixedTables) methods in C; each returns None when it cannot
                take the inputs (the caller then runs the numpy reference)
    rgl_eval(params, vndf, rgb, ndf, wo)
                an RGL material's f for one wi (RGLMaterial.eval's hot loop, for the baker)
    polar_grid(a, cos_b, sin_b, cap, wi, c, s)
                halfvector.polar_grid_from_ab's nodes (the baker's halfpolar quadrature)
    warp_to_s(warp, wi, wo), warp_from_s(warp, wi, s)
                rgl.WarpedCoords' to_s and from_s (the carried tables' hot loop)

The C code is a transcription of the numpy reference in bake/core/tables.py and profiles.py
(same formulas, same order of operations, same branches): results agree to a few ulps (libm's
or libmvec's atan2, exp, ... and numpy's own SIMD versions differ in the last bits). With glibc's
vector math (libmvec, x86-64 Linux) the transcendental functions of 16 samples run in
vector lanes (`flowbsdf report` measures the speed, with one wi per call and with a new
wi per sample, beside Mitsuba's).

Where the library comes from, first that works:
1. `bake/maths/_tables_c*.so` (or .pyd/.dylib) beside this file, built by setup.py when the
   package is installed (`pip install -e .` builds it in place). It embeds the SHA-256 of
   the C source it was built from; when that source is beside it and differs (edited after
   the install), the library is stale and skipped.
2. a per-user cache, $FLOWBSDF_CACHE or $XDG_CACHE_HOME/flowbsdf or ~/.cache/flowbsdf:
   `_tables_c-<source hash>.so`, compiled on first use with cc/gcc (written to a
   temporary file, then renamed: concurrent processes never see half a library).
3. none: numpy. Without a C compiler, in Blender, or with FLOWBSDF_NO_C=1 in the
   environment (which also skips steps 1 and 2).
"""
import ctypes
import hashlib
import os
import shlex
import shutil
import subprocess
import tempfile
import threading
import weakref
from pathlib import Path

import numpy as np

from ..io import threads

ABI = 8                       # FT_ABI in _tables_c.c
COORDS = ("wo", "halfvector", "halfpolar")     # tables.COORDS in the order of ft_tables.coords
HERE = Path(__file__).resolve().parent
SOURCE = HERE / "_tables_c.c"
# -ffp-contract=off: no fused multiply-adds (they would round the interpolations
# differently from numpy). Never -ffast-math.
CFLAGS = ["-O2", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno", "-std=c99"]
# glibc's vector math (x86-64 Linux, GCC): the block loops' libm calls in vector lanes
VECTOR_FLAGS = ["-fopenmp-simd", "-lmvec", "-lm"]


class _Tables(ctypes.Structure):
    _fields_ = [(name, ctypes.c_int64) for name in ("K", "R", "C", "P", "coords")] + [
        (name, ctypes.c_double) for name in ("period", "frame", "phi0")] + [
        (name, ctypes.c_void_p) for name in
        ("starts", "theta_bins", "cos_bins", "a", "b", "m", "alpha", "beta", "row_cdf", "col_cum", "weights")]


class _Warp(ctypes.Structure):
    _fields_ = [(name, ctypes.c_int64) for name in ("ny", "nx", "S", "horizon")] + [
        (name, ctypes.c_void_p) for name in ("theta_i", "tables")]


def source_sha():
    return hashlib.sha256(SOURCE.read_bytes()).hexdigest()


def _open(path, want_sha):
    """The loaded library at path, or raise OSError saying why not."""
    lib = ctypes.CDLL(str(path))
    if lib.ft_abi() != ABI:
        raise OSError(f"{path.name}: ABI {lib.ft_abi()} != {ABI}")
    lib.ft_source_sha.restype = ctypes.c_char_p
    if want_sha is not None and lib.ft_source_sha().decode() != want_sha:
        raise OSError(f"{path.name} is stale (built from another _tables_c.c; reinstall)")
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    for name in ("ft_sample", "ft_pdf", "ft_invert", "ft_eval"):
        fn = getattr(lib, name)
        fn.restype = None
        # the parts (nparts ft_tables), nparts, bounds, n, wi, wi_stride, in, out (, sample's pdf)
        fn.argtypes = [ctypes.POINTER(_Tables), i64, ptr, i64, ptr, i64, ptr, ptr] + [ptr] * (name == "ft_sample")
    for name in ("ft_warp_to_s", "ft_warp_from_s"):
        getattr(lib, name).restype = None
        getattr(lib, name).argtypes = [ctypes.POINTER(_Warp), i64, ptr, i64, ptr, ptr, ptr]
    lib.ft_rgl_eval.restype = None
    lib.ft_rgl_eval.argtypes = [i64, ptr, ptr, ptr, i64, i64, ptr, i64, i64, ptr, i64, i64, ptr]
    lib.ft_polar_grid.restype = None
    lib.ft_polar_grid.argtypes = [i64, i64, i64, ptr, ptr, ptr, ptr, ptr, ctypes.c_double, ctypes.c_double, ptr, ptr]
    return lib


def cache_dir():
    base = os.environ.get("FLOWBSDF_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "flowbsdf")
    return Path(base)


def compile_library(sha, out_dir=None):
    """Compile _tables_c.c into out_dir (default: the cache) as _tables_c-<sha[:16]>.so."""
    cc = shlex.split(os.environ.get("CC", ""))
    if not cc:
        found = next(filter(None, map(shutil.which, ("cc", "gcc", "clang"))), None)
        cc = [found] if found else []
    if not cc:
        raise OSError("no C compiler (cc/gcc/clang) found")
    out_dir = Path(out_dir or cache_dir())
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"_tables_c-{sha[:16]}.so"
    if target.exists():
        return target
    fd, tmp = tempfile.mkstemp(prefix=".tables_c-", suffix=".so", dir=out_dir)
    os.close(fd)
    try:
        for extra in VECTOR_FLAGS, ["-DFT_NO_MVEC", "-lm"]:     # libmvec where there is one
            r = subprocess.run([*cc, *CFLAGS, f'-DFT_SOURCE_SHA="{sha}"', "-o", tmp, str(SOURCE), *extra],
                               capture_output=True, text=True, timeout=120)
            if r.returncode == 0:
                break
        if r.returncode != 0:
            raise OSError(f"{Path(cc[0]).name} failed: " + (r.stderr.strip().splitlines() or ["?"])[-1])
        os.chmod(tmp, 0o755)      # mkstemp made it private; a shared FLOWBSDF_CACHE needs it readable
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def _load():
    if os.environ.get("FLOWBSDF_NO_C", "") not in ("", "0"):
        return None, "disabled by FLOWBSDF_NO_C"
    try:
        sha = source_sha()
    except OSError:
        sha = None                # an installed wheel without the source: trust its build
    notes = []
    built = sorted(p for p in HERE.glob("_tables_c*") if p.suffix in (".so", ".pyd", ".dylib"))
    for path in built:
        try:
            return _open(path, sha), f"C library {path}"
        except (OSError, AttributeError) as e:
            notes.append(str(e).splitlines()[0])
    if sha is None:
        return None, "numpy fallback: " + ("; ".join(notes) or "no C library installed, no source to compile")
    try:
        path = compile_library(sha)
        return _open(path, sha), f"C library {path} (compiled on first use)"
    except (OSError, AttributeError, subprocess.SubprocessError) as e:
        notes.append(str(e).splitlines()[0] if str(e) else type(e).__name__)
    return None, "numpy fallback: " + "; ".join(notes)


_lib = None
_loaded = False
_lock = threading.Lock()


def load():
    """Find (or build) and load the library, once; sets AVAILABLE and REASON. Never raises."""
    global _lib, _loaded, AVAILABLE, REASON
    with _lock:
        if not _loaded:
            try:
                _lib, REASON = _load()
            except Exception as e:      # never let the fast path break a caller (e.g. in Blender)
                _lib, REASON = None, f"numpy fallback: {type(e).__name__}: {e}"
            AVAILABLE = _lib is not None
            _loaded = True
    return _lib


def __getattr__(name):
    # AVAILABLE and REASON come into being on first use: importing bake never runs a compiler.
    if name in ("AVAILABLE", "REASON"):
        load()
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ------------------------------------------------------------------------------ calls

_STRUCTS = weakref.WeakKeyDictionary()     # Tables -> (array ids, struct, arrays it points into)


def _struct(tab):
    """The ctypes view of tab's working arrays (cached; rebuilt when an array is replaced),
    or None when their shapes are not a table's (or anisotropic tables are not over the half
    vector: the C code knows that phi axis only)."""
    if tab.anisotropic != (tab.coords == "halfvector"):    # isotropic: wo or halfpolar
        return None
    arrays = (tab.theta_bins, tab._a, tab._b, tab._m, tab._alpha, tab._beta, tab._row_cdf, tab._col_cum,
              tab.weights)
    key = tuple(map(id, arrays))
    cached = _STRUCTS.get(tab)
    if cached is not None and cached[0] == key:
        return cached[1]
    theta, a, b, m, alpha, beta, row_cdf, col_cum = (np.ascontiguousarray(x, np.float64) for x in arrays[:-1])
    weights = np.ascontiguousarray(arrays[-1], np.float32)
    K, R, C = len(theta), tab.rows, tab.cols
    P = 1 if tab.phi_bins is None else len(tab.phi_bins)
    B = K * P                     # the working arrays' bins: k P + p
    shapes = [(theta, (K,)), (a, (B, R + 1)), (row_cdf, (B, R + 1)), (b, (B, R, C + 1)), (col_cum, (B, R, C + 1)),
              (m, (B, R, C)), (alpha, (B, R, C, 4)), (beta, (B, R, C, 4)), (weights.reshape(-1, R, C, 3), (B, R, C, 3))]
    if K < 1 or R < 1 or C < 1 or any(x.shape != shape for x, shape in shapes):
        return None
    cos_bins = np.cos(theta)      # numpy's cos, as Tables._bins computes it
    phi0 = 0.0 if P == 1 else float(tab.phi_bins[0])
    starts = np.ascontiguousarray(np.zeros(1) if P == 1 else tab.phi_bins - tab.phi_bins[0], np.float64)
    s = _Tables(K, R, C, P, COORDS.index(tab.coords), tab.phi_period, tab.frame_angle, phi0,
                *(x.ctypes.data for x in (starts, theta, cos_bins, a, b, m, alpha, beta, row_cdf, col_cum, weights)))
    _STRUCTS[tab] = (key, s, arrays + (starts, theta, cos_bins, a, b, m, alpha, beta, row_cdf, col_cum, weights))
    return s


def _parts(tab):
    """(the ft_tables of tab's parts as a C array, their count, the parts' bounds or None): a
    Tables is one part, MixedTables has several (its bounds: MixedTables.bounds); None when
    a part is not the C code's."""
    parts = getattr(tab, "parts", None) or [tab]
    structs = [_struct(p) for p in parts]
    if any(s is None for s in structs):
        return None
    bounds = None if len(parts) == 1 else np.ascontiguousarray(tab.bounds, np.float64)
    if bounds is not None and bounds.shape != (len(parts) - 1,):
        return None
    return (_Tables * len(parts))(*structs), len(parts), bounds


def _wi_arg(wi, n):
    """wi as (pointer array, row stride): one direction (stride 0) or n contiguous rows."""
    wi = np.asarray(wi, np.float64)
    if wi.shape == (3,) or wi.shape == (1, 3):
        return np.ascontiguousarray(wi.reshape(3)), 0
    if wi.shape == (n, 3):
        return np.ascontiguousarray(wi), 3
    return None, None


def _call(tab, name, wi, x, width, out_shape):
    lib = _lib if _loaded else load()
    if lib is None:
        return None
    parts = _parts(tab)
    x = np.atleast_2d(np.asarray(x, np.float64))
    if parts is None or x.ndim != 2 or x.shape[1] != width:
        return None
    structs, nparts, bounds = parts
    n = len(x)
    wi, stride = _wi_arg(wi, n)
    if wi is None:
        return None
    x = np.ascontiguousarray(x)
    out = np.empty((n,) + out_shape)
    args = [structs, nparts, None if bounds is None else bounds.ctypes.data, n, wi.ctypes.data, stride,
            x.ctypes.data, out.ctypes.data]
    if name == "ft_sample":
        pdf = np.empty(n)
        getattr(lib, name)(*args, pdf.ctypes.data)
        return out, pdf
    getattr(lib, name)(*args)
    return out


def sample(tab, wi, u):
    return _call(tab, "ft_sample", wi, u, 2, (3,))


def pdf(tab, wi, wo):
    return _call(tab, "ft_pdf", wi, wo, 3, ())


def invert(tab, wi, wo):
    return _call(tab, "ft_invert", wi, wo, 3, (2,))


def eval(tab, wi, wo):  # noqa: A001 (the Tables method's name)
    return _call(tab, "ft_eval", wi, wo, 3, (3,))


def rgl_eval(params, vndf, vndf_shape, rgb, rgb_shape, ndf, wo):
    """RGLMaterial._eval_chunk for one wi in C (see ft_rgl_eval for `params`), or None without
    the library. vndf: (patches, 9) and rgb: (patches, 12) float64 tables of that wi."""
    lib = _lib if _loaded else load()
    if lib is None:
        return None
    arrays = [np.ascontiguousarray(x, np.float64) for x in (params, vndf, rgb, ndf, wo)]
    params, vndf, rgb, ndf, wo = arrays
    (vny, vnx), (ry, rx) = vndf_shape, rgb_shape
    if (params.shape != (10,) or wo.ndim != 2 or wo.shape[1] != 3 or vndf.shape != ((vny - 1) * (vnx - 1), 9)
            or rgb.shape != ((ry - 1) * (rx - 1), 12) or ndf.ndim != 2):
        return None
    out = np.empty((len(wo), 3))

    def run(lo, hi):
        lib.ft_rgl_eval(hi - lo, wo[lo:].ctypes.data, params.ctypes.data, vndf.ctypes.data, vny, vnx,
                        rgb.ctypes.data, ry, rx, ndf.ctypes.data, ndf.shape[0], ndf.shape[1], out[lo:].ctypes.data)
    _split(len(wo), run)
    return out


def polar_grid(a, cos_b, sin_b, cap, wi, c, s):
    """halfvector.polar_grid_from_ab's nodes from its per-b-node part, in C (ft_polar_grid: the
    same bits): (wo, jac), or None without the library. a: (cells, qa); cos_b, sin_b, cap:
    (cells, qb); wi: (3,) in the frame; c, s: the frame's cosine and sine."""
    lib = _lib if _loaded else load()
    if lib is None:
        return None
    a, cos_b, sin_b, cap, wi = (np.ascontiguousarray(x, np.float64) for x in (a, cos_b, sin_b, cap, wi))
    cells, qa = a.shape
    qb = cos_b.shape[1]
    wo, jac = np.empty((cells * qa * qb, 3)), np.empty(cells * qa * qb)
    lib.ft_polar_grid(cells, qa, qb, a.ctypes.data, cos_b.ctypes.data, sin_b.ctypes.data, cap.ctypes.data,
                      wi.ctypes.data, float(c), float(s), wo.ctypes.data, jac.ctypes.data)
    return wo, jac


def _warp_call(warp, name, wi, x, width):
    lib = _lib if _loaded else load()
    if lib is None:
        return None
    x = np.ascontiguousarray(np.atleast_2d(np.asarray(x, np.float64)))
    if x.ndim != 2 or x.shape[1] != width:
        return None
    wi, stride = _wi_arg(wi, len(x))
    S = len(warp.theta_i)
    if wi is None or warp.tables.shape != (S, warp.ny - 1, warp.nx - 1, 9) or warp.tables.dtype != np.float64 \
            or not warp.tables.flags.c_contiguous:
        return None
    args = _Warp(warp.ny, warp.nx, S, int(warp.horizon), warp.theta_i.ctypes.data, warp.tables.ctypes.data)
    out = np.empty((len(x), 5 - width))
    jac = np.empty(len(x))
    getattr(lib, name)(ctypes.byref(args), len(x), wi.ctypes.data, stride, x.ctypes.data, out.ctypes.data,
                       jac.ctypes.data)
    return out, jac


def warp_to_s(warp, wi, wo):
    """rgl.WarpedCoords.to_s in C: (s, jac), or None without the library."""
    return _warp_call(warp, "ft_warp_to_s", wi, wo, 3)


def warp_from_s(warp, wi, s):
    """rgl.WarpedCoords.from_s in C: (wo, jac), or None without the library."""
    return _warp_call(warp, "ft_warp_from_s", wi, s, 2)


_pool = None
MIN_SHARE = 1 << 16     # the fewest nodes worth a thread of their own


def _split(n, run):
    """run(lo, hi) over [0, n) in one slice per core, in threads (ctypes lets go of the GIL
    during the call): the baker's quadrature evaluates tens of millions of nodes per wi,
    one core at a time before (measured, 4.2 M nodes of chm_mint, 2 cores: see the note of
    issue 24). Small calls run in this thread."""
    global _pool
    parts = min(threads.workers(), n // MIN_SHARE)
    if parts < 2:
        run(0, n)
        return
    with _lock:
        if _pool is None:
            from concurrent.futures import ThreadPoolExecutor
            _pool = ThreadPoolExecutor(threads.workers(), thread_name_prefix="flowbsdf-eval")
    edges = [n * k // parts for k in range(parts + 1)]
    for f in [_pool.submit(run, lo, hi) for lo, hi in zip(edges[:-1], edges[1:])]:
        f.result()


# ------------------------------------------------------------------------------ BLAS threads

def _openblas_threads():
    """(get, set) of the thread count of the OpenBLAS that numpy loaded, or None (another BLAS,
    or not found). Found among the process's libraries (Linux) or beside numpy (its wheels'
    numpy.libs/ or numpy/.dylibs/); loading an already loaded library returns that library."""
    import sys
    paths = []
    if sys.platform.startswith("linux"):
        try:
            with open("/proc/self/maps") as fh:
                paths = [line.split()[-1] for line in fh if "openblas" in line.rsplit("/", 1)[-1].lower()]
        except OSError:
            pass
    root = Path(np.__file__).resolve().parent
    paths += [str(p) for p in (*root.parent.glob("numpy.libs/*openblas*"), *root.glob(".dylibs/*openblas*"))]
    for path in dict.fromkeys(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for suffix in ("64_", ""):
            get = getattr(lib, f"openblas_get_num_threads{suffix}", None)
            set_ = getattr(lib, f"openblas_set_num_threads{suffix}", None)
            if get is not None and set_ is not None:
                set_.argtypes = [ctypes.c_int]
                return get, set_
    return None


_blas = []          # [(get, set) or None], found on first use
_blas_users = [0, None]     # how many are inside one_blas_thread, and the thread count to restore


class one_blas_thread:
    """Context manager (and decorator): OpenBLAS in one thread inside, restored when the last
    one leaves. The baker calls BLAS only for small matrix-vector products, whose OpenBLAS
    threads spin between calls (measured: a third of a chm_mint bake's CPU time, in sched_yield)
    and take the cores from the baker's own threads; a product's bits do not depend on
    OpenBLAS's thread count."""

    def __enter__(self):
        with _lock:
            if not _blas:
                try:
                    _blas.append(_openblas_threads())
                except Exception:        # noqa: BLE001 (never let this break a bake)
                    _blas.append(None)
            _blas_users[0] += 1
            if _blas[0] is not None and _blas_users[0] == 1:
                _blas_users[1] = _blas[0][0]()
                _blas[0][1](1)
        return self

    def __exit__(self, *exc):
        with _lock:
            _blas_users[0] -= 1
            if _blas[0] is not None and _blas_users[0] == 0:
                _blas[0][1](_blas_users[1])

    def __call__(self, fn):
        import functools

        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            with one_blas_thread():
                return fn(*args, **kwargs)
        return wrapped

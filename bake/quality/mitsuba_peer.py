"""Mitsuba 3's own `measured` plugin as a peer sampler (tests and benchmarks only).

    MitsubaMeasuredSampler(path).sample(wi, u) -> (wo, pdf)
    MitsubaMeasuredSampler(path).pdf(wi, wo)
    MitsubaMeasuredSampler(path).eval(wi, wo)        # f without the cosine, (N, 3) RGB

with our conventions: numpy (N, 3) directions in the local frame, pdf per steradian.
Mitsuba's `sample()` returns (BSDFSample, weight) and sets `bs.pdf` even where the
reflected direction falls below the horizon (its weight is 0 there): such samples, and
any other invalid one, come back here with pdf 0, so `metrics.relative_variance` and
`metrics.chi2_test` count them as lost.

Mitsuba is not a runtime dependency of FlowBSDF: it is imported lazily, and a missing
install raises FlowBSDFError with the command that installs it.

Variants (`variant=None` picks one):
- `llvm_ad_rgb` (vectorized: whole arrays per call, JIT-compiled by Dr.Jit) needs
  libLLVM >= 19. Older system LLVMs (Debian 12 ships 14 and 15) abort the process inside
  LLVM's code generator, which Python cannot catch. Debian 12 has it as a package:
  `apt-get install libllvm19` (-> /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1). Dr.Jit reads
  `DRJIT_LIBLLVM_PATH`; when it is unset this module points it at the newest libLLVM >= 19
  it finds in the usual library folders, before Dr.Jit starts its LLVM backend.
- `scalar_rgb` (one Python call per sample, ~100x slower) is the fallback when no
  libLLVM >= 19 is found or the LLVM backend does not come up.
`$FLOWBSDF_MITSUBA_VARIANT` overrides the automatic choice. Dr.Jit's LLVM backend uses
all cores by default (Dr.Jit 1.5 ignores `DRJIT_NUM_THREADS`): pass `threads=1`, which
calls `drjit.set_thread_count(1)`, for per-core throughput; `limit_threads(n)` is the
context manager `bake.quality.bench` uses.
"""
import contextlib
import glob
import os
import re
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from ..materials.base import as_dirs

LLVM_VARIANTS = ("llvm_ad_rgb", "llvm_rgb")
SCALAR_VARIANT = "scalar_rgb"
MIN_LLVM = 19
LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
            "/usr/local/lib")
CHUNK = 1 << 22     # directions per LLVM call (keeps Dr.Jit's temporaries bounded)


def _import_mitsuba():
    try:
        import mitsuba
    except ImportError as e:
        raise FlowBSDFError(
            f"the Mitsuba peer sampler needs the `mitsuba` package ({e}); it is a test/benchmark "
            "dependency only: `pip install mitsuba` (or `pip install -e '.[test]'`)") from None
    return mitsuba


def _llvm_version(path):
    """Major version from a libLLVM file name (libLLVM.so.19.1, libLLVM-19.so, libLLVM-19.so.1)."""
    name = os.path.basename(path)
    m = re.match(r"libLLVM(?:-(\d+)[.\d]*\.so(?:\.\d+)*|\.so\.(\d+)(?:\.\d+)*)$", name)
    if not m:
        return None
    return int(m.group(1) or m.group(2))


def find_libllvm(min_version=MIN_LLVM):
    """Path of the newest libLLVM shared library >= min_version in the usual folders, or None."""
    best = None
    for d in LIB_DIRS:
        for path in glob.glob(os.path.join(d, "libLLVM*.so*")):
            v = _llvm_version(path)
            if v is not None and v >= min_version and os.path.isfile(path):
                if best is None or v > best[0]:
                    best = (v, path)
    return None if best is None else best[1]


def llvm_available():
    """True where the LLVM variant can run: DRJIT_LIBLLVM_PATH names a library, or a
    libLLVM >= 19 is installed (this sets DRJIT_LIBLLVM_PATH to it, for Dr.Jit to read)."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        return os.path.isfile(env)
    lib = find_libllvm()
    if lib is None:
        return False
    os.environ["DRJIT_LIBLLVM_PATH"] = lib
    return True


def default_variant():
    """$FLOWBSDF_MITSUBA_VARIANT, else llvm_ad_rgb where libLLVM >= 19 is present, else scalar_rgb."""
    env = os.environ.get("FLOWBSDF_MITSUBA_VARIANT")
    if env:
        return env
    if llvm_available():       # before Dr.Jit's LLVM backend starts: it reads the env var once
        mi = _import_mitsuba()
        for v in LLVM_VARIANTS:
            if v in mi.variants():
                return v
    return SCALAR_VARIANT


@contextlib.contextmanager
def _variant(mi, variant):
    """Switch Mitsuba's (process-global) variant for the block, and restore the previous one."""
    old = mi.variant()
    if old != variant:
        mi.set_variant(variant)
    try:
        yield
    finally:
        if old is not None and old != variant:
            mi.set_variant(old)


POLE_NUDGE = 1e-6


def _off_pole(wi):
    """wi exactly at the normal, moved by 1e-6 rad toward +x. At wi = (0, 0, 1) Mitsuba 3.9.1's
    LLVM variant evaluates the `measured` plugin with its lobe rotated (eval off by up to 37 %
    on chm_mint, rv 0.36 instead of 0.09), while its scalar variant and our RGL reader agree;
    1e-6 rad off the pole both variants agree with the reader (and with each other)."""
    pole = (wi[:, 0] == 0) & (wi[:, 1] == 0)
    if not pole.any():
        return wi
    wi = np.array(wi, dtype=np.float64)
    wi[pole, 0] = POLE_NUDGE
    return wi


class MitsubaMeasuredSampler:
    """Mitsuba 3's `measured` BSDF (an RGL `.bsdf` file) behind our sampler protocol."""

    name = "mitsuba"

    def __init__(self, path, variant=None, threads=None):
        path = Path(path)
        if not path.is_file():
            raise FlowBSDFError("no such RGL file", path)
        if variant is None:
            variant = default_variant()
        elif variant.startswith("llvm") and not llvm_available():
            raise FlowBSDFError(
                f"Mitsuba variant {variant!r} needs libLLVM >= {MIN_LLVM} (older ones abort the process): "
                "Debian 12: `apt-get install libllvm19`, or set DRJIT_LIBLLVM_PATH; or use variant='scalar_rgb'")
        mi = _import_mitsuba()
        if variant not in mi.variants():
            raise FlowBSDFError(f"Mitsuba variant {variant!r} is not in this build "
                                f"(available: {', '.join(mi.variants())})")
        self.path, self.variant = path, variant
        self.vectorized = not variant.startswith("scalar")
        import drjit as dr
        self._mi, self._dr = mi, dr
        if self.vectorized and not dr.has_backend(dr.JitBackend.LLVM):
            raise FlowBSDFError(
                f"Mitsuba variant {variant!r} needs Dr.Jit's LLVM backend, which did not start: "
                f"install libLLVM >= {MIN_LLVM} (Debian 12: `apt-get install libllvm19`) or set "
                "DRJIT_LIBLLVM_PATH; or use variant='scalar_rgb'")
        if threads is not None:
            dr.set_thread_count(int(threads))
        with _variant(mi, variant):
            try:
                self._bsdf = mi.load_dict({"type": "measured", "filename": str(path)})
            except Exception as e:   # Mitsuba raises RuntimeError with its own message
                raise FlowBSDFError(f"Mitsuba could not load the file: {e}", path) from None
            self._ctx = mi.BSDFContext()

    def __repr__(self):
        return f"MitsubaMeasuredSampler({self.path.name!r}, variant={self.variant!r})"

    @contextlib.contextmanager
    def limit_threads(self, n=1):
        """Run the block with Dr.Jit's thread pool limited to n threads."""
        dr = self._dr
        old = dr.thread_count()
        dr.set_thread_count(int(n))
        try:
            yield
        finally:
            dr.set_thread_count(old)

    # ------------------------------------------------------------------ the protocol

    def sample(self, wi, u):
        u = np.atleast_2d(np.asarray(u, float))
        wi, _ = as_dirs(wi, np.zeros((len(u), 3)))
        call = self._sample_llvm if self.vectorized else self._sample_scalar
        wo, pdf = self._chunked(call, wi, u)
        wo = wo.astype(np.float64)
        pdf = pdf.astype(np.float64)
        ok = (wo[:, 2] > 0) & np.isfinite(pdf) & (pdf > 0) & np.all(np.isfinite(wo), axis=1)
        return wo, np.where(ok, pdf, 0.0)

    def pdf(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        call = self._pdf_llvm if self.vectorized else self._pdf_scalar
        pdf = self._chunked(call, wi, wo)[0].astype(np.float64)
        return np.where(np.isfinite(pdf) & (pdf > 0) & (wo[:, 2] > 0), pdf, 0.0)

    def eval(self, wi, wo):
        """f without the cosine (Mitsuba's eval is f·cos theta_o), RGB, 0 below the horizon."""
        wi, wo = as_dirs(wi, wo)
        call = self._eval_llvm if self.vectorized else self._eval_scalar
        value = self._chunked(call, wi, wo)[0].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(wo[:, 2:3] > 0, value / wo[:, 2:3], 0.0)

    # ------------------------------------------------------------------ back ends

    def _chunked(self, call, a, b):
        n = len(a)
        with _variant(self._mi, self.variant):
            if n <= CHUNK or not self.vectorized:
                return call(a, b)
            parts = [call(a[s:s + CHUNK], b[s:s + CHUNK]) for s in range(0, n, CHUNK)]
        return tuple(np.concatenate(p) for p in zip(*parts))

    def _si(self, wi):
        mi, dr = self._mi, self._dr
        si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
        si.wi = self._vec(_off_pole(wi))
        return si

    def _vec(self, w):
        w = np.ascontiguousarray(w.T, dtype=np.float32)
        return self._mi.Vector3f(w[0], w[1], w[2])

    def _sample_llvm(self, wi, u):
        mi = self._mi
        n = len(u)
        u = np.ascontiguousarray(u.T, dtype=np.float32)
        bs, _ = self._bsdf.sample(self._ctx, self._si(wi), mi.Float(np.full(n, 0.5, np.float32)),
                                  mi.Point2f(u[0], u[1]))
        return np.array(bs.wo).T, np.array(bs.pdf)

    def _pdf_llvm(self, wi, wo):
        return (np.array(self._bsdf.pdf(self._ctx, self._si(wi), self._vec(wo))),)

    def _eval_llvm(self, wi, wo):
        return (np.array(self._bsdf.eval(self._ctx, self._si(wi), self._vec(wo))).T,)

    def _scalar_loop(self, wi, other, step, width):
        mi = self._mi
        si = mi.SurfaceInteraction3f()
        wi = _off_pole(wi)
        out = np.zeros((len(wi), width), np.float32)
        last = None
        for k in range(len(wi)):
            key = tuple(wi[k])
            if key != last:
                si.wi = mi.Vector3f(*key)
                last = key
            out[k] = step(si, other[k])
        return out

    def _sample_scalar(self, wi, u):
        mi, bsdf, ctx = self._mi, self._bsdf, self._ctx

        def step(si, uk):
            bs, _ = bsdf.sample(ctx, si, 0.5, mi.Point2f(float(uk[0]), float(uk[1])))
            return (*bs.wo, bs.pdf)

        out = self._scalar_loop(wi, u, step, 4)
        return out[:, :3], out[:, 3]

    def _pdf_scalar(self, wi, wo):
        mi, bsdf, ctx = self._mi, self._bsdf, self._ctx
        out = self._scalar_loop(wi, wo, lambda si, w: bsdf.pdf(ctx, si, mi.Vector3f(*w)), 1)
        return (out[:, 0],)

    def _eval_scalar(self, wi, wo):
        mi, bsdf, ctx = self._mi, self._bsdf, self._ctx
        return (self._scalar_loop(wi, wo, lambda si, w: np.array(bsdf.eval(ctx, si, mi.Vector3f(*w))), 3),)

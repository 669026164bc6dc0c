"""Build step of the optional C fast path of bake.core.tables (everything else is in pyproject.toml).

bake/maths/_tables_c.c is plain C (no Python API), loaded with ctypes by bake/maths/fasttables.py; it
is built here as an "extension module" only because that is how setuptools builds and
installs a shared library (`pip install -e .` puts it beside the source, in bake/). The
build is optional: without a C compiler, or if it fails, the install goes on and
bake.maths.fasttables compiles the library on first use, or falls back to numpy.
"""
import hashlib
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

SOURCE = "bake/maths/_tables_c.c"
SHA = hashlib.sha256((Path(__file__).resolve().parent / SOURCE).read_bytes()).hexdigest()


class OptionalBuildExt(build_ext):
    """build_ext that warns instead of failing: the C library is an optimization."""

    def run(self):
        try:
            super().run()
        except Exception as e:  # noqa: BLE001 (compiler missing, unsupported flags, ...)
            self.warn(f"flowbsdf: C tables library not built ({e}); bake.core.tables will compile "
                      "it on first use or use numpy")

    def build_extension(self, ext):
        try:
            super().build_extension(ext)
        except Exception as e:  # noqa: BLE001
            self.warn(f"flowbsdf: C tables library not built ({e}); bake.core.tables will compile "
                      "it on first use or use numpy")


setup(
    ext_modules=[Extension(
        "bake.maths._tables_c", [SOURCE],
        # the source hash lets bake.maths.fasttables spot a library built from an older source;
        # -ffp-contract=off: no fused multiply-add (results must round as numpy's do)
        define_macros=[("FT_SOURCE_SHA", f'"{SHA}"')],
        # -fopenmp-simd + libmvec: glibc's vector math in the block loops (x86-64 Linux; where
        # this fails, bake.maths.fasttables compiles it on first use without, -DFT_NO_MVEC)
        extra_compile_args=["-O2", "-ffp-contract=off", "-fno-math-errno", "-std=c99", "-fopenmp-simd"],
        libraries=["mvec", "m"],
        optional=True,
    )],
    cmdclass={"build_ext": OptionalBuildExt},
)

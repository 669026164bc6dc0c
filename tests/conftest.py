from pathlib import Path

import pytest

from bake.materials.rgl import SHARED_FILES as RGL_FILES, shared_dir as rgl_dir  # noqa: F401 (tests import them from here)

ROOT = Path(__file__).resolve().parents[1]


def rgl_path(name):
    path = rgl_dir() / f"{name}.bsdf"
    if not path.is_file():
        pytest.skip(f"shared RGL data not found at {path} (set FLOWBSDF_RGL_DIR)")
    return path


@pytest.fixture
def rgl():
    """rgl(name) -> path of a shared RGL file, or skip the test with the reason."""
    return rgl_path


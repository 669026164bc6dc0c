import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RGL_FILES = [
    "paper_white_rgb", "colodur_napoli_4f_rgb", "satin_rosaline_rgb", "cm_military_green_rgb",
    "cc_nothern_aurora_rgb", "vch_golden_yellow_rgb", "irid_flake_paint1_rgb",
    "cc_green_malachite_rgb", "ilm_solo_m_68_rgb", "chm_mint_rgb",
]


def rgl_dir():
    """Where the shared RGL files live: $FLOWBSDF_RGL_DIR, else ../shared/data/rgl beside the repo."""
    return Path(os.environ.get("FLOWBSDF_RGL_DIR", ROOT.parent / "shared" / "data" / "rgl"))


def rgl_path(name):
    path = rgl_dir() / f"{name}.bsdf"
    if not path.is_file():
        pytest.skip(f"shared RGL data not found at {path} (set FLOWBSDF_RGL_DIR)")
    return path


@pytest.fixture
def rgl():
    """rgl(name) -> path of a shared RGL file, or skip the test with the reason."""
    return rgl_path

"""open_sampler (bake/core/sampler.py): every kind it opens without files keeps the sampler contract."""
import numpy as np
import pytest

from bake import FlowBSDFError, Sampler, open_sampler
from bake.maths.geometry import incident
from bake.materials import open_material
from bake.core.sampler import KINDS, RENDER_KINDS
from contract import assert_sampler_contract

PLASTIC = {"kind": "analytic", "model": "plastic", "albedo": [0.5, 0.3, 0.2], "alpha": 0.2}
WITHOUT_FILES = ("uniform", "cosine", "ggx", "ideal", "ideal-binned")


@pytest.mark.parametrize("kind", WITHOUT_FILES)
def test_sampler_keeps_the_contract(kind):
    sampler = open_sampler(kind, open_material(PLASTIC))
    assert isinstance(sampler, Sampler)
    u = np.random.default_rng(3).random((20000, 2))
    # the ideal tabulations lose the samples whose half vector reflects below the horizon
    binning = "halfvector" if kind.startswith("ideal") else "cosine"
    assert_sampler_contract(sampler, incident(50.0, 0.7), u, pdf_rtol=1e-6, max_lost=0.01,
                            chi2=dict(n=100_000, n_tests=len(WITHOUT_FILES), seed=5, binning=binning))


def test_kinds_and_aliases():
    mat = open_material(PLASTIC)
    assert set(RENDER_KINDS) <= set(KINDS)
    assert open_sampler("ggx-fit", mat, ideal=open_sampler("ideal", mat, resolution=16)).name == "ggx"
    with pytest.raises(FlowBSDFError, match="unknown sampler"):
        open_sampler("gxx", mat)

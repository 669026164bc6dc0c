"""Write bake/export/ggx_albedo.npz: the albedo of Cycles' Glossy GGX lobes (colour 1) at the
closure fit's knots, over its grid of roughness and anisotropy (closure_fit.KNOTS_DEG, ALPHAS,
ANISOTROPY), each from 2^14 stratified samples of the lobe's own sampling: within ~0.2 % (1024
samples, what a fit at other angles computes, reach 2.5 % on wide anisotropic lobes). The fit
keeps kd + sum_j ks_j A_j equal to the baked albedo with these A_j. Rerun when that grid changes
(the fit then ignores the stale table and computes, slower and less exactly). ~3 min on 2 cores.

    .venv/bin/python scripts/ggx_albedo_table.py
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bake.export import closure_fit  # noqa: E402

if __name__ == "__main__":
    closure_fit.write_albedo_table()
    print(f"wrote {closure_fit.ALBEDO_TABLE}")

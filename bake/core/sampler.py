"""The sampler contract, and every sampler by name (`open_sampler`).

A sampler draws outgoing directions for an incident one, Mitsuba style. Directions are
(N, 3) arrays in the local frame (z = normal, wi pointing away from the surface); a single
wi of shape (3,) serves every row; pdf is per steradian.

    name                        what reports, plots and renders call it
    sample(wi, u) -> (wo, pdf)  u uniform in [0,1)², shape (N, 2); a lost sample (below
                                the horizon, or nothing to sample) has pdf 0
    pdf(wi, wo) -> pdf          the density sample() draws from; 0 below the horizon
    invert(wi, wo) -> u         optional (tables, flow): the u that sample() maps to wo
    eval(wi, wo) -> f           optional (tables, Mitsuba's peer): the sampler's own BSDF
                                value (RGB, without the cosine)

tests/contract.py checks a sampler against this contract (assert_sampler_contract).

The kinds `open_sampler` knows (`ggx-fit`, the report's old label, is an alias of `ggx`):

    uniform         uniform hemisphere (bake/core/baselines.py)
    cosine          cosine-weighted hemisphere
    ggx             the GGX + diffuse lobe fitted to the material (baselines.fit_ggx)
    ideal           the ideal tabulation, exact per distinct wi (bake/core/ideal.py IdealSampler)
    ideal-binned    the ideal tabulation at fixed incident bins, 1 degree apart (FineIdeal): what
                    renders use, where every pixel has its own wi
    tables          baked tables, the file at `path` (.exr; carried where they say so:
                    bake/core/carried.py, as the OSL back end renders them)
    flow            a trained flow, the file at `path` (.flow.npz)

Whether a manifest entry's files are current (built from its material and settings as they are
now) is the pipeline's business: bake/plumbing/pipeline.py's open_baked opens an entry's tables
or flow from an output folder, current only.

RENDER_KINDS are the names the reference tracer, `flowbsdf render/compare` and a manifest's
[run.render] accept; the tracer's `ideal` is `ideal-binned`.
"""
from typing import Protocol, runtime_checkable

from ..errors import FlowBSDFError

KINDS = ("uniform", "cosine", "ggx", "ideal", "ideal-binned", "tables", "flow")
ALIASES = {"ggx-fit": "ggx"}
RENDER_KINDS = ("tables", "flow", "ideal", "ggx", "cosine")
RENDER_KIND = {"ideal": "ideal-binned"}


@runtime_checkable
class Sampler(Protocol):
    name: str

    def sample(self, wi, u): ...

    def pdf(self, wi, wo): ...


@runtime_checkable
class Invertible(Sampler, Protocol):
    def invert(self, wi, wo): ...


def canonical_kind(kind):
    """`kind` with its alias resolved (ggx-fit -> ggx)."""
    return ALIASES.get(kind, kind)


def open_sampler(kind, material, path=None, ideal=None, **options):
    """The sampler `kind` (see the module's docstring) for `material`. `path` is the file tables
    and flow are read from; `ideal` is the ideal sampler the GGX fit samples from (a small one by
    default); `options` go to the ideal samplers' constructors (resolution, ...). FlowBSDFError
    when it cannot be built."""
    from .baselines import CosineSampler, UniformSampler, fit_ggx
    from .ideal import FineIdeal, IdealSampler
    kind = canonical_kind(kind)
    if kind == "uniform":
        return UniformSampler()
    if kind == "cosine":
        return CosineSampler()
    if kind == "ggx":
        return fit_ggx(material, ideal or IdealSampler(material, max_tables=16))
    if kind == "ideal":
        return IdealSampler(material, **options)
    if kind == "ideal-binned":
        return FineIdeal(material, **options)
    if kind in ("tables", "flow") and path is None:
        raise FlowBSDFError(f"the {kind} sampler reads a file: give its path")
    if kind == "tables":
        from .carried import as_rendered
        from .table_files import open_tables
        return as_rendered(open_tables(path), material)
    if kind == "flow":
        from .flow import load_model
        return load_model(path)
    raise FlowBSDFError(f"unknown sampler {kind!r} (one of {', '.join(KINDS)})")

"""A BSDF sampler per scene material, by the name a render asks for (bake/core/sampler.py's
RENDER_KINDS: tables | flow | ideal | ggx | cosine; `ideal` is the binned ideal tabulation).
Tables and flows come from the manifest material's files under `tables_dir`, current only
(pipeline.open_baked); the reference tracer (bake/tracer/) renders whatever it is handed."""
import time

from ..core.sampler import RENDER_KIND, RENDER_KINDS, canonical_kind
from ..errors import FlowBSDFError
from .pipeline import open_baked


def make_sampler(name, scene_material, tables_dir="out"):
    """The sampler `name` for a SceneMaterial; FlowBSDFError when it cannot be built."""
    name = canonical_kind(name)
    if name not in RENDER_KINDS:
        raise FlowBSDFError(f"unknown sampler {name!r} (one of {', '.join(RENDER_KINDS)})")
    if name in ("tables", "flow") and scene_material.entry is None:
        raise FlowBSDFError(f"material {scene_material.name!r} is inline: no baked tables "
                            "(give it `manifest = NAME` or `sampler = ...`)" if name == "tables" else
                            f"material {scene_material.name!r} is inline: no flow model")
    return open_baked(RENDER_KIND.get(name, name), scene_material.entry, scene_material.material, tables_dir)


def scene_samplers(scene, name, tables_dir="out", log=print):
    """One sampler per scene material: `name` for learned materials, their own otherwise."""
    out = []
    for sm in scene.materials:
        which = name if sm.learned else sm.sampler
        t0 = time.perf_counter()
        out.append(make_sampler(which, sm, tables_dir))
        dt = time.perf_counter() - t0
        if dt > 1.0:
            log(f"[sampler] {sm.name}: {which} ready in {dt:.1f}s")
    return out

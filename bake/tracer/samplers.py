"""Build a BSDF sampler by name for a scene material: tables | flow | ideal | ggx | cosine.

- tables: the baked tables of a manifest material (out/tables/<name>.exr, current only)
- flow:   the trained flow (out/models/<name>.flow.npz); slow, numpy inference
- ideal:  `FineIdeal`, the stand-in for Mitsuba's tabulated sampling: the ideal
          tabulation of f·cos (bake/ideal.py's Table, 256 x 512 half-vector cells) at
          incident elevations 1 degree apart (isotropic) or 3 x 6 degrees in (theta, phi)
          (anisotropic), each wi served by its nearest bin; tables are built lazily when a
          bin is first needed, and sample() and pdf() are exactly consistent
- ggx:    the fitted GGX + diffuse lobe (bake.baselines.fit_ggx)
- cosine: cosine-weighted hemisphere
"""
import time

import numpy as np

from ..errors import FlowBSDFError
from ..geometry import theta_phi
from ..ideal import Table
from ..warps import rotate_z

SAMPLERS = ("tables", "flow", "ideal", "ggx", "cosine")


class FineIdeal:
    name = "ideal"

    def __init__(self, material, theta_step_deg=1.0, resolution=256, supersample=2, phi_step_deg=6.0):
        self.material = material
        self.iso = bool(material.isotropic)
        self.step = np.radians(theta_step_deg if self.iso else 3.0)
        self.phi_step = np.radians(phi_step_deg)
        self.n_theta = int(np.ceil((np.pi / 2) / self.step)) + 1
        self.n_phi = 1 if self.iso else int(round(2 * np.pi / self.phi_step))
        self.resolution, self.supersample = resolution, supersample
        self.tables = {}
        self.build_seconds = 0.0

    def _bins(self, wi):
        theta, phi = theta_phi(wi)
        kt = np.clip(np.rint(theta / self.step), 0, self.n_theta - 1).astype(np.int64)
        if self.iso:
            return kt, phi         # rotate by phi_i to the bin's canonical frame
        kp = np.mod(np.rint(phi / self.phi_step), self.n_phi).astype(np.int64)
        return kt * self.n_phi + kp, np.zeros_like(phi)

    def _table(self, key):
        tab = self.tables.get(key)
        if tab is None:
            t0 = time.perf_counter()
            kt, kp = divmod(int(key), self.n_phi)
            th = min(kt * self.step, np.radians(89.9))
            ph = kp * self.phi_step
            wi = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
            tab = self.tables[key] = Table(self.material, wi, self.resolution, self.supersample)
            self.build_seconds += time.perf_counter() - t0
        return tab

    def prepare(self, theta_max_deg=90.0):
        """Build every bin up front (so timings exclude the tabulation); isotropic only
        (the anisotropic grid has ~1900 bins: those are built when first needed)."""
        if not self.iso:
            return
        for kt in range(self.n_theta):
            if kt * self.step <= np.radians(theta_max_deg) + 1e-9:
                for kp in range(self.n_phi):
                    self._table(kt * self.n_phi + kp)

    def sample(self, wi, u):
        wi = np.atleast_2d(wi)
        keys, rot = self._bins(wi)
        wo = np.zeros((len(wi), 3))
        wo[:, 2] = -1.0
        pdf = np.zeros(len(wi))
        for key in np.unique(keys):
            idx = np.flatnonzero(keys == key)
            tab = self._table(key)
            if tab.total <= 0.0:
                continue
            w, pdf[idx] = tab.sample_dir(u[idx])
            wo[idx] = rotate_z(w, rot[idx])
        return wo, pdf

    def pdf(self, wi, wo):
        wi, wo = np.atleast_2d(wi), np.atleast_2d(wo)
        keys, rot = self._bins(wi)
        out = np.zeros(len(wo))
        for key in np.unique(keys):
            idx = np.flatnonzero(keys == key)
            tab = self._table(key)
            if tab.total <= 0.0:
                continue
            out[idx] = tab.pdf_dir(rotate_z(wo[idx], -rot[idx]))
        return out


def make_sampler(name, scene_material, tables_dir="out", log=print):
    """The sampler `name` for a SceneMaterial; FlowBSDFError when it cannot be built."""
    from ..baselines import CosineSampler, fit_ggx
    from ..ideal import IdealSampler
    mat = scene_material.material
    if name == "cosine":
        return CosineSampler()
    if name == "ggx":
        return fit_ggx(mat, IdealSampler(mat, max_tables=16))
    if name == "ideal":
        return FineIdeal(mat)
    entry = scene_material.entry
    if name == "tables":
        if entry is None:
            raise FlowBSDFError(f"material {scene_material.name!r} is inline: no baked tables "
                                "(give it `manifest = NAME` or `sampler = ...`)")
        from ..pipeline import open_current_tables, table_path
        from pathlib import Path
        path = table_path(tables_dir, entry.name)
        if not Path(path).is_file():
            raise FlowBSDFError(f"no baked tables for {entry.name!r} (run flowbsdf bake)", path)
        tabs = open_current_tables(entry, tables_dir, None)
        if tabs is None:
            raise FlowBSDFError(f"the tables of {entry.name!r} are stale (the material, model or "
                                "bake settings changed): run flowbsdf bake", path)
        return tabs
    if name == "flow":
        if entry is None:
            raise FlowBSDFError(f"material {scene_material.name!r} is inline: no flow model")
        from ..pipeline import model_path
        from ..flow import load_model
        path = model_path(tables_dir, entry.name)
        if not path.is_file():
            raise FlowBSDFError(f"no trained flow for {entry.name!r} (run flowbsdf train); "
                                "the flow sampler is not available for it", path)
        return load_model(path)
    raise FlowBSDFError(f"unknown sampler {name!r} (one of {', '.join(SAMPLERS)})")


def scene_samplers(scene, name, tables_dir="out", log=print):
    """One sampler per scene material: `name` for learned materials, their own otherwise."""
    out = []
    for sm in scene.materials:
        which = name if sm.learned else sm.sampler
        t0 = time.perf_counter()
        out.append(make_sampler(which, sm, tables_dir, log))
        dt = time.perf_counter() - t0
        if dt > 1.0:
            log(f"[sampler] {sm.name}: {which} ready in {dt:.1f}s")
    return out

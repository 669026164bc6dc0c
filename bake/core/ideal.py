"""The ideal sampler: f·cos tabulated finely per incident direction and sampled exactly.

It is the "tabulation limit" every learned sampler is compared against, and a fast
exact source of training samples. For each distinct wi it tabulates the target
density max(lum f, 0)·cos(theta_o) over the half vector m, on a grid in the unit square
u = (sqrt(2 theta_m / pi), (phi_m + pi) / 2 pi) (the RGL parameterization, bake/maths/warps.py's
half_vector: the sqrt map puts resolution near the normal, where every microfacet lobe
lives, at any theta_i).
The density is piecewise constant in u, so sample() is a piecewise-linear bijection of
[0,1)² and pdf() is its exact density:

    pdf_omega(wo) = p_u(u) / |d omega_o / d u|,  |d omega_o / d u| = 4 (wi·m) sin(theta_m) pi u1 2 pi

Mass of a cell whose half vectors partly reflect below the horizon is spread over the
whole cell, so a small fraction of samples can land below the surface: those come back
with pdf 0 (lost, never re-weighted), and pdf() integrates to 1 minus that fraction.

    Table           one wi's tabulation: sample_dir, pdf_dir
    IdealSampler    a Table per distinct wi (isotropic materials: per theta_i), kept in a cache
    training_pairs  exact (wi, x1) pairs for the trainer
    BinnedIdeal     Tables at fixed theta_i bins, nearest bin: plain tabulation at a memory budget
    FineIdeal       Tables 1 degree apart, built lazily: the ideal sampler of renders
"""
import functools
import threading
import time

import numpy as np

from ..materials.base import as_dirs
from ..maths.geometry import luminance, theta_phi
from ..maths.warps import HALF_PI, dwo_du_of, half_vector, rotate_z, u_of_half_vector


@functools.lru_cache(maxsize=32)
def _sub_cells(n1, n2, s, r0, r1):
    """Stratified points inside the cells of rows r0:r1 of an n1 x n2 grid, (n1*s) x (n2*s)
    sub-cell centres u, their half vectors and sin(theta_m): the same for every wi (read-only,
    shared)."""
    g1 = (np.arange(n1 * s) + 0.5) / (n1 * s)
    g2 = (np.arange(n2 * s) + 0.5) / (n2 * s)
    u = np.stack(np.meshgrid(g1[r0 * s:r1 * s], g2, indexing="ij"), axis=-1).reshape(-1, 2)
    m = half_vector(u)
    sin_m = np.sin(HALF_PI * u[:, 0] * u[:, 0])      # dwo_du's sin(theta_m), which u alone decides
    for x in (u, m, sin_m):
        x.flags.writeable = False
    return u, m, sin_m


def _dot3(a, m):
    """The dot products of a (3,) or (n, 3) with the rows of m, added as np.sum(a * m, axis=-1)
    adds them (the same bits; numpy's reduction over a short last axis is slow)."""
    a = a.T if a.ndim == 2 else a
    return (a[0] * m[:, 0] + a[1] * m[:, 1]) + a[2] * m[:, 2]


def _mean_of_sub_cells(x):
    """x.mean(axis=(1, 3)) of x (rows, s, n2, s, 3), bit for bit: numpy adds the s x s sub-cells in
    order, (0, 0), (0, 1), ..., one trailing colour axis at a time (slow); here whole slices."""
    s = x.shape[1]
    total = None
    for i in range(s):
        for j in range(s):
            total = x[:, i, :, j] if total is None else total + x[:, i, :, j]
    return total / (s * s)


CHUNK = 1 << 17     # sub-cells per pass (smaller passes reuse their memory: ~10 % faster than 1 << 19)


class Table:
    """One wi's tabulated density: cell masses over the u grid, with their CDFs."""

    def __init__(self, material, wi, resolution, supersample):
        n1, n2 = resolution, 2 * resolution
        s = supersample
        self.wi = wi
        mass = np.zeros((n1, n2))
        rgb = np.zeros((n1, n2, 3))
        rows_per_chunk = max(1, CHUNK // (n2 * s * s))
        for r0 in range(0, n1, rows_per_chunk):
            r1 = min(n1, r0 + rows_per_chunk)
            u, m, sin_m = _sub_cells(n1, n2, s, r0, r1)
            # reflect(wi, m) and dwo_du(wi, m, u1) with wi.m taken once, in np.sum's order, and the
            # products in theirs: the same numbers, a third of the time (the table is built at
            # every angle the baker probes).
            cos_im = _dot3(wi, m)
            wo = (2.0 * cos_im)[:, None] * m - wi
            value = material.eval(wi, wo)
            jac = dwo_du_of(cos_im, sin_m, u[:, 0]) * (wo[:, 2] > 0)
            cos_o = np.maximum(wo[:, 2], 0.0)
            dens = np.maximum(luminance(value), 0.0) * cos_o * jac
            rows = r1 - r0
            mass[r0:r1] = dens.reshape(rows, s, n2, s).mean(axis=(1, 3))
            rgb[r0:r1] = _mean_of_sub_cells((value * (cos_o * jac)[:, None]).reshape(rows, s, n2, s, 3))
        cell_area = 1.0 / (n1 * n2)
        self.albedo_rgb = rgb.sum(axis=(0, 1)) * cell_area
        self.total = mass.sum() * cell_area
        self.shape = (n1, n2)
        if not self.total > 0.0:
            # Black for this wi: nothing to sample; pdf() is 0 everywhere.
            self.density = np.zeros((n1, n2))
            return
        self.density = mass / (mass.sum() * cell_area)       # p_u per cell, integrates to 1
        row_mass = mass.sum(axis=1)
        self.row_cdf = np.concatenate([[0.0], np.cumsum(row_mass)]) / row_mass.sum()
        with np.errstate(invalid="ignore", divide="ignore"):
            cond = np.cumsum(mass, axis=1) / row_mass[:, None]
        cond = np.where(row_mass[:, None] > 0, cond, (np.arange(1, n2 + 1) / n2)[None, :])
        cond = np.concatenate([np.zeros((n1, 1)), cond], axis=1)
        cond[:, -1] = 1.0
        # Row index + conditional CDF is one globally increasing array: one searchsorted for all rows.
        self.flat_cdf = (np.arange(n1)[:, None] + cond).ravel()

    def sample_u(self, u):
        """Map uniform u to the tabulated density in the unit square (piecewise linear, bijective)."""
        n1, n2 = self.shape
        row = np.clip(np.searchsorted(self.row_cdf, u[:, 0], side="right") - 1, 0, n1 - 1)
        lo, hi = self.row_cdf[row], self.row_cdf[row + 1]
        t1 = np.clip((u[:, 0] - lo) / np.where(hi > lo, hi - lo, 1.0), 0.0, 1.0)
        key = row + u[:, 1]
        k = np.clip(np.searchsorted(self.flat_cdf, key, side="right") - 1, 0, self.flat_cdf.size - 2)
        col = np.clip(k - row * (n2 + 1), 0, n2 - 1)
        c_lo = self.flat_cdf[row * (n2 + 1) + col] - row
        c_hi = self.flat_cdf[row * (n2 + 1) + col + 1] - row
        t2 = np.clip((u[:, 1] - c_lo) / np.where(c_hi > c_lo, c_hi - c_lo, 1.0), 0.0, 1.0)
        return np.stack([(row + t1) / n1, (col + t2) / n2], axis=-1)

    def density_u(self, v):
        n1, n2 = self.shape
        i = np.clip((v[:, 0] * n1).astype(np.int64), 0, n1 - 1)
        j = np.clip((v[:, 1] * n2).astype(np.int64), 0, n2 - 1)
        return self.density[i, j]

    def sample_dir(self, u):
        """(wo, pdf) in this table's frame; pdf 0 where the half vector reflects below the horizon.
        The pdf is pdf_dir(wo): a sample on a cell boundary whose round trip wo -> v lands in
        the neighbouring cell gets that cell's density, as pdf() says (the stress suite found
        3 in 2.5e6 disagreeing by up to 7e-4 when the pdf came from the sampled cell)."""
        m = half_vector(self.sample_u(u))
        w = (2.0 * _dot3(self.wi, m))[:, None] * m - self.wi         # reflect(wi, m)
        return w, self.pdf_dir(w)

    def pdf_dir(self, wo):
        """The solid-angle density of sample_dir at wo (this table's frame)."""
        h = self.wi[None, :] + wo
        m = h / np.sqrt(_dot3(h, h))[:, None]            # normalize(wi + wo)
        v = u_of_half_vector(m)
        u1 = v[:, 0]
        jac = dwo_du_of(_dot3(self.wi, m), np.sin(HALF_PI * u1 * u1), u1)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where((wo[:, 2] > 0) & (jac > 0), self.density_u(v) / jac, 0.0)


class IdealSampler:
    """Exact sampling of the tabulated target, one table per distinct (canonical) wi."""

    name = "ideal"
    tabulates_per_wi = True     # a table per distinct wi: a new wi per sample means a new table each

    def __init__(self, material, resolution=256, supersample=2, max_tables=512):
        self.material, self.resolution, self.supersample = material, resolution, supersample
        self.max_tables = max_tables
        self._tables = {}
        self._lock = threading.Lock()

    def _canonical(self, wi):
        """Isotropic materials: rotate wi to phi_i = 0 (the returned angle undoes it)."""
        if not self.material.isotropic:
            return wi, np.zeros(len(wi))
        theta_i, phi_i = theta_phi(wi)
        return np.stack([np.sin(theta_i), np.zeros_like(theta_i), np.cos(theta_i)], axis=-1), phi_i

    def table(self, wi):
        key = tuple(np.round(wi, 12))
        tab = self._tables.get(key)
        if tab is None:
            tab = Table(self.material, np.asarray(key, float), self.resolution, self.supersample)
            with self._lock:       # the baker samples from threads
                if key not in self._tables and len(self._tables) >= self.max_tables:
                    self._tables.pop(next(iter(self._tables)))
                tab = self._tables.setdefault(key, tab)
        return tab

    def _groups(self, wi):
        wi = np.round(wi, 12)
        if np.all(wi == wi[0]):        # the common case: one incident direction
            yield self.table(wi[0]), slice(None)
            return
        keys, inverse = np.unique(wi, axis=0, return_inverse=True)
        for k, key in enumerate(keys):
            yield self.table(key), np.flatnonzero(inverse.ravel() == k)

    def sample(self, wi, u):
        u = np.atleast_2d(np.asarray(u, float))
        wi, _ = as_dirs(wi, np.zeros((len(u), 3)))
        cwi, phi_i = self._canonical(wi)
        wo = np.zeros((len(u), 3))
        pdf = np.zeros(len(u))
        for tab, idx in self._groups(cwi):
            if tab.total <= 0.0:
                wo[idx, 2] = -1.0      # nothing to sample: an invalid direction with pdf 0
                continue
            wo[idx], pdf[idx] = tab.sample_dir(u[idx])
        return rotate_z(wo, phi_i), pdf

    def pdf(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        cwi, phi_i = self._canonical(wi)
        cwo = rotate_z(wo, -phi_i)
        out = np.zeros(len(wo))
        for tab, idx in self._groups(cwi):
            if tab.total <= 0.0:
                continue
            out[idx] = tab.pdf_dir(cwo[idx])
        return out

    def albedo(self, wi):
        """Directional albedo (RGB) by quadrature over the table: integral of f·cos over wo."""
        wi, _ = as_dirs(wi, np.zeros((1, 3)))
        cwi, _ = self._canonical(wi[:1])
        return self.table(cwi[0]).albedo_rgb


def training_pairs(material, domain, n, rng, theta_i, sampler=None):
    """n pairs (wi, x1): wi drawn from the given elevations (radians, isotropic: phi_i = 0),
    x1 = domain coordinates of wo drawn exactly from the ideal sampler for that wi.
    Samples lost below the horizon are redrawn, so x1 follows the normalized target."""
    sampler = sampler or IdealSampler(material)
    theta_i = np.asarray(theta_i, float)
    wi_out, x_out, have = [], [], 0
    while have < n:
        m = n - have
        t = theta_i[rng.integers(0, len(theta_i), m)]
        phi = np.zeros(m) if material.isotropic else rng.uniform(-np.pi, np.pi, m)
        s = np.sin(t)
        wi = np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(t)], axis=-1)
        wo, pdf = sampler.sample(wi, rng.random((m, 2)))
        ok = pdf > 0
        wi_out.append(wi[ok])
        x_out.append(domain.from_dir(wo[ok]))
        have += int(ok.sum())
    return np.concatenate(wi_out)[:n], np.concatenate(x_out)[:n]


class BinnedIdeal:
    """Plain tabulation: the ideal sampler's tables at fixed incident bins, each wi served by
    its nearest bin (no interpolation). The baseline the baked tables must beat at equal memory."""

    name = "plain"

    def __init__(self, material, theta_bins, resolution):
        self.theta_bins = np.sort(np.asarray(theta_bins, float))
        self.ideal = IdealSampler(material, resolution=resolution, max_tables=len(self.theta_bins) + 1)
        self.nbytes = len(self.theta_bins) * resolution * 2 * resolution * 4   # float32 cell masses

    @classmethod
    def with_memory(cls, material, theta_bins, nbytes):
        resolution = int(np.sqrt(nbytes / (len(theta_bins) * 8)))
        return cls(material, theta_bins, max(resolution, 2))

    def _snap(self, wi):
        theta, phi = theta_phi(wi)
        k = np.abs(theta[:, None] - self.theta_bins[None, :]).argmin(axis=1)
        t = self.theta_bins[k]
        return np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)], axis=-1)

    def sample(self, wi, u):
        u = np.atleast_2d(np.asarray(u, float))
        wi, _ = as_dirs(wi, np.zeros((len(u), 3)))
        return self.ideal.sample(self._snap(wi), u)

    def pdf(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        return self.ideal.pdf(self._snap(wi), wo)


class FineIdeal:
    """The ideal tabulation (`Table`, 256 x 512 half-vector cells) at incident elevations 1
    degree apart (isotropic) or 3 x 6 degrees in (theta, phi) (anisotropic), each wi served
    by its nearest bin: the stand-in for Mitsuba's tabulated sampling in renders, where every
    pixel has its own wi. A bin's table is built when first needed (`prepare` builds them
    all); sample() and pdf() are exactly consistent."""

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

    def _groups(self, keys):
        """(table, rows) per bin among `keys` that has something to sample."""
        for key in np.unique(keys):
            tab = self._table(key)
            if tab.total > 0.0:
                yield tab, np.flatnonzero(keys == key)

    def sample(self, wi, u):
        u = np.atleast_2d(np.asarray(u, float))
        wi, _ = as_dirs(wi, np.zeros((len(u), 3)))
        keys, rot = self._bins(wi)
        wo = np.zeros((len(u), 3))
        wo[:, 2] = -1.0            # a bin with nothing to sample: an invalid direction with pdf 0
        pdf = np.zeros(len(u))
        for tab, idx in self._groups(keys):
            w, pdf[idx] = tab.sample_dir(u[idx])
            wo[idx] = rotate_z(w, rot[idx])
        return wo, pdf

    def pdf(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        keys, rot = self._bins(wi)
        out = np.zeros(len(wo))
        for tab, idx in self._groups(keys):
            out[idx] = tab.pdf_dir(rotate_z(wo[idx], -rot[idx]))
        return out

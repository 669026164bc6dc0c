"""Vectorized (wavefront) unidirectional path tracer.

One pass traces one path per pixel, all pixels at once (in chunks): every bounce
intersects all live rays, then per material evaluates the true BSDF and samples the
next direction with that material's sampler. The BSDF value is always the material's
own `eval` (negative measured values included); only the sampling differs between samplers.

Modes
  mis:       next-event estimation (one light chosen uniformly, then a direction from
             it) combined with BSDF sampling by the power heuristic; the BSDF sampler's
             pdf() of light-sampled directions enters the weight.
  bsdf-only: only BSDF sampling finds the environment and the lamps it can hit. Delta
             lamps (point and spot of radius 0, sun of angle 0) can never be hit, so they
             are always sampled directly (no weight needed).
Lamps never block rays (as in Cycles): shadow rays ignore them, and a ray adds the emission
of every lamp it passes before the surface it hits. Camera rays skip lamps with camera false.
Russian roulette from depth 3: survive with probability min(1, max |throughput|) (at
least 0.05), the weight divided by it (unbiased). Paths stop at scene.max_depth bounces.

Frames: z = shading normal (flipped to the viewer's side), x = the shape's tangent
reference projected onto the tangent plane. Directions below the geometric surface
contribute nothing.
"""
import time
from dataclasses import dataclass, field

import numpy as np

from .scene import Hit

RR_DEPTH = 3


@dataclass
class Stats:
    paths: int = 0
    rays: int = 0
    seconds: float = 0.0
    sampling_seconds: float = 0.0     # inside sampler.sample and sampler.pdf
    eval_seconds: float = 0.0         # inside material.eval
    lost: int = 0                     # BSDF samples the sampler returned with pdf 0
    passes: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def sampling_share(self):
        """Share of the tracer's (CPU) time spent in sampler.sample and sampler.pdf."""
        return self.sampling_seconds / max(self.extra.get("worker_seconds", self.seconds), 1e-300)


def _frame(ns, tangent):
    t = tangent - ns * np.sum(tangent * ns, axis=1, keepdims=True)
    ln = np.linalg.norm(t, axis=1, keepdims=True)
    # fallback where the reference is (nearly) parallel to the normal
    a = np.where(np.abs(ns[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    fb = a - ns * np.sum(a * ns, axis=1, keepdims=True)
    t = np.where(ln > 1e-6, t / np.maximum(ln, 1e-300), fb / np.linalg.norm(fb, axis=1, keepdims=True))
    b = np.cross(ns, t)
    return t, b


def _to_local(v, t, b, n):
    return np.stack([np.sum(v * t, 1), np.sum(v * b, 1), np.sum(v * n, 1)], axis=1)


def _to_world(v, t, b, n):
    return v[:, :1] * t + v[:, 1:2] * b + v[:, 2:3] * n


def _power(a, b):
    a2, b2 = a * a, b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(a2 + b2 > 0, a2 / (a2 + b2), 0.0)


class PathTracer:
    def __init__(self, scene, samplers, mis=True, chunk=1 << 15):
        self.scene, self.samplers, self.mis = scene, samplers, bool(mis)
        self.chunk = int(chunk)
        self.stats = Stats()
        self.n_lights = len(scene.lights)
        self.sampled_lights = [l for l in scene.lights if self.mis or l.delta]

    # ------------------------------------------------------------------ one pass
    def render_pass(self, rng):
        """One sample per pixel: (H, W, 3) radiance."""
        cam = self.scene.camera
        W, H = cam.width, cam.height
        out = np.zeros((H * W, 3))
        t0 = time.perf_counter()
        for s in range(0, H * W, self.chunk):
            pix = np.arange(s, min(H * W, s + self.chunk))
            o, d = cam.rays(pix % W, pix // W, rng.random((len(pix), 2)))
            out[pix] = self.trace(o, d, rng)
        self.stats.seconds += time.perf_counter() - t0
        self.stats.paths += H * W
        self.stats.passes += 1
        return out.reshape(H, W, 3)

    def trace(self, o, d, rng):
        scene, st = self.scene, self.stats
        n = len(o)
        L = np.zeros((n, 3))
        beta = np.ones((n, 3))
        alive = np.arange(n)
        prev_pdf = np.zeros(n)          # BSDF pdf of the direction that led here
        prev_delta = np.ones(n, bool)   # camera rays: emitters seen with full weight
        for depth in range(scene.max_depth + 1):
            if alive.size == 0:
                break
            hit = scene.intersect(o, d)
            st.rays += len(o)
            kind = hit["kind"]
            # ---- emission found by this ray: the environment on a miss, every lamp the ray
            # passes before the surface it hits (lamps do not stop rays)
            miss = kind == Hit.NONE
            if scene.env is not None and miss.any():
                Le = scene.env.eval(d[miss])
                w = self._mis_weight_emitter(prev_pdf[miss], prev_delta[miss], scene.env.pdf(d[miss]))
                L[alive[miss]] += beta[miss] * Le * w[:, None]
            for lamp in scene.lamps:
                if depth == 0 and not lamp.camera:
                    continue
                m, t = lamp.intersect(o, d, hit["t"])
                if m.any():
                    om, dm, tm = o[m], d[m], t[m]
                    w = self._mis_weight_emitter(prev_pdf[m], prev_delta[m], lamp.pdf_hit(om, dm, tm))
                    L[alive[m]] += beta[m] * lamp.eval_hit(om, dm, tm) * w[:, None]
            surf = ~miss
            if depth == scene.max_depth or not surf.any():
                break
            # ---- keep surface hits
            sel = np.flatnonzero(surf)
            alive, beta, d = alive[sel], beta[sel], d[sel]
            p, ng, ns, tan, mat = (hit[k][sel] for k in ("p", "ng", "ns", "tangent", "mat"))
            flip = np.sum(ng * d, axis=1) > 0
            ng = np.where(flip[:, None], -ng, ng)
            ns = np.where(flip[:, None], -ns, ns)
            ns = np.where((np.sum(ns * ng, axis=1) > 0)[:, None], ns, ng)
            tx, ty = _frame(ns, tan)
            wi = _to_local(-d, tx, ty, ns)
            ok = wi[:, 2] > 0
            eps = 1e-4 * (1.0 + np.max(np.abs(p), axis=1))
            p_off = p + ng * eps[:, None]
            m_ids = mat
            # ---- next-event estimation
            if self.sampled_lights:
                self._direct(L, alive, beta, p_off, ng, wi, tx, ty, ns, m_ids, ok, rng)
            # ---- BSDF sampling
            wo_w = np.zeros_like(d)
            weight = np.zeros((len(sel), 3))
            pdf = np.zeros(len(sel))
            u = rng.random((len(sel), 2))
            for mid in np.unique(m_ids):
                idx = np.flatnonzero((m_ids == mid) & ok)
                if idx.size == 0:
                    continue
                sampler, material = self.samplers[mid], scene.materials[mid].material
                t1 = time.perf_counter()
                wo, pw = sampler.sample(wi[idx], u[idx])
                t2 = time.perf_counter()
                wo = np.asarray(wo, float)
                pw = np.asarray(pw, float)
                good = (pw > 0) & np.isfinite(pw) & (wo[:, 2] > 0)
                st.lost += int(np.sum(~good))
                f = material.eval(wi[idx], np.where(good[:, None], wo, [0.0, 0.0, 1.0]))
                t3 = time.perf_counter()
                st.sampling_seconds += t2 - t1
                st.eval_seconds += t3 - t2
                with np.errstate(divide="ignore", invalid="ignore"):
                    wt = f * (wo[:, 2] / pw)[:, None]
                weight[idx] = np.where(good[:, None], wt, 0.0)
                pdf[idx] = np.where(good, pw, 0.0)
                wo_w[idx] = _to_world(wo, tx[idx], ty[idx], ns[idx])
            above = np.sum(wo_w * ng, axis=1) > 0
            beta = beta * weight * above[:, None]
            # ---- Russian roulette
            if depth + 1 >= RR_DEPTH:
                q = np.clip(np.max(np.abs(beta), axis=1), 0.05, 1.0)
                survive = rng.random(len(q)) < q
                beta = beta / q[:, None]
                keep = survive
            else:
                keep = np.ones(len(beta), bool)
            keep &= np.any(beta != 0, axis=1) & (pdf > 0)
            alive, beta = alive[keep], beta[keep]
            o, d = p_off[keep], wo_w[keep]
            prev_pdf, prev_delta = pdf[keep], np.zeros(int(keep.sum()), bool)
        return L

    # ------------------------------------------------------------------ helpers
    def _mis_weight_emitter(self, bsdf_pdf, was_delta, light_pdf):
        """Weight of emission reached by BSDF sampling."""
        if not self.mis:
            return np.ones(len(bsdf_pdf))
        pl = light_pdf / self.n_lights
        return np.where(was_delta, 1.0, _power(bsdf_pdf, pl))

    def _direct(self, L, alive, beta, p, ng, wi, tx, ty, ns, m_ids, ok, rng):
        scene, st = self.scene, self.stats
        n = len(p)
        lights = self.sampled_lights
        pick = rng.integers(0, len(lights), n)
        u = rng.random((n, 2))
        wl = np.zeros((n, 3))
        dist = np.zeros(n)
        Li = np.zeros((n, 3))
        pl = np.zeros(n)
        delta = np.zeros(n, bool)
        for k, light in enumerate(lights):
            m = pick == k
            if m.any():
                wl[m], dist[m], Li[m], pl[m] = light.sample(p[m], u[m])
                delta[m] = light.delta
        # choosing one of len(lights) lights uniformly
        pl_sel = pl / len(lights)
        cand = ok & (pl_sel > 0) & (np.sum(wl * ng, axis=1) > 0) & np.any(Li != 0, axis=1)
        idx = np.flatnonzero(cand)
        if idx.size == 0:
            return
        tmax = np.where(np.isfinite(dist[idx]), dist[idx] * (1 - 1e-6) - 1e-6, np.inf)
        vis = ~scene.occluded(p[idx], wl[idx], tmax)
        st.rays += idx.size
        idx = idx[vis]
        if idx.size == 0:
            return
        wl_local = _to_local(wl[idx], tx[idx], ty[idx], ns[idx])
        front = wl_local[:, 2] > 0
        idx, wl_local = idx[front], wl_local[front]
        for mid in np.unique(m_ids[idx]):
            j = m_ids[idx] == mid
            ii, wloc = idx[j], wl_local[j]
            t1 = time.perf_counter()
            f = scene.materials[mid].material.eval(wi[ii], wloc)
            t2 = time.perf_counter()
            st.eval_seconds += t2 - t1
            w = np.ones(len(ii))
            if self.mis and not np.all(delta[ii]):
                pb = np.asarray(self.samplers[mid].pdf(wi[ii], wloc), float)
                st.sampling_seconds += time.perf_counter() - t2
                w = np.where(delta[ii], 1.0, _power(pl_sel[ii], pb))
            contrib = beta[ii] * f * (wloc[:, 2] * w / pl_sel[ii])[:, None] * Li[ii]
            np.add.at(L, alive[ii], contrib)


def render(scene, samplers, spp=16, seconds=None, mis=True, seed=0, progress=None, chunk=1 << 15, workers=1):
    """Average of `spp` passes (or as many as fit in `seconds`, at least one per worker).
    Pass k uses the random stream (seed, k), so the image does not depend on `workers`
    (optional processes, forked: Linux/macOS; pass k goes to worker k mod workers).

    Returns (image (H, W, 3), variance of the mean per pixel and channel (H, W, 3), Stats).
    With workers, Stats.seconds is wall time and the other timings are summed over workers.
    """
    if workers > 1:
        return _render_parallel(scene, samplers, spp, seconds, mis, seed, progress, chunk, workers)
    t0 = time.perf_counter()
    s1, s2, k, stats = _passes(scene, samplers, mis, chunk, seed, range(spp) if seconds is None else None,
                               seconds, t0, progress)
    return _finish(s1, s2, k, stats)


def _passes(scene, samplers, mis, chunk, seed, ks, seconds, t0, progress=None, start=0, step=1):
    tracer = PathTracer(scene, samplers, mis=mis, chunk=chunk)
    H, W = scene.camera.height, scene.camera.width
    s1 = np.zeros((H, W, 3))
    s2 = np.zeros((H, W, 3))
    n = 0
    k = start
    while True:
        if ks is not None:
            if k >= len(ks):
                break
            key = ks[k]
        else:
            key = k
        img = tracer.render_pass(np.random.default_rng([seed, key]))
        s1 += img
        s2 += img * img
        n += 1
        k += step
        elapsed = time.perf_counter() - t0
        if progress is not None:
            progress(n, elapsed, tracer.stats)
        if ks is None and elapsed >= seconds:
            break
    return s1, s2, n, tracer.stats


def _finish(s1, s2, k, stats):
    mean = s1 / k
    var = np.maximum(s2 / k - mean * mean, 0.0) / max(k - 1, 1)
    stats.extra["spp"] = k
    return mean, var, stats


_JOB = None


def _worker(args):
    w, workers, spp, seconds = args
    scene, samplers, mis, chunk, seed = _JOB
    t0 = time.perf_counter()
    return _passes(scene, samplers, mis, chunk, seed, range(spp) if seconds is None else None, seconds, t0,
                   start=w, step=workers)


def _render_parallel(scene, samplers, spp, seconds, mis, seed, progress, chunk, workers):
    import multiprocessing as mp
    global _JOB
    _JOB = (scene, samplers, mis, chunk, seed)
    t0 = time.perf_counter()
    try:
        with mp.get_context("fork").Pool(workers) as pool:
            parts = pool.map(_worker, [(w, workers, spp, seconds) for w in range(workers)])
    finally:
        _JOB = None
    s1 = sum(p[0] for p in parts)
    s2 = sum(p[1] for p in parts)
    k = sum(p[2] for p in parts)
    st = Stats()
    for p in parts:
        for f in ("paths", "rays", "sampling_seconds", "eval_seconds", "lost", "passes"):
            setattr(st, f, getattr(st, f) + getattr(p[3], f))
    st.extra["worker_seconds"] = sum(p[3].seconds for p in parts)
    st.seconds = time.perf_counter() - t0
    if progress is not None:
        progress(k, st.seconds, st)
    return _finish(s1, s2, k, st)

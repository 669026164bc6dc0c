"""Baseline samplers every learned sampler must beat: uniform, cosine, and a fitted GGX lobe.

They keep the sampler contract (bake/core/sampler.py): `sample(wi, u) -> (wo, pdf)` and
`pdf(wi, wo)`, pdf per steradian, zero below the horizon; `open_sampler("uniform" | "cosine" |
"ggx", material)` opens them by name.
"""
import numpy as np

from ..io.threads import parallel
from ..materials.analytic import ggx_reflection_pdf, ggx_sample_reflection
from ..materials.base import as_dirs
from ..maths.geometry import luminance


class UniformSampler:
    name = "uniform"

    def sample(self, wi, u):
        u = np.atleast_2d(u)
        z = u[:, 0]
        s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        phi = 2 * np.pi * u[:, 1]
        wo = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)
        return wo, self.pdf(wi, wo)

    def pdf(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        return np.where(wo[:, 2] > 0, 0.5 / np.pi, 0.0)


class CosineSampler:
    name = "cosine"

    def sample(self, wi, u):
        u = np.atleast_2d(u)
        r = np.sqrt(u[:, 0])
        phi = 2 * np.pi * u[:, 1]
        wo = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1.0 - r * r))], axis=-1)
        return wo, self.pdf(wi, wo)

    def pdf(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        return np.maximum(wo[:, 2], 0.0) / np.pi


class GGXSampler:
    """What Cycles-style sampling gives: a diffuse lobe (probability `diffuse`) and GGX
    visible-normal sampling of a reflection lobe with roughness (alpha_x, alpha_y)."""

    name = "ggx"

    def __init__(self, alpha_x, alpha_y=None, diffuse=0.0):
        self.alpha_x = float(alpha_x)
        self.alpha_y = float(alpha_x if alpha_y is None else alpha_y)
        self.diffuse = float(diffuse)
        self._cos = CosineSampler()

    def sample(self, wi, u):
        u = np.atleast_2d(np.asarray(u, float))
        wi, _ = as_dirs(wi, u[:, :1].repeat(3, axis=1))
        pick = u[:, 0] < self.diffuse
        spec_u = u.copy()
        # Reuse u[0] within each lobe: keeps the sampler a function of u alone.
        spec_u[:, 0] = np.where(pick, u[:, 0] / max(self.diffuse, 1e-300),
                                (u[:, 0] - self.diffuse) / max(1.0 - self.diffuse, 1e-300))
        spec_u = np.clip(spec_u, 0.0, np.nextafter(1.0, 0.0))
        wo = ggx_sample_reflection(wi, self.alpha_x, self.alpha_y, spec_u)
        if self.diffuse > 0:
            wo_d, _ = self._cos.sample(wi, spec_u)
            wo = np.where(pick[:, None], wo_d, wo)
        return wo, self.pdf(wi, wo)

    def pdf(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        p = (1.0 - self.diffuse) * ggx_reflection_pdf(wi, wo, self.alpha_x, self.alpha_y)
        if self.diffuse > 0:
            p = p + self.diffuse * self._cos.pdf(wi, wo)
        return p

    def __repr__(self):
        return f"GGXSampler(alpha={self.alpha_x:.4g}/{self.alpha_y:.4g}, diffuse={self.diffuse:.2f})"


FIT_THETAS_DEG = (0, 20, 40, 55, 70, 80, 87)
FIT_ALPHAS = np.geomspace(0.002, 1.0, 28)
FIT_DIFFUSE = (0.0, 0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 0.9, 1.0)


def fit_ggx(material, ideal, n=1 << 14, seed=0):
    """The GGX sampler (isotropic alpha, diffuse weight) of least mean log(1 + rv) over
    FIT_THETAS_DEG. rv of every candidate is estimated from one set of samples of the
    ideal sampler q: rv(p) = E_q[g² / (p q)] / (E_q[g / q])² - 1, g = lum(f)·cos."""
    rng = np.random.default_rng(seed)
    # Each angle's samples from its own draws of the one generator, drawn in turn; the angles'
    # evaluations and then the alphas' scores in threads (the planner waits for this fit: a
    # serial stretch at the start of every bake), the best picked in the loop's order.
    draws = [(t, rng.random((n, 2))) for t in np.radians(FIT_THETAS_DEG)]

    def case(draw):
        t, u = draw
        wi = np.array([np.sin(t), 0.0, np.cos(t)])
        wo, q = ideal.sample(wi, u)
        ok = q > 0
        wo, q = wo[ok], q[ok]
        g = luminance(material.eval(wi, wo)) * wo[:, 2]
        mean = np.mean(g / q) * ok.mean()
        return (wi, wo, q, g, mean, ok.mean()) if mean > 0 else None
    cases = [c for c in parallel(case, draws) if c is not None]
    if not cases:
        return GGXSampler(0.5, diffuse=1.0)

    def scores(alpha):
        spec = [ggx_reflection_pdf(wi, wo, alpha, alpha) for wi, wo, *_ in cases]
        out = []
        for d in FIT_DIFFUSE:
            score = 0.0
            for (wi, wo, q, g, mean, frac), ps in zip(cases, spec):
                p = (1 - d) * ps + d * wo[:, 2] / np.pi
                with np.errstate(divide="ignore"):
                    second = np.mean(np.where(g != 0, g * g / (p * q), 0.0)) * frac
                score += np.log1p(max(second / mean ** 2 - 1.0, 0.0))
            out.append(score)
        return out
    best, best_score = None, np.inf
    for alpha, by_d in zip(FIT_ALPHAS, parallel(scores, FIT_ALPHAS)):
        for d, score in zip(FIT_DIFFUSE, by_d):
            if score < best_score:
                best, best_score = (alpha, d), score
    return GGXSampler(best[0], diffuse=best[1])

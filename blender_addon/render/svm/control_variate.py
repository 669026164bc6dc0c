"""The control variate: the fit's Cycles closures (scaled, or matched to a small light) taken with
probability 1 - s, the portal carrying the rest; f_cv cos as Cycles renders those closures
(`_cv_fcos`), the match image's lookup. What it does and measured: docs/svm.md."""
import math

from .graph import (GROUP_PREFIX, X, Y, Z, _Graph, _group, _image, atan2, clamp, floor, fma, inversesqrt, maximum,
                    minimum, sqrt, where)
from .tables import _svm_export

CV = "FlowBSDF SVM cv"          # a Value node per control variate: 1 on, 0 off (ControlVariate)
# The fit's view tangent (node.view_tangent, and _cv_fcos_group's twin of it): the view direction
# projected onto the surface plus VIEW_TANGENT_EPS N x VIEW_TANGENT_NUDGE, a direction no shading
# normal is parallel to in practice (Cycles normalises cross(N, T): NaN for a zero tangent).
VIEW_TANGENT_NUDGE = (0.36, 0.48, 0.8)
VIEW_TANGENT_EPS = 1e-6
MATCHED_SHARE_MIN = 0.05      # node.matched_share's least share
# ... and its shares of the world's techniques (WorldShare, SunShare) there: the rest has next
# to nothing where the light is (paper_white, the lights acceptance's sky, noise per sample
# 0.162 / 0.142 / 0.139 at 1 / 0.25 / 0.05)
MATCHED_LIGHT_SCALE = 0.25


def _matching(mix, matchable):
    """Whether a control variate (with a match image: `matchable`) is matched to the light of
    the mixture `mix` (its world has a small light and something to sample)."""
    return matchable and (mix.light is not None or mix.match_lamp) and bool(mix)


def control_variate_wanted(texture_path, fit):
    """Whether the node's SVM back end hands build_svm_sampler a control variate: tables with a
    fit that has one, anisotropic tables only with a fit along their own tangent (FIT_VERSION
    10; an older one was made at phi_i 0 only)."""
    return (bool(fit and fit.get("cv"))
            and (_svm_export().read_layout(texture_path)["P"] == 1 or bool(fit.get("material_aligned", 0))))


def _cv_switched(g, cv, world, matched, match_lamp=False):
    """`cv` with "on" (the value of a node named CV: 1 uses the control variate, 0 leaves the
    portal alone: world inputs' ControlVariate, update_world; and only on camera rays) and "s",
    the share of shading points that take the portal: cv's share when on, else 1. None (the
    node kept, marked) for a control variate with no betas when the world has no light to
    match it to.
    Camera rays only: past a diffuse or rough bounce Cycles renders closures other than they
    are (Filter Glossy, on by default, blurs the GGX lobes; Caustics off drops them), so f_cv as
    rendered there is not the f_cv the portal's rest subtracts; the portal alone is exact there.
    A ray a portal continued at a camera-hit point is still a camera ray, neither blurred nor
    filtered (Cycles path_state_next: the portal adds only the transparent flag). The closures'
    own bounce is a diffuse or glossy one, so what they continue to is blurred or filtered,
    unlike what the portal continues to: node.caustics_gate turns the control variate off when
    Caustics are off (measured -8.9 % without); Filter Glossy's +2.1 % there is kept."""
    node = g.node("ShaderNodeValue", name=CV, label=CV)
    node.outputs[0].default_value = _cv_value(world)
    node["flowbsdf_light"] = int(matched)
    node["flowbsdf_matchable"] = int(bool(cv.get("match_image")))
    node["flowbsdf_match_lamp"] = int(matched and match_lamp)
    if not matched and not cv["has_betas"]:
        return None
    on = g.outputs(node)[0] * g.outputs(g.node("ShaderNodeLightPath"))["Is Camera Ray"]
    beta_d, beta_s = g.dot(cv["betas"], X), g.dot(cv["betas"], Y)
    return dict(cv, on=on, matching=matched, diffuse=g.combine(beta_d, beta_d, beta_d),
                specular=g.combine(beta_s, beta_s, beta_s),
                s=1.0 - on * (1.0 - g.dot(cv["betas"], Z)))


def _cv_value(world):
    return float((world or {}).get("ControlVariate", 0.0))


def _cv_pick(g, cv, u0):
    """(1 when the shading point takes the portal (probability s, the control variate's portal
    share), else 0; u0 rescaled within the part taken: uniform again for the portal's sampling).
    By u0, so that on camera rays the pick is as stratified over a pixel's samples as u0 is."""
    s = cv["s"]
    take = u0 < s
    inside = where(take, u0 / s, (u0 - s) / (1.0 - s))
    return take, minimum(inside, 1.0 - 2.0 ** -24)


def _cv_fcos(g, cv, wi, n, d):
    """What the control variate's closures render toward d, f_cv cos theta_o (colour): Cycles'
    Diffuse BSDF (colour kd scaled by cv["diffuse"]) and the fit's GGX Glossy BSDFs (colours
    ks_j scaled by cv["specular"], roughness r_j, anisotropy a_j, the tangent along the view:
    node.view_tangent) as bsdf_diffuse_eval and bsdf_microfacet_eval compute them (no Fresnel,
    height-correlated G2), at wi and d about the normal n, each tilted closure about its own
    normal (node._closures; the tilted Diffuse times Cycles' bump shadowing). (A node group, one
    for every lobe count and set of tilted closures: a mixture's branches each take it.)"""
    fit = cv["fit"]
    lobes = len(fit["ks"])
    tilted = tuple(bool(t) for t in fit.get("tilted", [False] * (lobes + 1))) if CV_TILTS else (False,) * (lobes + 1)
    inputs = {f"Specular {j + 1}": ks for j, ks in enumerate(fit["ks"])}
    if any(tilted[1:4]):
        inputs["Tilt"] = fit["tilt"]
    if lobes > 3 or tilted[0]:
        inputs["Lobe 4"] = fit["lobe4"]
    along = bool(fit.get("material_aligned"))
    if along:
        inputs["T"] = cv["tangent"]
    return g.group(_cv_fcos_group(lobes, tilted, along), Wi=wi, N=n, D=d, Diffuse=fit["kd"], Roughness=fit["roughness"],
                   Anisotropy=fit["anisotropy"], DiffuseScale=cv["diffuse"], SpecularScale=cv["specular"],
                   **inputs)[0]


# The control variate's closures tilted as the fit's (node._closures): else untilted, in the
# closures and in _cv_fcos alike (any f_cv is unbiased where the graph's equals what its closures render).
CV_TILTS = True


def _cv_fcos_group(lobes, tilted=None, along_t=False):
    """_cv_fcos's group: `lobes` GGX lobes (the first three view-aligned where their Anisotropy
    is not 0, the 4th isotropic: its roughness, tilt and the Diffuse's tilt from "Lobe 4" =
    (r_4, t_4, t_d)), tilted[k] whether closure k (the Diffuse first) has its own normal
    normalize(N + t T / |T|) (T the view tangent; else N). `along_t`: the three along the
    input "T" instead (a material-aligned fit: the tables' tangent turned by the fit's
    tangent_turn, fit_nodes.lobe_tangent, as the fit's closures take it; no tilts)."""
    tilted = tuple(tilted or (False,) * (lobes + 1))
    if along_t and any(tilted):
        raise ValueError("a fit along the material's tangent has no tilts")
    names = (["Wi", "N", "D", "Diffuse"] + [f"Specular {j + 1}" for j in range(lobes)]
             + ["Roughness", "Anisotropy"] + (["Tilt"] if any(tilted[1:4]) else [])
             + (["Lobe 4"] if lobes > 3 or tilted[0] else []) + ["DiffuseScale", "SpecularScale"]
             + (["T"] if along_t else []))
    mark = "" if not any(tilted) else ", tilted " + "".join("d" if k == 0 else str(k) for k, t in enumerate(tilted) if t)
    kind = "lobes along T" if along_t else "view-aligned lobes"
    done, tree = _group(f"{GROUP_PREFIX}control variate f cos, {lobes} {kind}{mark}, scaled",
                        [(name, "Vector") for name in names], [("F cos", "Vector")])
    if done:
        return done
    g = _Graph(tree)
    inp = g.node("NodeGroupInput").outputs
    wi, n, d = inp["Wi"], inp["N"], inp["D"]
    cos_i = g.dot(wi, n)
    cos_o = g.dot(d, n)
    above = (cos_i > 0.0) * (cos_o > 0.0)
    # Cycles' frame of an anisotropic closure (make_orthonormals_tangent): y = normalize(N x T),
    # x = y x N, T the view's tangent (node.view_tangent: wi less its normal part, nudged)
    tangent = inp["T"] if along_t else g.vmath('MULTIPLY_ADD', g.vmath('CROSS_PRODUCT', n, VIEW_TANGENT_NUDGE),
                                                 (VIEW_TANGENT_EPS,) * 3, g.vmath('SUBTRACT', wi, g.scale(n, cos_i)))
    h = g.vmath('NORMALIZE', g.vmath('ADD', wi, d))
    separated = {}

    def component(name, c):
        if name not in separated:
            separated[name] = g.node("ShaderNodeSeparateXYZ")
            g.set(separated[name].inputs[0], inp[name])
        return g.outputs(separated[name])[c]

    untilted = {}
    if any(tilted):
        # A tilted closure's normal normalize(N + t U) (U = T / |T|: orthogonal to N) and its
        # frame (make_orthonormals_tangent with T: y = normalize(N' x T) = N x U, the untilted y;
        # x = y x N') turn the untilted frame (U, y, N) about y: a vector's coordinates there are
        # ((v.U - t v.N) c, v.y, (v.N + t v.U) c), c = 1 / sqrt(1 + t^2). So each lobe takes scalars
        # of these dots alone, of its own branch: every value here depends on d, through a no-op
        # for the tilts (min with a 1e30 of d), else Cycles would merge the branches' equal nodes,
        # compute them before the branches and hold them all on its stack through all.
        big = maximum(cos_o, 1e30)
        # (U and y through the no-op too: each branch's own, not held through all; y = N x U exactly)
        unit = g.vmath('MINIMUM', g.vmath('NORMALIZE', tangent), big)
        fy = g.vmath('CROSS_PRODUCT', n, unit)
        # (wi.y: 0, wi in the plane of N and T; Cycles' float dot is ~1e-8 there)
        dots = {"h": (g.dot(h, unit), g.dot(h, fy), g.dot(h, n)), "i": (g.dot(wi, unit), 0.0, cos_i),
                "o": (g.dot(d, unit), g.dot(d, fy), cos_o)}

    def tilt_of(closure):       # 0: the Diffuse, j + 1: lobe j (this branch's own)
        t = component("Lobe 4", 2 if closure == 0 else 1) if closure in (0, 4) else component("Tilt", closure - 1)
        return minimum(t, big)

    def turned(t, c, v, aniso):
        a, y, b = v
        z = fma(a, t, b) * c
        if not aniso:
            return None, None, z
        return fma(b, -t, a) * c, y, z

    def local_of(closure, aniso):
        """(mask, local h, wi, d: each (x, y, z); x, y None for an isotropic lobe) about the
        closure's normal."""
        if not tilted[closure]:
            if aniso not in untilted:
                untilted[aniso] = (above, *_cv_local(g, n, tangent, h, wi, d, cos_i, cos_o, aniso))
            return untilted[aniso]
        t = tilt_of(closure)
        c = inversesqrt(fma(t, t, 1.0))
        lh, li, lo = (turned(t, c, dots[k], aniso) for k in ("h", "i", "o"))
        # (Cycles: wi and d above the closure's normal, d above the surface's)
        mask = (li[2] > 0.0) * (lo[2] > 0.0) * (cos_o > 0.0)
        return mask, lh, li, lo
    def square(x):      # x x, not a Power node: pow costs ~4x a multiply in Cycles' SVM (and a constant 2)
        return x * x
    lobe = []
    for j in range(lobes):
        aniso = j < 3
        r = clamp(component("Roughness", j) if j < 3 else component("Lobe 4", 0), 0.0, 1.0)
        alpha = r * r
        mask, lh, li, lo = local_of(j + 1, aniso)
        if aniso:
            a = clamp(component("Anisotropy", j), -0.99, 0.99)
            neg = a < 0.0
            # svm closure.h: a < 0: (alpha / (1 + a), alpha (1 + a)), else (alpha (1 - a), alpha / (1 - a))
            # (each at most 1: bsdf_microfacet_ggx_setup saturates them)
            ax = minimum(where(neg, alpha / (1.0 + a), alpha * (1.0 - a)), 1.0)
            ay = minimum(where(neg, alpha * (1.0 + a), alpha / (1.0 - a)), 1.0)
            hx, hy, hz = lh
            q = square(hx / ax) + square(hy / ay) + hz * hz
            ndf = (1.0 / math.pi) / (ax * ay * (q * q))

            def lam(v, ax=ax, ay=ay):    # bsdf_lambda<GGX>: 0.5 (sqrt(1 + (ax^2 vx^2 + ay^2 vy^2) / vz^2) - 1)
                t2 = (square(ax * v[0]) + square(ay * v[1])) / (v[2] * v[2])
                return (sqrt(t2 + 1.0) - 1.0) * 0.5
        else:
            # isotropic (alpha at most 1): D = 1 / (pi alpha^2 q^2), q = (1 - hz^2) / alpha^2 + hz^2;
            # lambda = 0.5 (sqrt(1 + alpha^2 (1 - vz^2) / vz^2) - 1)
            hz = lh[2]
            hz2 = hz * hz
            alpha2 = alpha * alpha
            q = (1.0 - hz2) / alpha2 + hz2
            ndf = (1.0 / math.pi) / (alpha2 * (q * q))

            def lam(v, alpha2=alpha2):
                vz2 = v[2] * v[2]
                t2 = alpha2 * (1.0 - vz2) / vz2
                return (sqrt(t2 + 1.0) - 1.0) * 0.5
        g2 = lam(li) + lam(lo) + 1.0
        lobe.append(ndf * mask / (li[2] * 4.0 * g2))
    # the Diffuse: max(d.N', 0) / pi, tilted times Cycles' bump shadowing G1 (bsdf.h
    # bump_shadowing_term: alpha^2 = min(tan^2 / 8, 1) of the tilt, tan^2 = t_d^2 as T is
    # orthogonal to N; 0 where d.N < 1e-6)
    if tilted[0]:
        td = tilt_of(0)
        td2 = td * td
        cos_od = turned(td, inversesqrt(td2 + 1.0), dots["o"], False)[2]    # d.N'
        a2 = minimum(td2 * 0.125, 1.0)
        c = maximum(cos_o, 1e-6)
        tan2 = 1.0 / (c * c) - 1.0
        g1 = 2.0 / (1.0 + sqrt(fma(a2, tan2, 1.0)))
        shade = maximum(cos_od, 0.0) * (1.0 / math.pi) * (g1 * (cos_o > 1e-6))
    else:
        shade = maximum(cos_o, 0.0) * (1.0 / math.pi)
    # the colours last (made last, Cycles runs them last: fewer values alive on its stack meanwhile)
    out = g.scale(g.vmath('MULTIPLY', inp["Diffuse"], inp["DiffuseScale"]), shade)
    for j, value in enumerate(lobe):
        out = g.vmath('MULTIPLY_ADD', g.vmath('MULTIPLY', inp[f"Specular {j + 1}"], inp["SpecularScale"]),
                      g.combine(value, value, value), out)
    g.set(g.node("NodeGroupOutput").inputs["F cos"], out)
    return tree


def _cv_local(g, nj, tangent, h, wi, d, cos_i, cos_o, aniso):
    """(h, wi, d) in the frame of normal nj (Cycles' make_orthonormals_tangent with the view
    tangent: y = normalize(nj x T), x = y x nj), each (x, y, z); x, y None when not `aniso`."""
    if not aniso:
        return (None, None, g.dot(h, nj)), (None, None, cos_i), (None, None, cos_o)
    fy = g.vmath('NORMALIZE', g.vmath('CROSS_PRODUCT', nj, tangent))
    fx = g.vmath('CROSS_PRODUCT', fy, nj)
    return ((g.dot(h, fx), g.dot(h, fy), g.dot(h, nj)), (g.dot(wi, fx), g.dot(wi, fy), cos_i),
            (g.dot(d, fx), g.dot(d, fy), cos_o))


def _cv_rest(g, cv, wi, n, d, weight, ok, q):
    """The portal's weight for the BSDF less the control variate (when on), when taken with
    probability s: (weight - on f_cv cos ok / q) / s."""
    rest = g.vmath('SUBTRACT', weight, g.scale(_cv_fcos(g, cv, wi, n, d), ok * cv["on"] / q))
    return g.scale(rest, 1.0 / cv["s"])


def _cv_closures(g, cv):
    """The control variate's closures, colours / (1 - s) (their weight when taken)."""
    keep = 1.0 - cv["s"]
    return cv["closures"](g.vmath('DIVIDE', cv["diffuse"], g.combine(keep, keep, keep)),
                          g.vmath('DIVIDE', cv["specular"], g.combine(keep, keep, keep)))


def _cv_matched(g, cv, at, axis, unmatched=None):
    """`cv` with the fit's closures scaled at this shading point so that f_cv = f toward the
    light's direction `axis` (beta = f / f_fit there per channel, trilinear in the match image:
    bake/export/closure_fit.match_ratios), the portal's share its matched_share: the light's part
    of the rest is ~0 (Cycles' light sampling of the closures carries it). The baked betas and
    share where the light is below the surface or the view angle's fit is too poor
    (matched_share 0)."""
    wo = tuple(g.dot(axis, v) for v in (at["tx"], at["ty"], at["n"]))
    beta = _match_lookup(g, cv["match_image"], at["cos_i"], wo)
    share = g.dot(cv["matched_share"], X)
    # (between a knot matched and one not, the share falls to 0: off below the least share)
    on = (wo[2] > 0.05) * ((share > 0.99 * MATCHED_SHARE_MIN) * cv["on"])
    off = 1.0 - on
    if unmatched is not None:
        # the other lamps' part of the rest is not ~0: toward the baked share as their weight grows
        share = fma(maximum(cv["s"] - share, 0.0), unmatched, share)
    return dict(cv, matched=on, s=fma(on, share, cv["s"] * off),
                diffuse=g.vmath('MULTIPLY_ADD', g.combine(on, on, on), beta, g.scale(cv["diffuse"], off)),
                specular=g.vmath('MULTIPLY_ADD', g.combine(on, on, on), beta, g.scale(cv["specular"], off)))


def _match_lookup(g, path, cos_v, wo):
    """The match image's ratio (colour) at view cosine cos_v and the light's local direction wo
    (x, y, z; the view's azimuth 0): bilinear in (|phi|, cos theta_l) within a view's tile
    (texel centres are the grid's nodes, so a lookup never blends two tiles), linear between
    the two nearest views' tiles."""
    image = _image(path)
    n = image.size[1]
    width, height = n * n, n
    fv = clamp(cos_v, 0.0, 1.0) * (n - 1.0)
    i0 = minimum(floor(fv), n - 2.0)
    t = fv - i0
    fphi = abs(atan2(wo[1], wo[0])) * ((n - 1.0) / math.pi)
    fl = clamp(wo[2], 0.0, 1.0) * (n - 1.0)
    v = 1.0 - (fl + 0.5) / height

    def tile(i):
        x = (fma(i, float(n), fphi) + 0.5) / width
        tex = g.node("ShaderNodeTexImage", image=image, interpolation='Linear', extension='EXTEND')
        g.set(tex.inputs["Vector"], g.combine(x, v))
        return tex.outputs["Color"]
    lo, hi = tile(i0), tile(i0 + 1.0)
    return g.vmath('MULTIPLY_ADD', g.vmath('SUBTRACT', hi, lo), g.combine(t, t, t), lo)

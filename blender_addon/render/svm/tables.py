"""The tables' sampler as SVM nodes: Tables.sample and its inverse Tables._locate (bake/core/tables.py,
the numpy reference; blender_addon/render/osl/tables.h, the OSL twin) on the texture of
bake/export/svm_export.py. Per-texture node groups "tables sample" and "tables pdf" hold them."""
import math

from .graph import (GROUP_PREFIX, X, Y, Z, _Graph, _group, _image, _key, atan2, cos, exp, floor, fma, log, maximum,
                    minimum, saturate, sin, sinh, sqrt, where)
from .halfvector import _half_from_ab, _half_to_ab, _half_wi, _polar_from_ab, _polar_ref, _polar_to_ab, _polar_wi

K_SMALL = 1e-4          # bake/core/profiles.py _SMALL: the in-cell density's small-rate branch
LOG_MEAN_SERIES = 1e-3  # bake/core/profiles.py LOG_MEAN_SERIES: the log mean's series below it


def _svm_export():
    import importlib
    from ... import deps
    return importlib.import_module(f"{deps.bake.__name__}.export.svm_export")


def _weight_inputs(alpha):
    return [("Weights", "Vector")] + ([("Weight A", "Float")] if alpha else [])


def _record_group(image, alpha):
    """Group "record": the texel at UV blended over the bins: dot(colour, Weights), + alpha x
    Weight A with `alpha` (a record in red/green: Weights = (w0, w1, 0), no alpha; in
    blue/alpha: (0, 0, w0) and w1; four bins: (w0, w1, w2) and w3)."""
    done, tree = _group(f"{GROUP_PREFIX}record{' RGBA' if alpha else ' RGB'}: {image.name}",
                        [("UV", "Vector")] + _weight_inputs(alpha), [("Value", "Float")])
    if done:
        return done
    g = _Graph(tree)
    inp = g.outputs(g.node("NodeGroupInput"))
    tex = g.node("ShaderNodeTexImage", image=image, interpolation='Closest', extension='EXTEND')
    g.set(tex.inputs["Vector"], inp["UV"])
    value = g.dot(tex.outputs["Color"], inp["Weights"])
    if alpha:
        value = fma(g.outputs(tex)["Alpha"], inp["Weight A"], value)
    g.set(g.node("NodeGroupOutput").inputs["Value"], value)
    return tree


def _step_group(image, alpha):
    """Group "search step" (branchless binary search): index = Lo + Half; Lo moves there when
    the record at texture x Base X + index x Stride, y Base Y is <= Target."""
    done, tree = _group(f"{GROUP_PREFIX}search step{' RGBA' if alpha else ' RGB'}: {image.name}",
                        [("Lo", "Float"), ("Target", "Float"), ("Base X", "Float"), ("Base Y", "Float"),
                         ("Stride", "Float"), ("Half", "Float")] + _weight_inputs(alpha), [("Lo", "Float")])
    if done:
        return done
    g = _Graph(tree)
    inp = g.outputs(g.node("NodeGroupInput"))
    index = inp["Lo"] + inp["Half"]
    uv = g.combine(fma(index, inp["Stride"], inp["Base X"]), inp["Base Y"])
    weights = {name: inp[name] for name, _ in _weight_inputs(alpha)}
    value = g.group(_record_group(image, alpha), UV=uv, **weights)[0]
    above = value > inp["Target"]                   # (tables.h: if (c <= u0) lo = mid)
    lo = fma(above, -inp["Half"], index)
    g.set(g.node("NodeGroupOutput").inputs["Lo"], lo)
    return tree


class _Sampler:
    """The sampler's nodes on one SVM texture (layout: bake/export/svm_export.py). `incident` adds
    the bin lookup and blend weights (once per graph), then `sample` and `locate` add the
    sampler and its inverse (the pdf at a direction).
    A texel's place is a pair (x, y) of texture coordinates (sockets or numbers), each moved by
    scalar Math and combined into a vector once per texel looked up: a Vector Math node costs
    Cycles' SVM ~5 scalar ones. The quantities of one texel (two records to a texel, isotropic
    tables) are read by image nodes of their own at that one place: Cycles merges them into one
    lookup (tests/test_svm.py test_cycles_merges_the_lookups_of_one_texel)."""

    def __init__(self, g, texture_path, lay=None):
        self.g, self.path = g, texture_path
        self.lay = lay or _svm_export().read_layout(texture_path)
        self.image = _image(texture_path)
        self.du = 1.0 / self.lay["width"]
        self.dv = 1.0 / self.lay["height"]
        self.rpt = 4 // self.lay["NB"]          # records per texel: record q at texel q // rpt, slot q % rpt
        self.offsets, self.uvs = {}, {}
        # a cell's quantities (svm_export.CELL_QUANTITIES): mass, the a and b profiles' node values, W
        n = (_svm_export().CELL_QUANTITIES - 4) // 2
        self.on_a, self.on_b, self.on_w = range(1, 1 + n), range(1 + n, 1 + 2 * n), range(1 + 2 * n, 4 + 2 * n)

    def uv(self, at):
        """The texel place `at` (x, y) as a vector, made once per place."""
        key = tuple(map(_key, at))
        if key not in self.uvs:
            self.uvs[key] = self.g.combine(*at)
        return self.uvs[key]

    def fetch(self, at):
        tex = self.g.node("ShaderNodeTexImage", image=self.image, interpolation='Closest', extension='EXTEND')
        self.g.set(tex.inputs["Vector"], self.uv(at))
        return tex.outputs["Color"], self.g.outputs(tex)["Alpha"]

    def offset(self, base, dx=0.0, dy=0.0):
        """base + (dx, dy) texels (dy down the image), each coordinate moved once per base and offset."""
        return tuple(self._moved(c, d) for c, d in zip(base, (dx * self.du, -dy * self.dv)))

    def _moved(self, c, d):
        if not d:
            return c
        key = (_key(c), d)
        if key not in self.offsets:
            self.offsets[key] = c + d
        return self.offsets[key]

    def blend(self, q):
        """(alpha used?, the group inputs that blend quantity q's slot of a texel)."""
        wv, wa = self.weights[q % self.rpt]
        return wa is not None, ({"Weights": wv} if wa is None else {"Weights": wv, "Weight A": wa})

    def quantity(self, base, q):
        """Quantity q of the records at texel `base`, blended over the bins."""
        alpha, weights = self.blend(q)
        return self.g.group(_record_group(self.image, alpha), UV=self.uv(self.offset(base, q // self.rpt)),
                            **weights)[0]

    def at(self, base, index, stride):
        """The texel `index` records of `stride` texels after `base`."""
        return fma(index, stride * self.du, base[0]), base[1]

    def search(self, lo, target, base, stride, steps, q, last):
        """The last index <= `last` (a socket or a number) whose quantity q is <= target, from
        lo (branchless, `steps` halvings). The end record (a total) can round to <= a target near
        its value: `last` caps the result there."""
        alpha, weights = self.blend(q)
        base = self.offset(base, q // self.rpt)
        for s in reversed(range(steps)):
            lo = self.g.group(_step_group(self.image, alpha), Lo=lo, Target=target, **{"Base X": base[0]},
                              **{"Base Y": base[1]}, Stride=stride * self.du, Half=float(2 ** s), **weights)[0]
        return minimum(lo, last)

    def guide_lo(self, base, u, count):
        """The guide's lo for u in [0, 1] (entries at base + g texels, g < count)."""
        entry = minimum(floor(u * float(count)), count - 1.0)      # tables.h: min(int(u0 * R), R - 1)
        color, _ = self.fetch(self.at(base, entry, 1))
        return self.g.dot(color, X)

    def bin_count(self, guide, value, index_value):
        """The bin index from a bin guide ([x0, G]) at `value`, the entry floor(index_value G)."""
        g = self.g
        x0, count = guide
        entry = floor(index_value * float(count))
        uv_x = fma(entry, self.du, (x0 + 0.5) * self.du)
        color, alpha = self.fetch((uv_x, 1.0 - 0.5 * self.dv))
        # [value < t_j] = ceil(clamp(t_j - value, 0, 1)) per channel
        below = g.vmath('CEIL', g.vmath('MAXIMUM', g.vmath('MINIMUM', g.vmath('SUBTRACT', color, value),
                                                            (1.0, 1.0, 1.0)), (0.0, 0.0, 0.0)))
        return alpha - g.dot(below, (1.0, 1.0, 1.0))

    def incident(self, cos_i, phi_i):
        """The corner block of the incident bins at sockets cos theta_i (>= 0) and phi_i (None
        for isotropic tables), the blend weights and the last row and column of the corner's
        own table (self.origin, self.weights, self.last: from the block's header for isotropic
        tables, whose bins may differ in size, MixedTables)."""
        g, lay = self.g, self.lay
        K, P, nx = lay["K"], lay["P"], lay["blocks_per_row"]
        bw, bh = lay["block"]
        k = self.bin_count(lay["theta_guide"], -cos_i, sqrt(1.0 - cos_i)) if K > 1 else g.const(0.0)
        if P > 1:
            x = (phi_i - lay["phi0"]) % lay["period"]
            # halfvector tables: the whole periods phi_i was turned back by, plus the lobe's axes
            self.ref = phi_i - lay["phi0"] - x + lay.get("frame", 0.0)
            p = self.bin_count(lay["phi_guide"], x, x * (1.0 / lay["period"]))
            corner = fma(k, float(P), p)
        else:
            corner = k
        if lay["corners"] > nx:
            brow = floor(fma(corner, 1.0 / nx, 0.5 / nx))
            bcol = fma(brow, -float(nx), corner)
        else:
            brow, bcol = g.const(0.0), corner
        self.origin = (fma(bcol, bw * self.du, 0.5 * self.du), fma(brow, -bh * self.dv, 1.0 - 1.5 * self.dv))
        head, head_a = self.fetch(self.origin)
        self.last = (lay["R"] - 1.0, lay["C"] - 1.0) if P > 1 else (g.dot(head, Z), head_a)
        t = s = g.const(0.0)
        if K > 1:
            c_k, c_k1 = g.dot(head, X), g.dot(head, Y)
            t = saturate((c_k - cos_i) / (c_k - c_k1))
        if P > 1:
            start = g.dot(head, Z)
            s = saturate((x - start) / (head_a - start))
        if lay["NB"] == 2:
            w0 = 1.0 - t
            self.weights = [(g.combine(w0, t), None), (g.combine(0.0, 0.0, w0), t)]
        else:
            t1, s1 = 1.0 - t, 1.0 - s
            self.weights = [(g.combine(t1 * s1, t * s1, t1 * s), t * s)]

    def direction(self, a, b, cos_i, phi_i):
        """wo (floats x, y, z in the local frame) at table coordinates (a, b), after `incident`,
        and d omega_o / (da db) (None: 1, the "wo" coordinates; bake/core/tables.py)."""
        g, coords = self.g, self.lay.get("coords", "wo")
        if coords == "wo":
            return _from_ab(g, a, b, phi_i), None
        if coords == "halfpolar":       # the map's frame: wi's turned by pi (phi_i None: wi's frame)
            wo, jac = _polar_from_ab(g, a, b, _polar_wi(g, cos_i))
            return _turn(g, wo, _polar_ref(g, phi_i)), jac
        wo, jac = _half_from_ab(g, a, b, _half_wi(g, cos_i, phi_i, self.ref))
        return _turn(g, wo, self.ref), jac

    def coordinates(self, wo, cos_i, phi_i):
        """(a, b, d omega_o / (da db) or None) of a local direction wo, after `incident`."""
        g, coords = self.g, self.lay.get("coords", "wo")
        if coords == "wo":
            return _to_ab(g, wo, phi_i) + (None,)
        if coords == "halfpolar":
            return _polar_to_ab(g, _turn(g, wo, -_polar_ref(g, phi_i)), _polar_wi(g, cos_i))
        return _half_to_ab(g, _turn(g, wo, -self.ref), _half_wi(g, cos_i, phi_i, self.ref))

    def rows(self):
        return self.offset(self.origin, self.lay["x_row"])

    def row(self, i):
        """Texel (0, 1 + i) of the block: table row i's guide, then its records."""
        x, y = self.offset(self.origin, 0, 1)
        return x, fma(i, -self.dv, y)

    def cell(self, row, j):
        """Cell j of the blended table's row at texel `row` (self.row): a function giving its
        quantity n (svm_export.CELL_QUANTITIES: mass, the a and b profiles' node values, W), each
        read where it is first needed, so few values are alive at once (the SVM stack)."""
        cell = self.at(self.offset(row, self.lay["x_cell"]), j, self.lay["cell_stride"])
        return lambda n: self.quantity(cell, n)

    def sample(self, u0, u1):
        """Tables.sample after `incident`: (a, b, weight W (colour), pdf) for sockets u0, u1."""
        g, lay = self.g, self.lay
        sr, sc = lay["row_stride"], lay["col_stride"]
        # row i: the last with CDF(i) <= u0
        rows = self.rows()
        i = self.search(self.guide_lo(self.offset(self.origin, 1), u0, lay["row_guide"]), u0, rows, sr,
                        lay["row_steps"], 0, self.last[0])
        rec = self.at(rows, i, sr)
        rec1 = self.offset(rec, sr)
        c0, a0, c1, a1 = (self.quantity(r, q) for r, q in ((rec, 0), (rec, 1), (rec1, 0), (rec1, 1)))
        v = u1 * (c1 - c0)
        # column j of row i: the last with cumsum(i, j) <= v
        row = self.row(i)
        cols = self.offset(row, lay["x_col"])
        j = self.search(self.guide_lo(row, u1, lay["col_guide"]), v, cols, sc, lay["col_steps"], 0, self.last[1])
        rec = self.at(cols, j, sc)
        d0, b0, b1 = self.quantity(rec, 0), self.quantity(rec, 1), self.quantity(self.offset(rec, sc), 1)
        q = self.cell(row, j)
        m = q(0)
        # the point in the cell, and its density along each axis
        x, dens_a = _profile_sample(g, saturate((u0 - c0) / (c1 - c0)), _profile(g, [q(n) for n in self.on_a]))
        a = fma(x, a1 - a0, a0)
        y, dens_b = _profile_sample(g, saturate((v - d0) / m), _profile(g, [q(n) for n in self.on_b]))
        db = b1 - b0
        b = fma(y, db, b0)
        pdf = m * (dens_a * dens_b) / ((a1 - a0) * db)
        return a, b, g.combine(*(q(n) for n in self.on_w)), pdf

    def locate(self, a, b):
        """Tables._locate after `incident`: (pdf, W (colour)) at table coordinates a, b."""
        g, lay = self.g, self.lay
        R, C, sr, sc = lay["R"], lay["C"], lay["row_stride"], lay["col_stride"]
        rows = self.rows()
        i = self.search(g.const(0.0), a, rows, sr, _log2(R), 1, self.last[0])
        rec = self.at(rows, i, sr)
        a0, a1 = self.quantity(rec, 1), self.quantity(self.offset(rec, sr), 1)
        row = self.row(i)
        cols = self.offset(row, lay["x_col"])
        j = self.search(g.const(0.0), b, cols, sc, _log2(C), 1, self.last[1])
        rec = self.at(cols, j, sc)
        b0, b1 = self.quantity(rec, 1), self.quantity(self.offset(rec, sc), 1)
        q = self.cell(row, j)
        da, db = a1 - a0, b1 - b0
        dens_a = _profile_density(g, saturate((a - a0) / da), _profile(g, [q(n) for n in self.on_a]))
        dens_b = _profile_density(g, saturate((b - b0) / db), _profile(g, [q(n) for n in self.on_b]))
        pdf = q(0) * (dens_a * dens_b) / (da * db)
        return pdf, g.combine(*(q(n) for n in self.on_w))


def _log2(n):
    """Binary search steps over n entries."""
    return max(int(n - 1).bit_length(), 0)


def _from_ab(g, a, b, phi_i):
    """bake/core/tables.py from_ab: wo (floats x, y, z) in the local frame, where wi has azimuth phi_i
    (None: 0, the isotropic frame that follows wi)."""
    sin_o = sqrt(a * (2.0 - a))
    phi_o = b + phi_i if phi_i is not None else b
    return sin_o * cos(phi_o), sin_o * sin(phi_o), 1.0 - a


def _to_ab(g, wo, phi_i):
    """bake/core/tables.py to_ab (phi_ref = phi_i + pi) of a local direction (floats x, y, z)."""
    x, y, z = wo
    a = (x * x + y * y) / (maximum(z, 0.0) + 1.0)
    a = where(z > 0.0, minimum(a, 1.0), 1.0)
    azimuth = atan2(y, x)
    if phi_i is not None:
        azimuth = azimuth - phi_i
    return a, azimuth % (2.0 * math.pi)


def _turn(g, w, angle):
    """Floats (x, y, z) turned about z by the socket `angle`."""
    c, s = cos(angle), sin(angle)
    return c * w[0] - s * w[1], fma(s, w[0], c * w[1]), w[2]


def _log_mean(g, v0, v1):
    """bake/core/profiles.py _log_mean: (v1 - v0) / log(v1 / v0), its series where they are close;
    and log(v1 / v0) (the piece's rate)."""
    r = v1 / v0
    lr = log(r)
    small = abs(lr) < LOG_MEAN_SERIES
    exact = v0 * ((r - 1.0) / lr)
    series = fma(lr, fma(lr, 1.0 / 6.0, 0.5), 1.0)
    return where(small, v0 * series, exact), lr


def _profile(g, nodes):
    """A cell's blended profile along one axis: its node values, the pieces' masses and their
    total (bake/core/profiles.py profile_parts), and the pieces' log rates."""
    n = len(nodes) - 1
    means, rates = zip(*(_log_mean(g, nodes[k], nodes[k + 1]) for k in range(n)))
    masses = [mean * (1.0 / n) for mean in means]
    total = masses[0]
    for mk in masses[1:]:
        total = total + mk
    return nodes, masses, total, rates


def _pick(g, steps, values):
    """values[k] for k = the number of the 0 / 1 sockets `steps` that are 1 (a prefix of them)."""
    out = values[0]
    for step, value in zip(steps, values[1:]):
        out = where(step, value, out)
    return out


def _profile_piece(g, steps, nodes, rates):
    """The piece's start value and its log rate (the one _profile computed: the same value as
    log(v1 / v0) of the picked end values, without a second logarithm)."""
    return _pick(g, steps, nodes[:-1]), _pick(g, steps, rates)


def _profile_sample(g, u, profile):
    """bake/core/profiles.py profile_sample: the place of u and the profile's density there (from
    the piece found: its start value, rate and place t)."""
    nodes, masses, total, rates = profile
    n = len(masses)
    target = u * total
    cum, steps = [], []
    c = masses[0]
    for k in range(1, n):
        cum.append(c)
        steps.append(1.0 - (target < c))      # cum_k <= target
        c = c + masses[k]
    prev = _pick(g, steps, [0.0] + cum)
    mk = _pick(g, steps, masses)
    v0, rate = _profile_piece(g, steps, nodes, rates)
    t, _ = _exp_inverse_cdf(g, saturate((target - prev) / mk), rate)
    k = steps[0]
    for step in steps[1:]:
        k = k + step
    density = v0 * exp(t * rate) / total
    return (k + t) / float(n), density


def _profile_density(g, x, profile):
    """bake/core/profiles.py profile_density."""
    nodes, masses, total, rates = profile
    n = len(masses)
    s = x * float(n)
    steps = [1.0 - (s < float(k)) for k in range(1, n)]
    k = steps[0]
    for step in steps[1:]:
        k = k + step
    t = saturate(s - k)
    v0, rate = _profile_piece(g, steps, nodes, rates)
    return v0 * exp(t * rate) / total


def _expm1(g, k):
    """e^k - 1 to float precision near k = 0: 2 sinh(k / 2) e^(k / 2)."""
    h = k * 0.5
    return sinh(h) * exp(h) * 2.0


def _log1p(g, z):
    """log(1 + z) to float precision near z = 0: log(w) z / (w - 1) with w = 1 + z, or z
    where w rounds to 1."""
    w = z + 1.0
    d = w - 1.0
    rounds = abs(d) < 1e-30
    return fma(rounds, z, log(w) * (z / d))


def _small(g, k):
    return abs(k) < K_SMALL


def _exp_inverse_cdf(g, u, k):
    """bake/core/profiles.py exp_inverse_cdf, both branches, one selected; also e^k - 1 (reused)."""
    series = fma(k * (u * (1.0 - u)), 0.5, u)
    ex = _expm1(g, k)
    exact = _log1p(g, u * ex) / k
    return saturate(where(_small(g, k), series, exact)), ex


def _tables_group(sampler, kind, inputs, outputs, build):
    """Group "tables <kind>" of a sampler's texture, inputs Cos I (clamped to >= 0), Phi I
    (anisotropic tables) and `inputs`; build(g, sampler in the group, group inputs, cos_i,
    phi_i) -> {output: socket}. (A group: every node added to a tree costs in proportion to
    the tree's size (_Graph), and a material rebuilt on the same texture reuses it.)"""
    phi = [("Phi I", "Float")] if sampler.lay["P"] > 1 else []
    done, tree = _group(f"{GROUP_PREFIX}tables {kind}: {sampler.image.name}", [("Cos I", "Float")] + phi + inputs,
                        outputs)
    if done:
        return done
    g = _Graph(tree)
    inp = g.outputs(g.node("NodeGroupInput"))
    values = build(g, _Sampler(g, sampler.path, sampler.lay), inp, inp["Cos I"], inp["Phi I"] if phi else None)
    out = g.node("NodeGroupOutput")
    for name, value in values.items():
        g.set(out.inputs[name], value)
    return tree


def _tables_call(g, sampler, kind, cos_i, phi_i, **inputs):
    """The outputs of the group `kind` (_TABLES_GROUPS) of the sampler's texture at these inputs."""
    if phi_i is not None:
        inputs["Phi I"] = phi_i
    inputs_, outputs, build = _TABLES_GROUPS[kind]
    return g.group(_tables_group(sampler, kind, inputs_, outputs, build), **{"Cos I": cos_i}, **inputs)


def _pdf_in_group(g, inner, inp, cos_i, phi_i):
    pdf, fcos = _inverse(g, inner, cos_i, phi_i, (inp["X"], inp["Y"], inp["Z"]))
    return {"Pdf": pdf, "F cos": fcos}


def _sample_in_group(g, inner, inp, cos_i, phi_i):
    inner.incident(cos_i, phi_i)
    a, b, weight, pdf = inner.sample(inp["U0"], inp["U1"])
    wo, jac = inner.direction(a, b, cos_i, phi_i)
    if jac is not None:
        pdf = pdf / jac
    return {"X": wo[0], "Y": wo[1], "Z": wo[2], "Weight": weight, "Pdf": pdf}


# The per-texture groups: "pdf", _inverse's pdf and f·cos at the local direction (X, Y, Z);
# "sample", Tables.sample at U0, U1: the local direction, the weight W and the pdf per steradian.
_TABLES_GROUPS = {
    "pdf": ([("X", "Float"), ("Y", "Float"), ("Z", "Float")], [("Pdf", "Float"), ("F cos", "Vector")],
            _pdf_in_group),
    "sample": ([("U0", "Float"), ("U1", "Float")],
               [("X", "Float"), ("Y", "Float"), ("Z", "Float"), ("Weight", "Vector"), ("Pdf", "Float")],
               _sample_in_group),
}


def _tables_sample(g, sampler, cos_i, phi_i, u0, u1):
    """(local direction (x, y, z), W, pdf per steradian) of the tables' sample at u0, u1."""
    out = _tables_call(g, sampler, "sample", cos_i, phi_i, U0=u0, U1=u1)
    return (out["X"], out["Y"], out["Z"]), out["Weight"], out["Pdf"]


def _inverse(g, sampler, cos_i, phi_i, wo):
    """(pdf, f·cos) at the local direction wo (floats x, y, z), both 0 for wo_z <= 0."""
    sampler.incident(cos_i, phi_i)
    a, b, jac = sampler.coordinates(wo, cos_i, phi_i)
    pdf, weight = sampler.locate(a, b)
    if jac is not None:
        pdf = pdf / jac
    pdf = pdf * (wo[2] > 0.0)
    return pdf, g.scale(weight, pdf)

"""Ray intersection, vectorized over rays: a triangle BVH plus analytic spheres, planes and lathes.

The BVH is built once (median split on the longest centroid axis, leaves of at most
LEAF_SIZE triangles) and traversed breadth-first for all rays at once: a list of
(ray, node) pairs is culled by the slab test against the ray's current nearest hit, leaf
pairs expand into (ray, triangle) pairs tested with Moller-Trumbore, inner pairs into
their two children.
"""
import numpy as np

LEAF_SIZE = 4
EPS_T = 1e-9


def _safe_inv(d):
    return 1.0 / np.where(np.abs(d) < 1e-30, 1e-30, d)


class TriangleBVH:
    def __init__(self, v0, v1, v2):
        self.v0 = np.ascontiguousarray(v0, float)
        self.e1 = np.ascontiguousarray(v1 - v0, float)
        self.e2 = np.ascontiguousarray(v2 - v0, float)
        n = len(self.v0)
        lo = np.minimum(np.minimum(v0, v1), v2)
        hi = np.maximum(np.maximum(v0, v1), v2)
        cen = (lo + hi) * 0.5
        order = np.arange(n)
        bmin, bmax, left, right, start, count = [], [], [], [], [], []

        def new_node():
            for lst in (bmin, bmax, left, right, start, count):
                lst.append(None)
            return len(bmin) - 1

        stack = [(new_node(), 0, n)]
        while stack:
            node, s, e = stack.pop()
            idx = order[s:e]
            bmin[node], bmax[node] = lo[idx].min(axis=0), hi[idx].max(axis=0)
            if e - s <= LEAF_SIZE:
                left[node], right[node], start[node], count[node] = -1, -1, s, e - s
                continue
            c = cen[idx]
            axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
            mid = (e - s) // 2
            part = np.argpartition(c[:, axis], mid)
            order[s:e] = idx[part]
            a, b = new_node(), new_node()
            left[node], right[node], start[node], count[node] = a, b, 0, 0
            stack += [(a, s, s + mid), (b, s + mid, e)]
        self.order = order
        self.v0, self.e1, self.e2 = self.v0[order], self.e1[order], self.e2[order]
        self.bmin, self.bmax = np.array(bmin), np.array(bmax)
        self.left, self.right = np.array(left), np.array(right)
        self.start, self.count = np.array(start), np.array(count)

    def intersect(self, o, d, t_best, any_hit=False):
        """Nearest hits with t < t_best (updated in place). Returns (tri, b1, b2): the
        triangle (original index, -1 where none) and barycentrics."""
        n = len(o)
        tri = np.full(n, -1)
        b1 = np.zeros(n)
        b2 = np.zeros(n)
        inv = _safe_inv(d)
        rays = np.arange(n)
        nodes = np.zeros(n, dtype=np.int64)
        done = np.zeros(n, bool)
        while rays.size:
            if any_hit:
                keep = ~done[rays]
                rays, nodes = rays[keep], nodes[keep]
            t0 = (self.bmin[nodes] - o[rays]) * inv[rays]
            t1 = (self.bmax[nodes] - o[rays]) * inv[rays]
            tn = np.minimum(t0, t1).max(axis=1)
            tf = np.maximum(t0, t1).min(axis=1)
            hit = (tn <= tf) & (tf > 0) & (tn < t_best[rays])
            rays, nodes = rays[hit], nodes[hit]
            cnt = self.count[nodes]
            leaf = cnt > 0
            if leaf.any():
                lr, ln, lc = rays[leaf], nodes[leaf], cnt[leaf]
                r = np.repeat(lr, lc)
                first = np.repeat(np.cumsum(lc) - lc, lc)
                k = np.repeat(self.start[ln], lc) + (np.arange(len(r)) - first)
                t, u, v = self._moller(o[r], d[r], k)
                ok = (t > EPS_T) & (t < t_best[r])
                r, k, t, u, v = r[ok], k[ok], t[ok], u[ok], v[ok]
                if r.size:
                    np.minimum.at(t_best, r, t)
                    win = t == t_best[r]
                    tri[r[win]], b1[r[win]], b2[r[win]] = k[win], u[win], v[win]
                    done[r] = True
            inner = ~leaf
            rays = np.concatenate([rays[inner], rays[inner]])
            nodes = np.concatenate([self.left[nodes[inner]], self.right[nodes[inner]]])
        return np.where(tri >= 0, self.order[np.maximum(tri, 0)], -1), b1, b2

    def _moller(self, o, d, k):
        e1, e2 = self.e1[k], self.e2[k]
        p = np.cross(d, e2)
        det = np.sum(e1 * p, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o - self.v0[k]
            u = np.sum(s * p, axis=1) * inv
            q = np.cross(s, e1)
            v = np.sum(d * q, axis=1) * inv
            t = np.sum(e2 * q, axis=1) * inv
        ok = (np.abs(det) > 1e-18) & (u >= 0) & (v >= 0) & (u + v <= 1)
        return np.where(ok, t, np.inf), u, v


def intersect_spheres(o, d, centers, radii, t_best):
    """Nearest sphere hit per ray with t < t_best (updated in place); index or -1."""
    idx = np.full(len(o), -1)
    for k, (c, r) in enumerate(zip(centers, radii)):
        oc = o - c
        b = np.sum(oc * d, axis=1)
        cc = np.sum(oc * oc, axis=1) - r * r
        disc = b * b - cc
        sq = np.sqrt(np.maximum(disc, 0.0))
        t_near, t_far = -b - sq, -b + sq
        t = np.where(t_near > EPS_T * (1 + r), t_near, t_far)
        ok = (disc > 0) & (t > EPS_T * (1 + r)) & (t < t_best)
        t_best[ok] = t[ok]
        idx[ok] = k
    return idx


def intersect_planes(o, d, points, normals, axes, half_sizes, t_best):
    """Planes (infinite where half_size is inf, else squares); index or -1."""
    idx = np.full(len(o), -1)
    for k, (p, n, (ax_u, ax_v), h) in enumerate(zip(points, normals, axes, half_sizes)):
        dn = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((p - o) @ n) / dn
        ok = (np.abs(dn) > 1e-18) & (t > EPS_T) & (t < t_best)
        if np.isfinite(h):
            x = o + t[:, None] * d - p
            ok &= (np.abs(x @ ax_u) <= h) & (np.abs(x @ ax_v) <= h)
        t_best[ok] = t[ok]
        idx[ok] = k
    return idx


def _roots(a, b, c):
    """Both roots of a t² + 2 b t + c = 0 (t0 <= t1), NaN where there are none."""
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        q = -(b + np.copysign(sq, b))
        r0, r1 = q / a, c / q
    good = (disc >= 0) & (a > 0)
    return np.where(good, np.minimum(r0, r1), np.nan), np.where(good, np.maximum(r0, r1), np.nan)


def intersect_lathe(o, d, pieces, t_best):
    """A surface of revolution about the z axis made of analytic pieces, in its own frame:
    ("disk", z, r0, r1), ("cylinder", r, z0, z1), ("sphere", zc, R, z0, z1).
    Returns (piece index or -1, normal (N, 3)) and updates t_best."""
    n = len(o)
    idx = np.full(n, -1)
    normal = np.zeros((n, 3))
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    for k, piece in enumerate(pieces):
        if piece[0] == "disk":
            _, z, r0, r1 = piece
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (z - oz) / dz
            x, y = ox + t * dx, oy + t * dy
            r2 = x * x + y * y
            ok = (t > EPS_T) & (t < t_best) & (r2 >= r0 * r0) & (r2 <= r1 * r1)
            t_best[ok] = t[ok]
            idx[ok] = k
            normal[ok] = [0.0, 0.0, 1.0]
            continue
        if piece[0] == "cylinder":
            _, r, z0, z1 = piece
            a, b, c = dx * dx + dy * dy, ox * dx + oy * dy, ox * ox + oy * oy - r * r
        else:
            _, zc, R, z0, z1 = piece
            ozc = oz - zc
            a, b, c = np.ones(n), ox * dx + oy * dy + ozc * dz, ox * ox + oy * oy + ozc * ozc - R * R
        t0, t1 = _roots(a, b, c)
        z_0, z_1 = oz + t0 * dz, oz + t1 * dz
        v0 = (t0 > EPS_T) & (z_0 >= z0) & (z_0 <= z1)
        v1 = (t1 > EPS_T) & (z_1 >= z0) & (z_1 <= z1)
        t = np.where(v0, t0, np.where(v1, t1, np.inf))
        ok = (v0 | v1) & (t < t_best)
        if not ok.any():
            continue
        t_best[ok] = t[ok]
        idx[ok] = k
        p = o[ok] + t[ok, None] * d[ok]
        if piece[0] == "cylinder":
            nm = np.stack([p[:, 0], p[:, 1], np.zeros(len(p))], axis=1) / r
        else:
            nm = (p - np.array([0.0, 0.0, zc])) / R
        normal[ok] = nm
    return idx, normal

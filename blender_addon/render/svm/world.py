"""The world's importance map as SVM nodes: its layout (`world_layout`), its sampling and its pdf
(node groups "world sample", "world pdf": blender_addon/render/osl/world.h, bake/export/world_map.py's
WorldMap the numpy reference), the map's numbers constants of groups named after its image."""
import math
import os

from .graph import (GROUP_PREFIX, X, Y, Z, _Graph, _group, _image, acos, atan2, cos, floor, fma, maximum, minimum,
                    saturate, sin, sqrt)


def _world_map_module():
    import importlib
    from ... import deps
    return importlib.import_module(f"{deps.bake.__name__}.export.world_map")


_world_layouts = {}


def world_layout(path):
    """The numbers the graph needs of a world importance map (bake/export/world_map.py's texture): W,
    H (map pixels), Wt, Ht (texture texels), the binary searches' steps over its rows and
    columns, its layout; None when `path` is empty or not a current world map (then the graph
    draws no world-map samples). Read once per file version from the image's pixels (numpy; no
    OpenEXR module needed)."""
    if not path or not os.path.isfile(path):
        return None
    stat = os.stat(path)
    key = (os.path.abspath(path), stat.st_mtime_ns, stat.st_size)
    if key not in _world_layouts:
        _world_layouts[key] = _read_world_layout(path)
    return _world_layouts[key]


def _read_world_layout(path):
    try:
        import numpy as np
        layout = _world_map_module().LAYOUT
        image = _image(path)
        wt, ht = image.size
        px = np.empty(wt * ht * 4, np.float32)
        image.pixels.foreach_get(px)
    except (ImportError, RuntimeError, ValueError):
        return None
    if wt < 2 or ht < 3:
        return None
    px = px.reshape(ht, wt, 4)[::-1]        # Blender's pixels start at the bottom row
    version, w, h = px[0, 0, :3]
    if version != layout or min(w, h) < 1 or ht < 2 + h or wt <= max(w, h):
        return None
    w, h = int(w), int(h)
    return {"W": w, "H": h, "Wt": wt, "Ht": ht, "row_steps": (h - 1).bit_length(), "col_steps": (w - 1).bit_length(),
            "layout": layout}


def _world_texel(g, wl, image, x, row):
    """The colour of the world texture's texel (x, row)."""
    tex = g.node("ShaderNodeTexImage", image=image, interpolation='Closest', extension='EXTEND')
    wt, ht = float(wl["Wt"]), float(wl["Ht"])
    g.set(tex.inputs["Vector"], g.combine(fma(x, 1.0 / wt, 0.5 / wt), fma(row, -1.0 / ht, 1.0 - 0.5 / ht)))
    return tex.outputs["Color"]


def _world_group_name(kind, wl, image):
    return f"{GROUP_PREFIX}world{wl['layout']} {kind}: {image.name}"


def _is_world_group(name, kind):
    """Whether a node group is a world group of this kind (of any map, any layout)."""
    head = name.split(": ")[0]
    return head.startswith(f"{GROUP_PREFIX}world") and head.endswith(f" {kind}")


def _world_group(kind, wl, image, inputs, outputs, build):
    """The node group `kind` of a world texture (its numbers are constants of the group): a new
    map gets new groups, which update_world swaps in."""
    done, tree = _group(_world_group_name(kind, wl, image), inputs, outputs)
    if done:
        return done
    g = _Graph(tree)
    results = build(g, g.outputs(g.node("NodeGroupInput")))
    out = g.node("NodeGroupOutput")
    for name, value in results.items():
        g.set(out.inputs[name], value)
    return tree


def _world_step_group(wl, image):
    """Group "world search step" over a CDF in texture row Row (entries 0 .. Last, the last 1):
    index = Lo + Half; Lo moves there when its entry (past Last: the last, 1) is <= Target."""
    def build(g, inp):
        index = inp["Lo"] + inp["Half"]
        entry = g.dot(_world_texel(g, wl, image, minimum(index, inp["Last"]), inp["Row"]), X)
        above = entry > inp["Target"]
        return {"Lo": fma(above, -inp["Half"], index)}
    return _world_group("search step", wl, image, [("Lo", "Float"), ("Target", "Float"), ("Half", "Float"),
                                                   ("Row", "Float"), ("Last", "Float")],
                        [("Lo", "Float")], build)


def _world_search(g, wl, image, u, row, last, steps):
    """(k, cdf_k, cdf_k+1): the last entry k < last of the CDF in texture row `row` with cdf_k <=
    u, found branchlessly in `steps` halvings (2^steps >= last)."""
    lo = g.const(0.0)
    for s in reversed(range(steps)):
        lo = g.group(_world_step_group(wl, image), Lo=lo, Target=u, Half=float(2 ** s), Row=row, Last=float(last))[0]
    c0 = g.dot(_world_texel(g, wl, image, lo, row), X)
    c1 = g.dot(_world_texel(g, wl, image, lo + 1.0, row), X)
    return lo, c0, c1


def _world_sample_group(wl, image):
    """Group "world sample": world.h sample_world / WorldMap.sample. The pixel's row by the
    rows' marginal CDF (U0), its column by the row's conditional CDF (U1), each searched
    branchlessly; the direction uniform in the pixel's solid angle (z from U0's place in its
    row's share, azimuth from U1's in its pixel's); Pdf is the pixel's density per steradian."""
    def build(g, inp):
        u0, u1 = inp["U0"], inp["U1"]
        w, h = float(wl["W"]), float(wl["H"])
        row, r0, r1 = _world_search(g, wl, image, u0, g.const(1.0), wl["H"], wl["row_steps"])
        cond_row = row + 2.0
        col, c0, c1 = _world_search(g, wl, image, u1, cond_row, wl["W"], wl["col_steps"])
        t_row = saturate((u0 - r0) / (r1 - r0))
        t_col = saturate((u1 - c0) / (c1 - c0))
        z0 = cos(row * (math.pi / h))
        z1 = cos(fma(row, math.pi / h, math.pi / h))
        z = fma(t_row, z1 - z0, z0)
        phi = fma(col + t_col, -2.0 * math.pi / w, math.pi)
        s = sqrt(maximum(1.0 - z * z, 0.0))
        direction = g.combine(s * cos(phi), s * sin(phi), z)
        return {"Direction": direction, "Pdf": g.dot(_world_texel(g, wl, image, col, cond_row), Y)}
    return _world_group("sample", wl, image, [("U0", "Float"), ("U1", "Float")],
                        [("Direction", "Vector"), ("Pdf", "Float")], build)


def _world_pdf_group(wl, image):
    """Group "world pdf": world.h pdf_world / WorldMap.pdf, the density per steradian of the
    map's sampling at a unit Direction (its pixel's)."""
    def build(g, inp):
        d = inp["Direction"]
        w, h = float(wl["W"]), float(wl["H"])
        theta = acos(g.dot(d, Z))            # (Cycles' acos clamps its argument)
        row = minimum(floor(theta * (h / math.pi)), h - 1.0)
        u = fma(atan2(g.dot(d, Y), g.dot(d, X)), -0.5 / math.pi, 0.5) % 1.0
        col = minimum(floor(u * w), w - 1.0)
        return {"Pdf": g.dot(_world_texel(g, wl, image, col, row + 2.0), Y)}
    return _world_group("pdf", wl, image, [("Direction", "Vector")], [("Pdf", "Float")], build)


_WORLD_GROUPS = {"sample": _world_sample_group, "pdf": _world_pdf_group}

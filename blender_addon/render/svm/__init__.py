"""The baked-table sampler as a plain Cycles shader node graph (SVM): every Cycles device.

`build_svm_sampler` adds to a shader node tree the nodes that reproduce `Tables.sample`
(bake/core/tables.py) on the texture of bake/export/svm_export.py and end in a Ray Portal BSDF
that continues the path in the sampled direction with weight W = baked f·cos / pdf; with the
world's inputs the direction comes from a mixture of the tables, the world's map, the sky's sun
and the lamps, and with the fit a control variate renders part of it as Cycles closures. No OSL:
the graph runs wherever Cycles runs. The package mirrors blender_addon/render/osl/:

    graph.py            the builder (nodes in evaluation order, node groups, packed textures)
    tables.py           the tables' sampler and its inverse (osl/tables.h)
    halfvector.py       the half-vector cell coordinates (osl/tables.h, bake/core/halfvector.py)
    world.py            the world map's sampling and pdf (osl/world.h)
    mixture.py          the portal's mixture of techniques, lamps included (learned_bsdf.osl, lamps.h)
    control_variate.py  the fit's closures as a control variate
    film.py             a path vertex's u: hashed, or from the film (osl/random.h)
    shader.py           the shading point and the shader: build_svm_sampler, sample_graph, tables_pdf_graph

What the graph does per shading point, why it is built as it is (Cycles' SVM stack) and what
was measured: docs/svm.md. Test probes (graphs on inputs read from an image, node counts):
tests/svm_probes.py.
"""
from .control_variate import (CV, CV_TILTS, MATCHED_LIGHT_SCALE, MATCHED_SHARE_MIN, VIEW_TANGENT_EPS,
                              VIEW_TANGENT_NUDGE, control_variate_wanted)
from .film import FILM, film_settings, set_film
from .graph import GRAPH_VERSION, GROUP_PREFIX, PACKED, X, Y, Z, _image
from .mixture import LAMP, LAMPS, LIGHT, SUN, WORLD, update_world
from .shader import CUTOFF, TANGENT, build_svm_sampler, sample_graph, tables_pdf_graph
from .world import world_layout

__all__ = ["CUTOFF", "CV", "CV_TILTS", "FILM", "GRAPH_VERSION", "GROUP_PREFIX", "LAMP", "LAMPS", "LIGHT",
           "MATCHED_LIGHT_SCALE", "MATCHED_SHARE_MIN", "PACKED", "SUN", "TANGENT", "VIEW_TANGENT_EPS",
           "VIEW_TANGENT_NUDGE", "WORLD", "X", "Y", "Z", "_image", "build_svm_sampler", "control_variate_wanted",
           "film_settings", "sample_graph", "set_film", "tables_pdf_graph",
           "update_world", "world_layout"]

"""The version numbers of FlowBSDF's files and graphs, in one place: numpy (bake/), the Blender
add-on (blender_addon/: it reads this file by its path, without numpy: deps.formats) and the OSL
shader (blender_addon/render/osl/*.h: its #defines, held equal to these by tests/test_formats.py).

Plain Python, no imports: the bottom of bake/. A table format change bumps FORMAT (or
MIXED_FORMAT) and the layouts of the textures made from the tables (OSL_LAYOUT, SVM_LAYOUT), and
the shader's or graph's reader of those layouts with them.
"""

# The table file (bake/core/tables.py; opened by table_files.py). 5: the cell edges once per layout, "layouts" naming each
# bin's (3: once per bin; alpha and beta hold profiles since 3, 2 held exponentials' leans, 1 their
# rates)
FORMAT = 5
MIXED_FORMAT = 6        # the file of a MixedTables: its parts' arrays side by side (4: edges once per bin)

# Bumped when the construction changes in a way that should rebuild existing tables (a table file
# records it among its inputs: bake/plumbing/pipeline.inputs_of).
BUILDER = 13             # 2: cells that miss a hard-edged sliver of mass are integrated around their points
                         # 3: isotropic plans aim at the ideal tabulation's rv (planner.plan_tables)
                         # 4: when no resolution reaches its target, the closest one (not the largest)
                         # 5: cells per lobe segment by weight, an even share of every segment (tabulate.SHARES)
                         # 6: isotropic tables over the half vector where that plans closer (planner.ISO_PLANNED)
                         # 7: measured files' own incident angles among the first bins (Material.measured_theta_i)
                         # 8: split while a midpoint loses over half its target (planner.SPLIT_LOSS)
                         # 9: isotropic: one cell layout for all bins where that interpolates closer (planner.LAYOUT_WINDOWS)
                         # 10: isotropic: two layout groups (a repeated boundary bin) where that interpolates closer (planner._between_bins);
                         #     a ridge on the plane of incidence integrated beside it (tabulate._ridge_edges)
                         # 11: isotropic: layout groups of their own resolutions (mixed_tables.MixedTables), placements
                         #     compared at quarter points too
                         # 12: bins placed alike store their edges once (tables.Tables.layouts): the budget keeps more bins
                         # 13: isotropic RGL files: which intervals carry (tables.meta["carried"], bake setting `carry`)

# The OSL texture (bake/export/osl_export.py; osl/tables.h's LAYOUT; part of its file name, which
# the node builds without numpy). 8: tables of mixed resolutions (each corner's own rows and
# columns: its guides, its count texel); 9: a cell in three RGBA texels (weight with the profiles),
# the header in two; 10: isotropic corners' sums carry their edges (blue, alpha); 11: what a sample
# reads together lies together (cells' texels and bins, a table row's sums, edges, guide); 12: the
# header also as the file's attributes (the shader reads it by gettextureinfo: folded when compiled)
OSL_LAYOUT = 12
# The SVM texture (bake/export/svm_export.py). 4: tables of mixed resolutions (isotropic headers
# hold the corner's last row and column); 5: the theta guide over sqrt(1 - cos theta_i) (bins a
# fraction of a degree apart near the normal: ilm_solo_m_68's default bake)
SVM_LAYOUT = 5
WORLD_LAYOUT = 3        # the world map's texture (bake/export/world_map.py; osl/world.h)
CARRY_LAYOUT = 1        # the carried blend's texture (bake/export/carry_export.py; osl/carried.h)

# The SVM graph (blender_addon/render/svm/graph.py): in the node groups' names, so a graph built by other code
# gets new groups
GRAPH_VERSION = 4       # 4: the theta guide's entry from sqrt(1 - cos theta_i)

# The closure fit file (bake/export/closure_fit.py, read without numpy by blender_addon/render/derived.py)
FIT_VERSION = 10        # 9: anisotropic tables' lobes along the material's tangent; 10: and their control variate
READABLE_FIT_VERSIONS = (6, 7, 8, 9, 10)    # a version 6 fit has no tilts (all 0), 6 and 7 no "eevee"


def fit_current(version, anisotropic):
    """Whether a fit of `version` is the one FIT_VERSION makes: isotropic tables' fits have not
    changed since 8 (so they are not made again), anisotropic ones since 10."""
    return version == FIT_VERSION or (version in (8, 9) and not anisotropic)

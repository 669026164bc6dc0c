"""The samplers and what they stand on (numpy only).

    sampler        the sampler contract; every sampler by name (open_sampler)
    flow           the learned flow sampler: a trained model (.flow.npz) run exactly
    flow_maps      the flow's coordinate maps: flow coordinates <-> outgoing directions
    special        special functions of the flow's base distributions
    tables         baked tables (.exr): an exact, table-speed sampler per material
    carried        an RGL file's tables blended along the file's own coordinates (numpy only)
    fasttables     the tables' optional C fast path (_tables_c.c, loaded with ctypes)
    tabulate       building tables from a material and a source sampler
    settings       BakeSettings: a manifest's [bake] table, checked once, as the planner takes it
    ideal          the ideal sampler: f·cos tabulated finely per incident direction
    baselines      uniform, cosine and a fitted GGX lobe: what every learned sampler must beat
    domains        2D sampling domains of outgoing directions (disk, spherical)
    warps          the maps between the unit square and directions that several modules share
    halfvector     the anisotropic tables' coordinates: the half vector on a disk
    geometry       directions in the local shading frame, luminance
"""

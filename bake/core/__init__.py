"""The samplers and what they stand on (numpy only).

    sampler        the sampler contract; every sampler by name (open_sampler)
    flow           the learned flow sampler: a trained model (.flow.npz) run exactly
    flow_maps      the flow's coordinate maps: flow coordinates <-> outgoing directions
    domains        2D sampling domains of outgoing directions (disk, spherical)
    tables         baked tables (.exr): an exact, table-speed sampler per material
    profiles       the tables' cells' 1-D profiles: CDF, inverse CDF, density
    mixed_tables   MixedTables: layout groups of their own resolutions, one sampler
    table_files    open_tables: a table file as Tables or MixedTables, its checks
    halfvector     the anisotropic tables' coordinates: the half vector on a disk
    carried        an RGL file's tables blended along the file's own coordinates (numpy only)
    tabulate       building tables from a material and a source sampler
    planner        plan_tables: the resolution, bins and layout a material's tables need, then built
    settings       BakeSettings: a manifest's [bake] table, checked once, as the planner takes it
    ideal          the ideal sampler: f·cos tabulated finely per incident direction
    baselines      uniform, cosine and a fitted GGX lobe: what every learned sampler must beat
    metrics        relative variance of the albedo estimator (what the baker plans with, and the
                   reports measure); chi-square of sample() vs pdf()
"""

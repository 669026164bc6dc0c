"""The maths the materials and the samplers share (numpy; the C fast path optional).

    geometry       directions in the local shading frame, luminance
    warps          the maps between the unit square and directions that several modules share
    special        special functions (normal, von Mises) of the flow's base distributions
    fasttables     the C fast path (_tables_c.c, loaded with ctypes) of the tables, of an RGL
                   file's evaluation and warp, and of the baker's quadrature
"""

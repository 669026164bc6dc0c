"""What Blender's Cycles back ends read: baked tables and the world turned into shader data.

    derived        what the node needs beside a table file (bake_derived), the exporter contract
    osl_export     the tables as the texture the OSL shader reads (blender_addon/render/osl/)
    svm_export     the tables as the texture the SVM node graph reads (blender_addon/render/svm/)
    carry_export   the carried blend's data as the texture the OSL shader reads (osl/carried.h)
    closure_fit    Cycles closures (diffuse + GGX) fitted to the tables: the fit back end
    guides         the search guides the OSL and SVM textures store
    world_map      the world's importance map, where the back ends sample the environment
"""

"""The render side: what a Learned BSDF node renders, with or without the artist side (a saved
.blend renders in any Blender; farms bind nodes with no panel). Never imports artist/.
    node        the node group: built, rebuilt, synced with the scene, the file handlers
    backends    which back end renders in a scene and why, in the UI's words (Status)
    binding     the group's binding data (paths relative to the .blend)
    derived     the files beside the tables the node reads (fit JSON, textures), without numpy
    osl_script  the OSL Script node (osl/ inlined into a text block of the .blend)
    osl/        the OSL back end's shader (tables, carried blend, lamps, world, random numbers)
    fit_nodes   the fit back end's node group and closures (also the SVM control variate's)
    refits      an older add-on's fits remade after a file opens
    lamps       the scene's lamps -> the shaders      world    the world's importance map
    sockets     group sockets across Blender versions; values written only on change
The SVM back end's graph (svm) is the render side's too.
"""

"""FlowBSDF for Blender: learned importance sampling of measured BSDFs in Cycles."""
bl_info = {
    "name": "FlowBSDF",
    "author": "FlowBSDF developers",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "Shader Editor > Sidebar > FlowBSDF",
    "description": "Learned importance sampling of measured and analytic BSDFs",
    "category": "Material",
}


def register():
    pass


def unregister():
    pass

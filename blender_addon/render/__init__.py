"""The render side of the add-on: what Cycles and EEVEE render (the node's groups, the SVM and OSL back ends, the world and lamps)."""

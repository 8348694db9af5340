"""Stage 2 of the flow: the mesh's topology, the classification of its boundary nodes and the constraints that
keep them on the boundary."""

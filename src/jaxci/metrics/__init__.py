"""Stage 3 of the flow: corner kernels per cell type (the hexahedron is the fast path), the objective F over all
cells and the quality report."""

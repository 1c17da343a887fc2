"""Features: creases, minutiae and the minutia set, the shading the extractor sees, and
their numba kernels. Imports terrain and render (the sun)."""

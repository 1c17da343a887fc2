"""Matching: minutia matching (parameters, index, proposals, registration, significance and
the ``Matcher`` front end), descriptors, crease check and search, baselines, the PVA fix and
the numba kernels. Imports terrain and features."""

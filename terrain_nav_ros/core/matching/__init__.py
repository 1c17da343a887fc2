"""Matching: minutiae-based terrain matching and localisation (dissertation chapter 4) and
what works with it. Imports terrain and features.

The matcher, split by role along its pipeline (:mod:`.matcher` describes the whole):
:mod:`.params` (settings, Table 4.1), :mod:`.index` (a set prepared for matching),
:mod:`.proposals` (candidate votes), :mod:`.consensus` (Hough hypotheses),
:mod:`.registration` (RANSAC, least squares, pairing, covariance), :mod:`.significance` (the
score and its threshold), :mod:`.scoring` (a registration scored, with the crease check),
:mod:`.crease_proposals` (the crease search's registrations) and :mod:`.matcher` (the
``Matcher`` front end). Beside it: :mod:`.descriptors`, :mod:`.crease_check`,
:mod:`.crease_search`, :mod:`.baselines` (the study's baselines), :mod:`.pva_fix` (a match
as a position fix), :mod:`.fix_stream` (what the ``matcher`` node decides around them) and
the numba kernels.
"""

"""Geometric primitives, each written once: half-plane polytopes (:mod:`.halfplanes`: vertices,
boundedness, Chebyshev centre), lattice hulls (:mod:`.lattice`), ellipsoid-box tests
(:mod:`.ellipsoid_box`) and the Monte Carlo volume of a union of polytopes (:mod:`.union_volume`).
Lengths in metres unless a function says lattice units.
"""

"""Regions: one field over a region-wide hinge lattice, its evidence stored in tiles.

- :mod:`bdf.region.spec`: what a region is (the schema, its geometry and tiling).
- :mod:`bdf.region.evidence`: points to per-tile and per-class increments, their sum.
- :mod:`bdf.region.map`: the posterior of that sum and the queries it answers.
"""

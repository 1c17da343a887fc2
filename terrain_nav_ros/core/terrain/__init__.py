"""Terrain: DEM reading and sources, the metamap and its interpolation, geodesy, geo-
referencing, the tile policy and synthetic terrain. Imports no other stage."""

"""Tiled reconstruction beyond one machine (issue 15): a partition of unity over k-d tiles.

f(x) = f0(x) + sum_t W_t(x) g_t(x): :func:`o3drbf.tiles.fit.fit_tiled` fits it
(tiles as Dask tasks), :class:`o3drbf.tiles.surface.TiledSurface` evaluates
and stores it, :func:`o3drbf.tiles.extract.extract_tiled` meshes it tile by
tile on one global lattice and welds the pieces exactly.
"""

"""The forward pipeline: a pattern becomes a mesh, a shell model, its released equilibrium
and the files ``selfshape simulate`` writes (mm, N, MPa).

Sits above :mod:`shellfem` (the engine) and :mod:`geometry` (patterns and meshing) and
joins them; neither of those imports it.
"""

"""Discrete elastic rods on the sheet's vertices (the seed's chapter-3 star model).

shellfem.rods.energy: rod energies (stretching, two-axis bending with rest curvature,
twist) with exact gradients and Hessians; shellfem.rods.monolayer: the effective-monolayer
rest curvature and stiffness of a plastic-on-fabric bilayer arm (seed Eq. 3.4-3.13);
shellfem.rods.ad: the vectorised second-order differentiation they use.
"""
from shellfem.rods.energy import RodNetwork, bend_measures, build_network, rest_turning_curvature  # noqa: F401

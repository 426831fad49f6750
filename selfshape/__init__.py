"""selfshape: computational design of self-shaping textiles.

The toolkit is split by concern: :mod:`shellfem` (the forward shell engine),
:mod:`geometry` (patterns, meshing, curvature, flattening, stripes),
:mod:`inverse` (design pipeline, G-code) and :mod:`validation` (calibration,
the closed validation loop, studies). This package holds the command line.
Units everywhere: millimetres, newtons, MPa.
"""
from selfshape.errors import SelfshapeError

__all__ = ["SelfshapeError"]
__version__ = "0.1.0"

"""selfshape: computational design of self-shaping textiles.

The toolkit is layered, each package importing only those below it:
:mod:`shellfem` (the shell engine), :mod:`geometry` (patterns, meshing, surfaces, G-code),
:mod:`forward` (pattern -> mesh -> model -> equilibrium -> files), :mod:`inverse` (design),
:mod:`validation` (calibration and the validation loop). This package is the command line.
Units everywhere: millimetres, newtons, MPa.
"""
from shellfem.errors import SelfshapeError

__all__ = ["SelfshapeError"]
__version__ = "0.1.0"

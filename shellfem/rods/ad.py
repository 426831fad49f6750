"""Second-order forward differentiation, vectorised over a batch of stencils.

A :class:`Jet` holds a batch of k scalars together with their gradients (k, n) and
Hessians (k, n, n) with respect to n local inputs. Arithmetic, sqrt and atan2 propagate
all three exactly (the chain rule, no differences), so an energy written once as ordinary
formulas comes with its exact gradient and Hessian. Linear quantities carry no Hessian
(``h is None``) until a nonlinear operation creates one, which keeps the (k, n, n) work to
the operations that need it.

Why not hand-derived formulas: the discrete-elastic-rod bending and twist of
shellfem.rods depend on two unit tangents, two unit surface normals, a parallel transport
and an atan2; their Hessians by hand are long and fragile, while here each operation's
rule is a few lines that the FD tests of tests/test_rods.py check once for all energies.
The cost is O(ops x k x n^2) numpy work: with n = 12 local inputs (two edge vectors, two
frame source vectors) it is ~1 ms per 1000 stencils per operation, small next to the
shell's assembly for the star patterns' few thousand rod vertices (measured in
tests/test_rods.py::test_rod_energy_cost).
"""
from __future__ import annotations

import numpy as np


class Jet:
    """k scalars with gradient g (k, n) and Hessian h (k, n, n) (h None = zero)."""

    __slots__ = ("v", "g", "h")

    def __init__(self, v, g, h=None):
        self.v, self.g, self.h = v, g, h

    # --- construction ---------------------------------------------------------------
    @staticmethod
    def inputs(values: np.ndarray) -> list:
        """Independent inputs: values (k, n) -> n jets with unit gradients."""
        k, n = values.shape
        eye = np.eye(n)
        return [Jet(values[:, i].copy(), np.broadcast_to(eye[i], (k, n))) for i in range(n)]

    # --- helpers ----------------------------------------------------------------------
    @staticmethod
    def _h(a, b):
        if a is None:
            return b
        if b is None:
            return a
        return a + b

    @staticmethod
    def _outer(ga, gb):
        return ga[:, :, None] * gb[:, None, :]

    def _sym_outer(self, other):
        o = self._outer(self.g, other.g)
        return o + np.swapaxes(o, 1, 2)

    # --- arithmetic -----------------------------------------------------------------------
    def __add__(self, o):
        if isinstance(o, Jet):
            return Jet(self.v + o.v, self.g + o.g, self._h(self.h, o.h))
        return Jet(self.v + o, self.g, self.h)

    __radd__ = __add__

    def __neg__(self):
        return Jet(-self.v, -self.g, None if self.h is None else -self.h)

    def __sub__(self, o):
        return self + (-o)

    def __rsub__(self, o):
        return (-self) + o

    def __mul__(self, o):
        if isinstance(o, Jet):
            h = self._sym_outer(o)
            if self.h is not None:
                h = h + self.h * o.v[:, None, None]
            if o.h is not None:
                h = h + o.h * self.v[:, None, None]
            return Jet(self.v * o.v, self.g * o.v[:, None] + o.g * self.v[:, None], h)
        o = np.asarray(o, float)
        oc = o[..., None] if o.ndim else o
        return Jet(self.v * o, self.g * oc, None if self.h is None else self.h * (oc[..., None] if o.ndim else o))

    __rmul__ = __mul__

    def unary(self, f, f1, f2):
        """phi(self) from phi, phi', phi'' evaluated at self.v (arrays (k,))."""
        h = f2[:, None, None] * self._outer(self.g, self.g)
        if self.h is not None:
            h = h + f1[:, None, None] * self.h
        return Jet(f, self.g * f1[:, None], h)

    def reciprocal(self):
        r = 1.0 / self.v
        return self.unary(r, -r * r, 2 * r * r * r)

    def __truediv__(self, o):
        if isinstance(o, Jet):
            return self * o.reciprocal()
        return self * (1.0 / np.asarray(o, float))

    def sqrt(self):
        s = np.sqrt(self.v)
        return self.unary(s, 0.5 / s, -0.25 / (s * self.v))

    def square(self):
        return self * self


def recip(a):
    """1 / a of a Jet or of a plain array (the value-only path of the energies)."""
    return a.reciprocal() if isinstance(a, Jet) else 1.0 / a


def sqrt(a):
    return a.sqrt() if isinstance(a, Jet) else np.sqrt(a)


def atan2(y: Jet, x: Jet) -> Jet:
    """atan2(y, x) with exact first and second derivatives (away from x = y = 0); of plain
    arrays, np.arctan2."""
    if not isinstance(y, Jet):
        return np.arctan2(y, x)
    r2 = x.v * x.v + y.v * y.v
    fy, fx = x.v / r2, -y.v / r2
    r4 = r2 * r2
    fyy, fxx, fxy = -2 * x.v * y.v / r4, 2 * x.v * y.v / r4, (y.v * y.v - x.v * x.v) / r4
    o = Jet._outer
    h = (fyy[:, None, None] * o(y.g, y.g) + fxx[:, None, None] * o(x.g, x.g)
         + fxy[:, None, None] * (o(x.g, y.g) + o(y.g, x.g)))
    if y.h is not None:
        h = h + fy[:, None, None] * y.h
    if x.h is not None:
        h = h + fx[:, None, None] * x.h
    return Jet(np.arctan2(y.v, x.v), fy[:, None] * y.g + fx[:, None] * x.g, h)


# --- 3-vectors as tuples of jets -----------------------------------------------------------
def dot(a, b) -> Jet:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a, b) -> tuple:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def scale(a, s) -> tuple:
    return tuple(c * s for c in a)


def add(a, b) -> tuple:
    return tuple(x + y for x, y in zip(a, b))


def unit(a) -> tuple:
    """a / |a| (and |a|)."""
    n = sqrt(dot(a, a))
    r = recip(n)
    return tuple(c * r for c in a), n


def zero_hessian(j: Jet) -> np.ndarray:
    """j's Hessian as an array (zeros when it is linear)."""
    k, n = j.g.shape
    return np.zeros((k, n, n)) if j.h is None else j.h

"""Safe, vectorised field expressions in x, y, r (printed-state mm).

A field is a number or a string such as ``"clip(10 - 6*r/54, 4, 10) / 18"``. Strings are
parsed with :mod:`ast` and only a whitelist is accepted (never ``eval``): numbers,
``+ - * / ** %``, parentheses, comparisons (``< <= > >= == !=``, for ``where``),
``and``/``or``/``not``, the names x, y, r (r = distance to the fabric outline's
centroid), the constants pi and e, and the functions sqrt, exp, log, sin, cos, tan,
abs, min, max (element-wise, 2+ arguments), clip(v, lo, hi) and where(cond, a, b).
Evaluation walks the tree once on whole numpy arrays.
"""
from __future__ import annotations

import ast
import math
from functools import reduce

import numpy as np

from geometry.schema import MAX_EXPRESSION_DEPTH
from shellfem.errors import SelfshapeError

VARIABLES = ("x", "y", "r")
CONSTANTS = {"pi": math.pi, "e": math.e}
#: name -> (numpy function, min args, max args)
FUNCTIONS = {
    "sqrt": (np.sqrt, 1, 1), "exp": (np.exp, 1, 1), "log": (np.log, 1, 1),
    "sin": (np.sin, 1, 1), "cos": (np.cos, 1, 1), "tan": (np.tan, 1, 1),
    "abs": (np.abs, 1, 1),
    "min": (lambda *a: reduce(np.minimum, a), 2, None),
    "max": (lambda *a: reduce(np.maximum, a), 2, None),
    "clip": (lambda v, lo, hi: np.minimum(np.maximum(v, lo), hi), 3, 3),
    "where": (lambda c, a, b: np.where(c, a, b), 3, 3),
}
_BINOPS = {ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply, ast.Div: np.divide,
           ast.Pow: np.power, ast.Mod: np.mod}
_CMPOPS = {ast.Lt: np.less, ast.LtE: np.less_equal, ast.Gt: np.greater, ast.GtE: np.greater_equal,
           ast.Eq: np.equal, ast.NotEq: np.not_equal}
MAX_LENGTH = 2000


def tree_depth(root) -> int:
    """Depth of an ast tree (root = 1), walked iteratively: a chain of 1,000 unary minus or
    ``0+0+...`` terms fits the length cap but would overflow Python's recursion limit in any
    recursive walk."""
    depth, stack = 0, [(root, 1)]
    while stack:
        node, d = stack.pop()
        depth = max(depth, d)
        stack.extend((child, d + 1) for child in ast.iter_child_nodes(node))
    return depth


class Expression:
    """A compiled field: ``Expression(text, where)(x, y, r) -> ndarray`` (broadcast shape)."""

    def __init__(self, text: str, where: str = "expression"):
        self.text, self.where = text, where
        if len(text) > MAX_LENGTH:
            raise SelfshapeError(f"{where}: expression is longer than {MAX_LENGTH} characters")
        try:
            tree = ast.parse(text.strip(), mode="eval")
        except SyntaxError as e:
            col = (e.offset or 1) + len(text) - len(text.lstrip())
            raise SelfshapeError(f"{where}: cannot parse {text!r}: {e.msg} at column {col}") from None
        except (RecursionError, MemoryError, ValueError):
            raise SelfshapeError(f"{where}: cannot parse {text!r}: too deeply nested") from None
        self._tree = tree.body
        depth = tree_depth(self._tree)
        if depth > MAX_EXPRESSION_DEPTH:       # before the recursive check and evaluation
            raise SelfshapeError(f"{where}: expression is nested {depth} levels deep (each operator, call, name "
                                 f"or number is a level); at most {MAX_EXPRESSION_DEPTH} are allowed")
        self._check(self._tree)
        self.variables = sorted({n.id for n in ast.walk(self._tree) if isinstance(n, ast.Name) and n.id in VARIABLES})

    def _fail(self, node, what):
        col = getattr(node, "col_offset", -1) + 1 + (len(self.text) - len(self.text.lstrip()))
        raise SelfshapeError(f"{self.where}: {what} at column {col} of {self.text!r}")

    def _check(self, node):
        if isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or not isinstance(node.value, (int, float)):
                self._fail(node, f"{node.value!r:.40} is not a number")
            try:
                float(node.value)
            except OverflowError:
                self._fail(node, f"a {len(str(node.value))}-digit number is beyond the float range")
        elif isinstance(node, ast.Name):
            if node.id not in VARIABLES and node.id not in CONSTANTS:
                if node.id in FUNCTIONS:
                    self._fail(node, f"function {node.id!r} used without arguments")
                self._fail(node, f"unknown name {node.id!r} (use x, y, r, pi, e)")
        elif isinstance(node, ast.BinOp):
            if type(node.op) not in _BINOPS:
                self._fail(node, f"operator {type(node.op).__name__} is not allowed")
            self._check(node.left), self._check(node.right)
        elif isinstance(node, ast.UnaryOp):
            if not isinstance(node.op, (ast.USub, ast.UAdd, ast.Not)):
                self._fail(node, f"operator {type(node.op).__name__} is not allowed")
            self._check(node.operand)
        elif isinstance(node, ast.Compare):
            for op in node.ops:
                if type(op) not in _CMPOPS:
                    self._fail(node, f"comparison {type(op).__name__} is not allowed")
            for n in [node.left, *node.comparators]:
                self._check(n)
        elif isinstance(node, ast.BoolOp):
            for n in node.values:
                self._check(n)
        elif isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
                name = node.func.id if isinstance(node.func, ast.Name) else ast.unparse(node.func)
                self._fail(node, f"unknown function {name!r} (allowed: {', '.join(FUNCTIONS)})")
            if node.keywords:
                self._fail(node, f"{node.func.id}() takes no keyword arguments")
            _, lo, hi = FUNCTIONS[node.func.id]
            n = len(node.args)
            if n < lo or (hi is not None and n > hi):
                want = str(lo) if hi == lo else (f"{lo} or more" if hi is None else f"{lo} to {hi}")
                self._fail(node, f"{node.func.id}() takes {want} arguments, got {n}")
            for a in node.args:
                if isinstance(a, ast.Starred):
                    self._fail(a, "starred arguments are not allowed")
                self._check(a)
        else:
            self._fail(node, f"{type(node).__name__} is not allowed")

    def _eval(self, node, env):
        if isinstance(node, ast.Constant):
            return float(node.value)
        if isinstance(node, ast.Name):
            return env[node.id] if node.id in env else CONSTANTS[node.id]
        if isinstance(node, ast.BinOp):
            return _BINOPS[type(node.op)](self._eval(node.left, env), self._eval(node.right, env))
        if isinstance(node, ast.UnaryOp):
            v = self._eval(node.operand, env)
            if isinstance(node.op, ast.USub):
                return np.negative(v)
            return np.logical_not(v) if isinstance(node.op, ast.Not) else v
        if isinstance(node, ast.Compare):
            vals = [self._eval(n, env) for n in [node.left, *node.comparators]]
            out = True
            for op, a, b in zip(node.ops, vals[:-1], vals[1:]):
                out = np.logical_and(out, _CMPOPS[type(op)](a, b))
            return out
        if isinstance(node, ast.BoolOp):
            f = np.logical_and if isinstance(node.op, ast.And) else np.logical_or
            return reduce(f, [self._eval(n, env) for n in node.values])
        fn = FUNCTIONS[node.func.id][0]
        return fn(*[self._eval(a, env) for a in node.args])

    def __call__(self, x, y, r):
        """Values at the points (x, y) with r = distance to the centroid, as a float array."""
        x, y, r = (np.asarray(v, dtype=float) for v in (x, y, r))
        with np.errstate(all="ignore"):
            v = self._eval(self._tree, {"x": x, "y": y, "r": r})
            return np.broadcast_to(np.asarray(v, dtype=float), np.broadcast_shapes(x.shape, y.shape, r.shape)).copy()

    def __repr__(self):
        return f"Expression({self.text!r})"


def compile_field(value, where: str):
    """A field given as a number or an expression string -> float or Expression."""
    if isinstance(value, bool):
        raise SelfshapeError(f"{where} must be a number or an expression string, got {value!r}")
    if isinstance(value, (int, float)):
        v = float(value)
        if not math.isfinite(v):
            raise SelfshapeError(f"{where} must be finite, got {value!r}")
        return v
    if isinstance(value, str):
        if not value.strip():
            raise SelfshapeError(f"{where}: empty expression")
        return Expression(value, where)
    if isinstance(value, Expression) or callable(value):
        return value
    raise SelfshapeError(f"{where} must be a number or an expression string, got {value!r:.80}")


def evaluate_field(value, x, y, r, where: str = "field") -> np.ndarray:
    """Evaluate a number / expression string / Expression / callable f(x, y, r) at points.

    Returns a float array of the broadcast shape; a non-finite value raises
    SelfshapeError naming ``where`` and the first point where it happens.
    """
    f = compile_field(value, where)
    x, y, r = (np.asarray(v, dtype=float) for v in (x, y, r))
    shape = np.broadcast_shapes(x.shape, y.shape, r.shape)
    if isinstance(f, float):
        return np.full(shape, f)
    with np.errstate(all="ignore"):
        v = np.broadcast_to(np.asarray(f(x, y, r), dtype=float), shape)
    bad = ~np.isfinite(v)
    if bad.any():
        i = np.unravel_index(int(np.argmax(bad)), shape)
        xb, yb = (round(float(np.broadcast_to(v, shape)[i]), 9) + 0.0 for v in (x, y))
        text = f.text if isinstance(f, Expression) else repr(f)
        raise SelfshapeError(f"{where}: {text!r} is {v[i]} at (x, y) = ({xb:.4g}, {yb:.4g})")
    return np.array(v, dtype=float)

import numpy as np
import pytest

from geometry.expressions import Expression, compile_field, evaluate_field
from shellfem.errors import SelfshapeError

rng = np.random.default_rng(0)
X, Y = rng.uniform(-50, 50, 200), rng.uniform(-50, 50, 200)
R = np.hypot(X, Y)

CASES = [
    ("0.7", lambda x, y, r: np.full_like(x, 0.7)),
    ("clip(10 - 6 * r / 54, 4, 10) / 18", lambda x, y, r: np.clip(10 - 6 * r / 54, 4, 10) / 18),
    ("sqrt(x**2 + y**2) - r", lambda x, y, r: np.sqrt(x ** 2 + y ** 2) - r),
    ("exp(-r / 20) * cos(pi * x / 25) + sin(y) * tan(0.01 * x)",
     lambda x, y, r: np.exp(-r / 20) * np.cos(np.pi * x / 25) + np.sin(y) * np.tan(0.01 * x)),
    ("log(1 + r) + abs(x) - -y % 7", lambda x, y, r: np.log(1 + r) + np.abs(x) - np.mod(-y, 7)),
    ("min(x, y, 3) + max(x, 2 * y)", lambda x, y, r: np.minimum(np.minimum(x, y), 3) + np.maximum(x, 2 * y)),
    ("where(r < 20, 0.6, where(x > 0 and y > 0, 0.4, 0.2))",
     lambda x, y, r: np.where(r < 20, 0.6, np.where((x > 0) & (y > 0), 0.4, 0.2))),
    ("where(-10 <= x < 10, e, 2 ** 0.5)", lambda x, y, r: np.where((-10 <= x) & (x < 10), np.e, 2 ** 0.5)),
    ("where(not (x != 0), 1, 0)", lambda x, y, r: np.where(x == 0, 1.0, 0.0)),
]


@pytest.mark.parametrize("text,ref", CASES)
def test_expression_matches_numpy(text, ref):
    v = evaluate_field(text, X, Y, R, "f")
    assert v.shape == X.shape
    np.testing.assert_allclose(v, ref(X, Y, R), rtol=1e-14, atol=1e-14)


def test_numbers_and_callables_broadcast():
    np.testing.assert_array_equal(evaluate_field(0.3, X, Y, R), np.full(200, 0.3))
    np.testing.assert_array_equal(evaluate_field(2, X[:5], Y[:5], R[:5]), np.full(5, 2.0))
    np.testing.assert_allclose(evaluate_field(lambda x, y, r: x * y, X, Y, R), X * Y)
    assert Expression("x + r").variables == ["r", "x"]
    assert compile_field(1, "f") == 1.0 and isinstance(compile_field(1, "f"), float)


@pytest.mark.parametrize("text,needle", [
    ("0.7*(x", "cannot parse"),
    ("z * 2", "unknown name 'z'"),
    ("foo(x)", "unknown function 'foo'"),
    ("__import__('os').system('true')", "unknown function"),
    ("__import__('os')", "unknown function '__import__'"),
    ("().__class__", "is not allowed"),
    ("x.real", "is not allowed"),
    ("[x, y]", "List is not allowed"),
    ("lambda: 1", "is not allowed"),
    ("clip(x, 1)", "clip() takes 3 arguments, got 2"),
    ("min(x)", "min() takes 2 or more arguments"),
    ("sqrt(x=1)", "no keyword"),
    ("'abc'", "is not a number"),
    ("x if y else r", "IfExp is not allowed"),
    ("x // 2", "FloorDiv is not allowed"),
    ("sqrt", "used without arguments"),
])
def test_bad_expressions_name_field_and_position(text, needle):
    with pytest.raises(SelfshapeError) as e:
        Expression(text, "[stars] arm_length")
    msg = str(e.value)
    assert msg.startswith("[stars] arm_length") and needle in msg and "\n" not in msg


def test_error_column_points_at_the_offending_name():
    with pytest.raises(SelfshapeError, match=r"unknown name 'q' .* at column 9 of '1 \+ 2 \* q'"):
        Expression("1 + 2 * q", "f")
    with pytest.raises(SelfshapeError, match=r"'\(' was never closed at column 3"):
        Expression("  (1 + 2", "f")
    with pytest.raises(SelfshapeError, match=r"unknown name 'rr' .* at column 11"):
        Expression("  2 * x + rr", "f")


def test_non_finite_value_names_the_point():
    with pytest.raises(SelfshapeError, match=r"\[stars\] thickness_mm: 'log\(x\)' is -inf at \(x, y\) = \(0, 2\)"):
        evaluate_field("log(x)", np.array([1.0, 0.0]), np.array([1.0, 2.0]), np.zeros(2), "[stars] thickness_mm")
    with pytest.raises(SelfshapeError, match="is nan"):
        evaluate_field("sqrt(x)", np.array([-1.0]), np.zeros(1), np.zeros(1), "f")
    with pytest.raises(SelfshapeError, match="is inf"):
        evaluate_field("10 ** 10 ** 10", np.zeros(1), np.zeros(1), np.zeros(1), "f")


def test_bad_field_types():
    for v in (True, [1, 2], None, float("nan"), "  "):
        with pytest.raises(SelfshapeError):
            compile_field(v, "f")

"""shellfem.triangle_distance: exact triangle-pair distances (the contact skip test's third stage)
against configurations with a known answer and against tests/test_contact's independent helper."""
import numpy as np

from shellfem.triangle_distance import triangle_pair_distances
from test_contact import triangle_distances


def test_known_configurations():
    A = np.array([[0.0, 0, 0], [4, 0, 0], [0, 4, 0]])
    cases = [
        (A + [0.5, 0.5, 0.7], 0.7),                                    # parallel, face over face
        (np.array([[1.0, 1, -1], [1, 1, 1], [1.5, 1.2, 0]]), 0.0),      # an edge through the face
        (np.array([[6.0, -1, 2], [6, 1, 2], [7, 0, 3]]), np.hypot(2.0, 2.0)),   # corner (4,0,0) to edge x=6,z=2
        (np.array([[-1.0, 2, 3], [-1, 2, 5], [-2, 2, 4]]), np.hypot(1.0, 3.0)),  # edge x=-1 to corner (0, 2, 0)
        (A + [5.0, 0, 0], 1.0),                                        # coplanar, 1 mm apart along x
    ]
    B = np.array([b for b, _ in cases])
    d = triangle_pair_distances(np.repeat(A[None], len(cases), 0), B)
    assert np.allclose(d, [v for _, v in cases], atol=1e-12), d


def test_equals_the_independent_helper_and_sampled_bounds():
    rng = np.random.default_rng(4)
    k = 3000
    A = rng.normal(size=(k, 3, 3))
    B = rng.normal(size=(k, 3, 3)) + rng.normal(size=(k, 1, 3)) * rng.uniform(0, 3, (k, 1, 1))
    d = triangle_pair_distances(A, B)
    x = np.concatenate([A.reshape(-1, 3), B.reshape(-1, 3)])
    tri = np.arange(6 * k).reshape(2 * k, 3)
    ref = triangle_distances(x, tri, np.column_stack([np.arange(k), k + np.arange(k)]))
    assert np.allclose(d, ref, atol=1e-12)
    assert 0.05 * k < (d == 0).sum() < 0.95 * k                   # both kinds of pair are tested
    w = rng.dirichlet([1, 1, 1], size=300)                       # points on both triangles
    pa, pb = np.einsum("sj,kjc->ksc", w, A[:50]), np.einsum("sj,kjc->ksc", w, B[:50])
    sampled = np.linalg.norm(pa[:, :, None] - pb[:, None], axis=3).min((1, 2))
    assert np.all(d[:50] <= sampled + 1e-12) and np.all(sampled - d[:50] < 0.5)

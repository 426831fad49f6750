"""BlockScatter: the compiled pattern build and gather against scipy's COO assembly."""
import numpy as np
import pytest
import scipy.sparse as sp

from shellfem.assembly import BlockScatter


@pytest.mark.parametrize("upper", [False, True])
def test_scatter_matches_coo_assembly(upper):
    rng = np.random.default_rng(5)
    n = 60
    sets = [rng.integers(0, n, (40, 6)), rng.integers(0, n, (25, 4))]     # repeated DOFs inside blocks too
    blocks = [rng.standard_normal(s.shape + (s.shape[1],)) for s in sets]
    free = rng.random(n) > 0.2
    red = -np.ones(n, int)
    red[free] = np.arange(free.sum())
    rows, cols, vals = [], [], []
    for idx, B in zip(sets, blocks):
        R = np.repeat(red[idx][:, :, None], idx.shape[1], 2)
        C = np.repeat(red[idx][:, None, :], idx.shape[1], 1)
        keep = (R >= 0) & (C >= 0) & ((R <= C) if upper else True)
        rows.append(R[keep]), cols.append(C[keep]), vals.append(B[keep])
    ref = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(free.sum(),) * 2).tocsr()
    sc = BlockScatter(sets, n, free, upper=upper)
    M = sc.matrix(blocks)
    assert M.has_canonical_format and sc.nnz == M.nnz == ref.nnz
    assert np.array_equal(M.indptr, ref.indptr) and np.array_equal(M.indices, ref.indices)
    assert np.abs(M.toarray() - ref.toarray()).max() < 1e-12
    one = BlockScatter(sets[:1], n, free, upper=upper).matrix(blocks[:1])
    assert one.nnz < M.nnz
    with pytest.raises(ValueError, match="block sizes"):
        sc.matrix([blocks[0], blocks[0]])
    with pytest.raises(ValueError, match="two index sets"):
        BlockScatter(sets + sets[:1], n, free)


def test_pattern_union_sums_and_keeps_its_pattern_across_calls(monkeypatch):
    """PatternUnion (the contact Hessian added to the scatter's): A + B exactly; a B whose
    entries are already in the union (a contact set that settled) reuses the union's index arrays
    (the solver then keeps its symbolic analysis) and does not rebuild the union; a new entry grows it."""
    from shellfem.assembly import PatternUnion
    from shellfem.linalg import same_frozen
    rng = np.random.default_rng(2)
    n = 30
    sets = [rng.integers(0, n, (20, 3))]
    free = np.ones(n, bool)
    sc = BlockScatter(sets, n, free, upper=True)
    blocks = [rng.standard_normal((20, 3, 3))]
    builds = []
    orig = PatternUnion._grow
    monkeypatch.setattr(PatternUnion, "_grow", lambda self, A, new=None: (builds.append(1), orig(self, A, new)))
    B = sp.triu(sp.random(n, n, density=0.05, random_state=3, format="csr") + sp.eye(n)).tocsr()
    u = PatternUnion()
    M1 = u.add(sc.matrix(blocks), B)
    assert np.abs(M1.toarray() - (sc.matrix(blocks) + B).toarray()).max() < 1e-14
    M2 = u.add(sc.matrix(blocks), 2 * B)           # a new matrix object from the scatter, same pattern
    assert len(builds) == 1 and same_frozen(M2.indices, M1.indices) and same_frozen(M2.indptr, M1.indptr)
    assert np.abs(M2.toarray() - (sc.matrix(blocks) + 2 * B).toarray()).max() < 1e-14
    C = sp.csr_matrix(([1.0], ([0], [n - 1])), shape=(n, n))
    if (sc.matrix(blocks) + B)[0, n - 1] == 0:
        M3 = u.add(sc.matrix(blocks), C)
        assert len(builds) == 2 and M3.nnz > M1.nnz and M3[0, n - 1] == pytest.approx(sc.matrix(blocks)[0, n - 1] + 1)


def test_pattern_union_grown_by_insertion_equals_a_fresh_union():
    """A union grown call after call by contact patterns that come and go (new entries merged in
    by insertion) holds exactly the sorted union of every pattern seen, and each sum is A + B."""
    from shellfem.assembly import PatternUnion
    rng = np.random.default_rng(5)
    n = 60
    sets = [rng.integers(0, n, (40, 3))]
    sc = BlockScatter(sets, n, np.ones(n, bool), upper=True)
    u = PatternUnion()
    seen = set()
    for k in range(12):
        A = sc.matrix([rng.standard_normal((40, 3, 3))])
        B = sp.triu(sp.random(n, n, density=0.02 + 0.01 * (k % 3), random_state=k, format="csr")).tocsr()
        M = u.add(A, B)
        assert np.abs(M.toarray() - (A + B).toarray()).max() < 1e-13
        for X in (A, B):
            C = X.tocoo()
            seen |= set(zip(C.row.tolist(), C.col.tolist()))
        Mc = M.tocoo()
        assert set(zip(Mc.row.tolist(), Mc.col.tolist())) == seen
        assert np.all(np.diff(M.indptr) >= 0) and M.indptr[-1] == M.nnz == len(seen)
        for r in range(n):                              # sorted, unique columns in every row
            assert np.all(np.diff(M.indices[M.indptr[r]:M.indptr[r + 1]]) > 0)

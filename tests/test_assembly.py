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

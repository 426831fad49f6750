"""The MKL PARDISO binding and the sparse Cholesky backends agree."""
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from shellfem import pardiso
from shellfem.linalg import HAVE_CHOLMOD, NotPositiveDefinite, SparseSPD, default_backend

needs_pardiso = pytest.mark.skipif(not pardiso.available(), reason="MKL PARDISO not installed")


def _laplacian(n=30, seed=0):
    """A 2D grid Laplacian (n^2 unknowns) plus a random positive diagonal: SPD, with a
    smallest eigenvalue of the order of the diagonal term."""
    T = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    K = sp.kronsum(T, T).tocsr()
    rng = np.random.default_rng(seed)
    return (K + sp.diags(rng.uniform(0.01, 0.1, n * n))).tocsr()


@needs_pardiso
def test_pardiso_cholesky_solves_with_and_without_shift():
    A = _laplacian()
    b = np.random.default_rng(1).standard_normal(A.shape[0])
    chol = pardiso.PardisoCholesky(A)
    chol.factor(A.data)
    x = chol.solve(b)
    assert np.linalg.norm(A @ x - b) <= 1e-10 * np.linalg.norm(b)
    shift = np.linspace(0.5, 2.0, A.shape[0])
    chol.factor(A.data, shift)
    x = chol.solve(b)
    assert np.linalg.norm((A + sp.diags(shift)) @ x - b) <= 1e-10 * np.linalg.norm(b)
    assert chol.factor_nonzeros > A.nnz // 2


@needs_pardiso
def test_pardiso_solves_several_right_hand_sides_at_once():
    """The columns of b (n, k) solved in one call equal the one-by-one solves (round-off),
    whatever b's memory order; k = 0 gives an empty result."""
    A = _laplacian()
    B = np.random.default_rng(3).standard_normal((A.shape[0], 7))
    chol = pardiso.PardisoCholesky(A)
    chol.factor(A.data, 0.1)
    X = chol.solve(B)
    ref = np.column_stack([chol.solve(B[:, k]) for k in range(B.shape[1])])
    assert X.shape == B.shape
    assert np.allclose(X, ref, rtol=1e-12, atol=1e-14)
    assert np.linalg.norm((A + 0.1 * sp.eye(A.shape[0])) @ X - B) <= 1e-10 * np.linalg.norm(B)
    assert np.allclose(chol.solve(np.ascontiguousarray(B)), chol.solve(np.asfortranarray(B)), rtol=0, atol=0)
    assert chol.solve(np.zeros((A.shape[0], 0))).shape == (A.shape[0], 0)
    with pytest.raises(ValueError, match="right-hand side"):
        chol.solve(np.ones((3, 2)))


@needs_pardiso
def test_pardiso_reports_indefinite_matrices():
    """Shifting an SPD matrix just below its smallest eigenvalue makes the Cholesky fail
    (one negative eigenvalue); just above, it succeeds."""
    A = _laplacian(20)
    lam_min = spla.eigsh(A, k=1, sigma=0, which="LM", return_eigenvectors=False)[0]
    chol = pardiso.PardisoCholesky(A)
    with pytest.raises(pardiso.ZeroPivot):
        chol.factor(A.data, -1.001 * lam_min)
    with pytest.raises(pardiso.PardisoError, match="without a successful"):
        chol.solve(np.ones(A.shape[0]))
    chol.factor(A.data, -0.999 * lam_min)
    assert np.all(np.isfinite(chol.solve(np.ones(A.shape[0]))))


@needs_pardiso
def test_pardiso_rejects_bad_patterns():
    A = _laplacian(5).tolil()
    A[3, 3] = 0.0
    A = A.tocsr()
    A.eliminate_zeros()
    with pytest.raises(ValueError, match="whole diagonal"):
        pardiso.PardisoCholesky(A)
    B = sp.csr_matrix((np.ones(3), np.array([1, 0, 1]), np.array([0, 2, 3])), shape=(2, 2))
    with pytest.raises(ValueError, match="canonical"):
        pardiso.PardisoCholesky(B)
    chol = pardiso.PardisoCholesky(_laplacian(5))
    chol.factor(_laplacian(5).data)
    with pytest.raises(ValueError, match="right-hand side"):
        chol.solve(np.ones(3))


@pytest.mark.parametrize("backend", ["pardiso", "cholmod", "superlu"])
def test_backends_agree_and_detect_indefiniteness(backend):
    if backend == "pardiso" and not pardiso.available():
        pytest.skip("MKL PARDISO not installed")
    if backend == "cholmod" and not HAVE_CHOLMOD:
        pytest.skip("scikit-sparse not installed")
    A = _laplacian(15)
    b = np.random.default_rng(2).standard_normal(A.shape[0])
    solver = SparseSPD(backend)
    x = solver.factor(A, shift=0.25)(b)
    ref = spla.spsolve((A + 0.25 * sp.eye(A.shape[0])).tocsc(), b)
    assert np.allclose(x, ref, rtol=1e-10, atol=1e-12)
    # several right-hand sides as the columns of a matrix (equilibrium_jacobian's blocks)
    B = np.column_stack([b, 2 * b, -b])
    X = np.asarray(solver.factor(A, shift=0.25)(B)).reshape(B.shape)
    assert np.allclose(X, np.column_stack([ref, 2 * ref, -ref]), rtol=1e-10, atol=1e-12)
    # the upper triangle alone (what BlockScatter(upper=True) assembles) gives the same answer
    U = sp.triu(A, format="csr")
    assert np.allclose(SparseSPD(backend).factor(U, shift=0.25, upper=True)(b), ref, rtol=1e-10, atol=1e-12)
    with pytest.raises(NotPositiveDefinite):
        SparseSPD(backend).factor(U, shift=-4.0, upper=True)
    with pytest.raises(NotPositiveDefinite):
        solver.factor(A, shift=-4.0)         # the grid Laplacian's spectrum reaches ~8
    # the pattern changes: a new symbolic analysis, same answers
    A2 = _laplacian(10)
    b2 = b[:A2.shape[0]]
    assert np.allclose(solver.factor(A2)(b2), spla.spsolve(A2.tocsc(), b2), rtol=1e-10, atol=1e-12)


def test_upper_scatter_and_symmetric_matvec():
    """BlockScatter(upper=True) holds the upper triangle of the full assembly, and
    symmetric_matvec multiplies by the whole symmetric matrix."""
    from shellfem.assembly import BlockScatter, symmetric_matvec
    rng = np.random.default_rng(3)
    idx = rng.integers(0, 40, size=(25, 6))
    B = rng.standard_normal((25, 6, 6))
    B = B + np.swapaxes(B, 1, 2)
    free = np.ones(40, bool)
    free[[3, 17]] = False
    full = BlockScatter([idx], 40, free).matrix([B])
    U = BlockScatter([idx], 40, free, upper=True).matrix([B])
    assert np.allclose(U.toarray(), np.triu(full.toarray()))
    x = rng.standard_normal(full.shape[0])
    assert np.allclose(symmetric_matvec(U, x), full @ x)


def test_default_backend_and_bad_backend_names():
    assert default_backend() == ("pardiso" if pardiso.available() else "cholmod" if HAVE_CHOLMOD else "superlu")
    with pytest.raises(ValueError, match="unknown sparse solver backend"):
        SparseSPD("umfpack")

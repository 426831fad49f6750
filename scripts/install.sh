#!/usr/bin/env bash
# Install selfshape and everything it needs on a fresh Debian/Ubuntu machine (or a
# machine that already has them: every step is idempotent). Python >= 3.10 with pip.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if command -v apt-get >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  export DEBIAN_FRONTEND=noninteractive
  # gmsh needs the GL/X client libraries even headless; libegl1 for off-screen pyvista
  # PNGs; OpenBLAS makes CHOLMOD 3-7x faster than reference BLAS; libsuitesparse-dev
  # and a compiler build scikit-sparse (CHOLMOD) from source.
  pkgs="libgl1 libglu1-mesa libxrender1 libxcursor1 libxft2 libxinerama1 libgomp1 libegl1
        libopenblas0-pthread libsuitesparse-dev gcc g++"
  missing=$(for p in $pkgs; do dpkg -s "$p" >/dev/null 2>&1 || echo "$p"; done)
  if [ -n "$missing" ]; then
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq --no-install-recommends $missing >/dev/null
  fi
  # Debian's chromium (headless) draws the index.html page in tests/test_view.py (WebGL through
  # SwiftShader, no GPU); optional: without it that test skips (Ubuntu ships it as a snap only)
  if ! dpkg -s chromium >/dev/null 2>&1; then
    { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq --no-install-recommends chromium >/dev/null; } \
      || echo "chromium not installed: the browser test of the 3D page will skip"
  fi
fi
$PY -m pip install -q --upgrade pip >/dev/null 2>&1 || true
# scikit-sparse 0.4.16 (CHOLMOD) builds against Debian's libsuitesparse-dev; 0.5 does not build
$PY -m pip install -q "scikit-sparse==0.4.16" 2>&1 | grep -v -i warning || true
$PY -m pip install -q -c scripts/constraints.txt -e ".[test]" 2>&1 | grep -v -i warning || true
$PY -c "import shellfem, geometry, gmsh, skfem, pyvista; print('selfshape installed')"
$PY -c "import sksparse.cholmod" 2>/dev/null && echo "CHOLMOD available" || echo "CHOLMOD not available"
$PY -c "from shellfem.linalg import default_backend; print('sparse Cholesky used by the solver:', default_backend())"
# drop numba caches of an earlier checkout: numba checks a cached kernel against its own
# module's time stamp only, so a kernel that inlines a function of another module that has
# changed since (shellfem.layers.layer_terms in shellfem.face_energy) would load stale code
find shellfem geometry forward inverse validation selfshape -name '*.nbi' -delete -o -name '*.nbc' -delete 2>/dev/null || true
# compile the numba kernels once (~20 s; cached beside the modules) so the first run is not slower
$PY -c "
import numpy as np
from shellfem.assembly import BlockScatter
from shellfem.model import ShellModel
from shellfem.sheet import Sheet
M = ShellModel.homogeneous(Sheet.rectangle(4, 2, 2, 1), 1.0, 0.3, 0.1)
q = M.initial_state()
M.energy(q), M.gradient(q), M.edge_angle_problem(q)
E, g, blocks = M.hessian_blocks(q)
BlockScatter([M.face_dofs, M.hinge_dofs], M.n_dofs, np.ones(M.n_dofs, bool), upper=True).matrix(blocks)
print('numba kernels compiled')"

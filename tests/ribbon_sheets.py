"""Small printed sheets for the refinement and stability tests: a square of bare fabric with a
checkerboard of front ribbons, one thickness parameter per ribbon (mm)."""
import numpy as np

from shellfem.sheet import Sheet


def ribbon_checkerboard(size: float, n: int, cells: int, half_length: float):
    """A size x size mm sheet (n x n cells) with cells x cells ribbons 2 * half_length x 2 mm,
    one at each cell's centre, along x and along y in turn (a doubly curved, well-determined
    shape). Returns (bare sheet, (m,) triangle -> ribbon index, -1 off the ribbons)."""
    base = Sheet.rectangle(size, size, n, n)
    c = base.points[base.triangles].mean(1)
    param = np.full(base.n_triangles, -1)
    cell = size / cells
    for j in range(cells):
        for i in range(cells):
            cx, cy = cell * (i + 0.5), cell * (j + 0.5)
            along, across = (0, 1) if (i + j) % 2 == 0 else (1, 0)
            sel = ((np.abs(c[:, along] - (cx, cy)[along]) < half_length)
                   & (np.abs(c[:, across] - (cx, cy)[across]) < 1.0))
            param[sel] = cells * j + i
    return base, param


def sheet_at(base, param, p):
    """The sheet with ribbon k printed p[k] mm thick on the front (region = ribbon + 1)."""
    t = np.where(param >= 0, np.asarray(p)[np.maximum(param, 0)], 0.0)
    return Sheet(base.points, base.triangles, region=param + 1, thickness_front=t)

"""`selfshape simulate` end to end, and bad input."""
import json
import os

import meshio
import numpy as np
import pytest

from selfshape.cli import main
from selfshape.errors import SelfshapeError
from shellfem.materials import Fabric, Plastic
from shellfem.sheet import Sheet

HERE = os.path.dirname(__file__)
EXAMPLE = os.path.join(HERE, "..", "examples", "strip_narrow.toml")


def test_simulate_strip_writes_outputs(tmp_path):
    out = tmp_path / "strip"
    assert main(["simulate", EXAMPLE, "-o", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    for key in ("converged", "newton_iterations", "energy", "gradient_norm", "wall_time_s", "n_vertices",
                "n_triangles", "bbox_mm"):
        assert key in s
    assert s["converged"] is True
    m = meshio.read(out / "deployed.vtu")
    assert {"region", "thickness_mm", "side"} <= set(m.cell_data)
    assert np.allclose(m.point_data["reference"][:, 2], 0)
    assert (out / "deployed.png").stat().st_size > 1000
    # the strip curls: shorter than printed, and lifted out of the plane
    assert s["bbox_mm"][0] < 30.0 / 1.0 and s["bbox_mm"][2] > 1.0


@pytest.mark.parametrize("kwargs,word", [
    (dict(stretch=0.9), "stretch"), (dict(thickness=-1), "thickness"), (dict(young_modulus=float("nan")), "young"),
])
def test_bad_fabric_parameters(kwargs, word):
    with pytest.raises(SelfshapeError, match=word):
        Fabric(**kwargs)


def test_degenerate_triangle_and_negative_thickness():
    pts = np.array([[0, 0], [1, 0], [2, 0], [0, 1]], float)
    with pytest.raises(SelfshapeError, match="degenerate"):
        Sheet(pts, np.array([[0, 1, 2], [0, 1, 3]]))
    with pytest.raises(SelfshapeError, match="thickness"):
        Sheet(pts, np.array([[0, 1, 3]]), thickness_front=np.array([-0.1]))


def test_support_that_misses_the_sheet(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text(open(EXAMPLE).read() + '\n[[support]]\npoints = [[0.0, 0.0]]\nfix = "z"\n')
    from shellfem.simulate import simulate_sheet
    from geometry.patterns import load_pattern
    from geometry.elements import Support
    pat = load_pattern(str(p))
    sheet = Sheet.rectangle(30, 3, 10, 2)
    with pytest.raises(SelfshapeError, match="does not hit the sheet"):
        simulate_sheet(sheet, pat.fabric, Plastic(), [Support(np.array([[80.0, 50.0]]), "z")])


def test_cli_reports_bad_input_in_one_line(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text(open(EXAMPLE).read().replace("stretch = 1.35", "stretch = 0.8"))
    assert main(["simulate", str(p), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "stretch" in err
    assert not (tmp_path / "o" / "summary.json").exists()

"""The 3D page (forward.view, `selfshape view DIR`): self-contained, offline, drawn in a real
headless Chromium (skipped where there is none; scripts/install.sh installs it)."""
import base64
import json
import os
import re
import shutil
import subprocess
import tempfile

import meshio
import numpy as np
import pytest

from forward.view import CSP, folder_page, write_view
from selfshape.cli import main
from shellfem.errors import SelfshapeError

ROOT = os.path.join(os.path.dirname(__file__), "..")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
BACKGROUND = np.array([245, 245, 242])      # the WebGL clear colour (0.96, 0.96, 0.95)


def _result_folder(path, design=True):
    """A small result folder: deployed.vtu (a bent 40 x 20 mm sheet with curvature, region and
    side), and for a design flat.vtu with a target (the same sheet bent a little more) and
    pattern.svg."""
    from geometry import cad
    from geometry.target import cylinder_patch
    os.makedirs(path, exist_ok=True)
    V, F = cylinder_patch(n_arc=12, n_len=8)
    m = len(F)
    cells = {"mean_curvature_per_mm": [np.full(m, -1 / 60.0)], "region": [np.arange(m) % 3],
             "side": [np.where(np.arange(m) % 2, 1, -1)], "thickness_mm": [np.full(m, 0.4)]}
    meshio.write(os.path.join(path, "deployed.vtu"), meshio.Mesh(V, [("triangle", F)], cell_data=cells))
    if design:
        target = V * np.array([1.0, 1.0, 1.3])
        flat = np.column_stack([V[:, 0], V[:, 1], np.zeros(len(V))])
        meshio.write(os.path.join(path, "flat.vtu"), meshio.Mesh(flat, [("triangle", F)],
                                                                point_data={"target": target}))
        shapes = [cad.Shape(np.array([[0, 0], [40, 0], [40, 20], [0, 20]], float), "fabric"),
                  cad.Shape(np.array([[5, 5], [35, 5], [35, 7], [5, 7]], float), "front_0.40mm")]
        cad.write_svg(os.path.join(path, "pattern.svg"), shapes)
        with open(os.path.join(path, "report.json"), "w") as f:
            json.dump({"n_ribbons": 1, "stretch": 1.3, "deviation_pct_bbox": [1.0, 3.0]}, f)
    return path


def _data(page):
    blob = re.search(r'<script type="application/json" id="data">(.*?)</script>', page, re.S).group(1)
    return json.loads(blob.replace("<\\/", "</"))


def test_page_is_self_contained_with_its_data(tmp_path):
    folder = _result_folder(str(tmp_path / "d"))
    page = folder_page(folder)
    assert f'content="{CSP}"' in page and "default-src 'none'" in CSP and "unsafe-inline'; style" not in CSP
    assert not re.search(r"https?://", page), "the page must name no URL (no CDN, no fetch)"
    assert not re.search(r"\b(src|href)\s*=", page), "the page must load nothing"
    d = _data(page)
    V = np.frombuffer(base64.b64decode(d["deployed"]["points"]), "<f4").reshape(-1, 3)
    m = meshio.read(os.path.join(folder, "deployed.vtu"))
    assert np.allclose(V, m.points, atol=1e-4) and d["deployed"]["m"] == len(m.cells_dict["triangle"])
    assert d["target"] is not None and d["target"]["n"] == len(m.points)
    assert "mean curvature (1/mm)" in d["deployed"]["fields"] and "region" in d["deployed"]["fields"]
    assert "<polygon" in page and "front_0.40mm" in page       # the flat pattern beside it
    assert "1 ribbons, stretch 1.3" in page                     # the report's line


def test_a_design_without_verification_shows_its_target():
    """No deployed.vtu (design without --verify): the target is the surface, no ghost."""
    import tempfile as tf
    with tf.TemporaryDirectory() as d:
        _result_folder(d)
        os.remove(os.path.join(d, "deployed.vtu"))
        data = _data(folder_page(d))
        assert data["target"] is None and data["deployed"]["fields"] == {}
        assert data["deployed"]["n"] == len(meshio.read(os.path.join(d, "flat.vtu")).points)


def test_layer_names_and_titles_cannot_inject_markup(tmp_path):
    """A pattern.svg edited by hand (a layer id with markup) and an odd folder name stay text."""
    from geometry import cad
    folder = _result_folder(str(tmp_path / "@DATA@ <b>"))
    shapes = [cad.Shape(np.array([[0, 0], [1, 0], [0, 1]], float), 'front"><script>alert(1)</script>')]
    cad.write_svg(os.path.join(folder, "pattern.svg"), shapes)
    page = folder_page(folder)
    assert "<script>alert" not in page and page.count("<script") == 2
    assert "<title>@DATA@ &lt;b&gt;</title>" in page
    assert cad.read_svg(os.path.join(folder, "pattern.svg"))[0][0].layer == shapes[0].layer


def test_a_fine_target_ghost_is_coarsened():
    from forward.view import coarsened
    from geometry.target import cylinder_patch
    V, F = cylinder_patch(n_arc=60, n_len=40)
    P, T = coarsened(V, F, 1000)
    assert len(T) <= 1000 and T.max() < len(P)
    assert np.allclose(P.min(0), V.min(0), atol=1.0) and np.allclose(P.max(0), V.max(0), atol=1.0)
    assert coarsened(V, F, len(F))[1] is not None and len(coarsened(V, F, len(F))[1]) == len(F)


def test_view_verb_writes_index_html_and_refuses_a_folder_without_results(tmp_path, capsys):
    folder = _result_folder(str(tmp_path / "d"), design=False)
    assert main(["view", folder]) == 0
    assert os.path.isfile(os.path.join(folder, "index.html"))
    assert _data(open(os.path.join(folder, "index.html")).read())["target"] is None
    capsys.readouterr()
    empty = tmp_path / "empty"
    empty.mkdir()
    for bad in (str(empty), str(tmp_path / "missing"), os.path.join(folder, "deployed.vtu")):
        assert main(["view", bad]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("selfshape view: error: ") and bad in err[0], err
    assert os.listdir(empty) == []
    with pytest.raises(SelfshapeError, match="no results to view"):
        write_view(str(empty))


@pytest.mark.parametrize("name, content", [
    ("deployed.vtu", b"<VTKFile>"),                # meshio exit(): status 1 and no line (issue 19)
    ("deployed.vtu", b"\x89PNG" + bytes(300)),
    ("pattern.svg", b'<svg xmlns="http://www.w3.org/2000/svg" width="a" height="b"/>'),
    ("pattern.svg", b'<svg xmlns="http://www.w3.org/2000/svg" width="1mm" height="1mm" viewBox="0 0 x 1"/>'),
    ("pattern.svg", b'<svg xmlns="http://www.w3.org/2000/svg" width="1mm" height="1mm" viewBox="0 0 1 1">'
                    b'<g id="fabric"><polygon points="0,0 nan,1 1,inf"/></g></svg>'),
], ids=["vtu-exit", "vtu-binary", "svg-size", "svg-viewbox", "svg-nan"])
def test_broken_result_files_are_one_line_naming_them(tmp_path, capsys, name, content):
    """`view` reads whatever a folder holds: a result file replaced by something else is a
    one-line error naming it, status 2, and no index.html."""
    folder = _result_folder(str(tmp_path / "d"), design=False)
    with open(os.path.join(folder, name), "wb") as f:
        f.write(content)
    assert main(["view", folder]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and name in err[0] and "internal error" not in err[0], err
    assert not os.path.exists(os.path.join(folder, "index.html"))


def _chromium(url, shot, netlog, size="1000,600"):
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                        "--disable-quic", "--no-first-run", "--disable-background-networking",
                        "--disable-component-update", "--disable-sync", f"--user-data-dir={profile}",
                        f"--log-net-log={netlog}", f"--screenshot={shot}", f"--window-size={size}", url],
                       capture_output=True, timeout=120, check=False)


def _page_requests(netlog):
    """URLs the page itself asked for (the browser's own background requests have no origin)."""
    with open(netlog) as f:
        d = json.load(f)
    start = d["constants"]["logEventTypes"]["URL_REQUEST_START_JOB"]
    return [e["params"]["url"] for e in d["events"] if e["type"] == start and "url" in e.get("params", {})
            and e["params"].get("initiator") != "not an origin"
            and not e["params"]["url"].startswith(("file:", "data:"))]


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium (scripts/install.sh installs Debian's chromium)")
def test_page_draws_in_headless_chromium_without_network_requests(tmp_path):
    """The page draws the surface (non-background pixels in the 3D pane) and asks for nothing;
    the request detector is shown to work on a page that does ask."""
    from PIL import Image
    folder = _result_folder(str(tmp_path / "d"))
    page = write_view(folder)
    shot, netlog = str(tmp_path / "shot.png"), str(tmp_path / "net.json")
    _chromium("file://" + os.path.abspath(page), shot, netlog)
    a = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    h, w, _ = a.shape
    pane = a[60:h - 60, : int(0.55 * w)]                 # the 3D view, below the header, above the legend
    drawn = (np.abs(pane - BACKGROUND).sum(axis=2) > 30).mean()
    assert (np.abs(pane - BACKGROUND).sum(axis=2) <= 6).mean() > 0.3, "the WebGL pane was not cleared (no WebGL?)"
    assert drawn > 0.05, f"only {drawn:.1%} of the 3D pane is drawn"
    assert _page_requests(netlog) == []
    control = tmp_path / "control.html"
    control.write_text('<html><body><img src="http://127.0.0.1:9/x.png"></body></html>')
    _chromium("file://" + str(control), str(tmp_path / "c.png"), str(tmp_path / "c.json"), "300,200")
    assert _page_requests(str(tmp_path / "c.json")) == ["http://127.0.0.1:9/x.png"]

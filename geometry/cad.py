"""CAD exchange files, reader and writer of each format side by side (mm throughout).

The flat pattern is a drawing: a list of :class:`Shape` (a closed or open polyline in printed-state
mm on a named layer). :func:`pattern_drawing` makes it from a geometry.patterns.Pattern: the
fabric outline on layer ``fabric`` and each printed polygon on the layer of its side and
plastic thickness (``front_0.40mm``, ``back_0.80mm``: a CAD user selects all plastic of one
thickness by layer). Holes of a printed polygon are closed polylines on the same layer. Every
layer is in the pattern's frame, the fabric seen from its front (back.gcode is mirrored for
printing after flipping the fabric; the drawing is not).

- DXF (:func:`write_dxf`, :func:`read_dxf`, ezdxf): R2010, ``$INSUNITS`` = 4 (millimetres) and
  ``$MEASUREMENT`` = 1 (metric), one LWPOLYLINE per shape (closed flag set for closed shapes),
  one layer per name (fabric white, front red, back blue), ``$EXTMIN``/``$EXTMAX`` set: what
  Rhino and laser-cutter software import at true size.
- SVG (:func:`write_svg`, :func:`read_svg`): ``width``/``height`` in mm and a ``viewBox`` in
  mm, so one user unit is one millimetre; one ``<g>`` per layer (also an Inkscape layer),
  ``<polygon>`` for closed shapes, ``<polyline>`` for open ones, y up as in the pattern (the
  SVG stores -y). Hairline strokes, no fill: a laser cutter cuts along them.
- Surfaces (:func:`write_surface`, :func:`read_surface`, meshio): OBJ, STL (binary) and PLY
  (binary) of a triangulated surface (vertex positions in mm), for Rhino, slicers and ParaView.

One call per job, by the file's suffix as meshio does: :func:`write_drawing` / :func:`read_drawing`
(.dxf, .svg) for a flat pattern, :func:`write_surface` / :func:`read_surface` (.obj, .stl, .ply)
for a surface::

    write_drawing("pattern.dxf", pattern_drawing(load_pattern("examples/ribbons.toml")))

Every writer refuses a non-finite coordinate (shellfem.outfiles.NonFiniteOutput, nothing
written); the writers write exactly the path they are given (callers make it atomic through
shellfem.outfiles.write_atomic or OutputDir.write).
"""
from __future__ import annotations

import html
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from shellfem.errors import SelfshapeError
from shellfem.outfiles import check_finite_arrays

#: DXF colour index (ACI) of a layer by its first word: fabric white/black, front red, back blue
LAYER_COLOURS = {"fabric": 7, "front": 1, "back": 5}
#: SVG stroke colour of a layer by its first word
SVG_COLOURS = {"fabric": "#000000", "front": "#d62728", "back": "#1f77b4"}
SVG_STROKE_MM = 0.1
SURFACE_FORMATS = {".obj": "obj", ".stl": "stl", ".ply": "ply"}


@dataclass
class Shape:
    """One polyline of a flat drawing: ``points`` (k, 2) in mm (a closed shape without its
    repeated first point), its ``layer`` name and whether it is ``closed``."""
    points: np.ndarray
    layer: str
    closed: bool = True


def layer_name(side: str, thickness_mm: float) -> str:
    """The layer of printed plastic on ``side`` ("front"/"back") of ``thickness_mm``: e.g. front_0.40mm."""
    return f"{side}_{thickness_mm:.2f}mm"


def _rings(geom):
    """The exterior and interior rings of a shapely (Multi)Polygon as (k, 2) arrays, unrepeated."""
    polys = getattr(geom, "geoms", [geom])
    for p in polys:
        if p.is_empty or p.geom_type != "Polygon":
            continue
        for ring in (p.exterior, *p.interiors):
            yield np.asarray(ring.coords, float)[:-1, :2]


def pattern_drawing(pattern) -> list[Shape]:
    """The flat drawing of a geometry.patterns.Pattern: its fabric outline (layer ``fabric``)
    and each printed element's polygons, clipped to the fabric as the pattern holds them, on
    the layer of its side and thickness (:func:`layer_name`). Printed-state mm."""
    shapes = [Shape(r, "fabric") for r in _rings(pattern.outline)]
    for e in pattern.elements:
        layer = layer_name(e.side, float(e.thickness_mm))
        shapes += [Shape(r, layer) for r in _rings(e.geometry)]
    return shapes


def _check(where: str, shapes) -> None:
    for i, s in enumerate(shapes):
        check_finite_arrays(where, {f"shape {i + 1} ({s.layer})": np.asarray(s.points, float)})


# ----------------------------------------------------------------------------- DXF
def write_dxf(path, shapes) -> None:
    """DXF R2010 in millimetres ($INSUNITS 4): one LWPOLYLINE per shape on its layer."""
    import ezdxf
    from ezdxf import units

    _check("pattern.dxf", shapes)
    doc = ezdxf.new("R2010", setup=False)
    doc.units = units.MM
    doc.header["$MEASUREMENT"] = 1
    msp = doc.modelspace()
    for s in shapes:
        if s.layer not in doc.layers:
            doc.layers.add(s.layer, color=LAYER_COLOURS.get(s.layer.split("_")[0], 7))
        msp.add_lwpolyline([(float(x), float(y)) for x, y in s.points], close=bool(s.closed),
                           dxfattribs={"layer": s.layer})
    if shapes:                              # the drawing's extents, for viewers' initial "zoom all"
        lo, hi = _bounds(shapes, 0.0)
        ext = (float(lo[0]), float(lo[1]), 0.0), (float(hi[0]), float(hi[1]), 0.0)
        msp.reset_extents(*ext)
        # ezdxf copies the modelspace's extents into the header on saving, unless one is the
        # zero vector (a drawing from the origin): then the header's own values are kept
        doc.header["$EXTMIN"], doc.header["$EXTMAX"] = ext
    doc.saveas(path)


def read_dxf(path) -> tuple[list[Shape], int]:
    """(shapes, $INSUNITS) of a DXF: its LWPOLYLINEs (x, y) with their layer and closed flag."""
    import ezdxf

    try:
        doc = ezdxf.readfile(path)
    except (OSError, ezdxf.DXFStructureError) as e:
        raise SelfshapeError(f"{path}: not a readable DXF file ({e})") from None
    shapes = [Shape(np.array([(p[0], p[1]) for p in e.get_points("xy")], float), e.dxf.layer, bool(e.closed))
              for e in doc.modelspace().query("LWPOLYLINE")]
    return shapes, int(doc.header.get("$INSUNITS", 0))


# ----------------------------------------------------------------------------- SVG
SVG_NS = "http://www.w3.org/2000/svg"
INKSCAPE_NS = "http://www.inkscape.org/namespaces/inkscape"


def _bounds(shapes, margin_mm: float):
    pts = np.vstack([np.asarray(s.points, float) for s in shapes]) if shapes else np.zeros((1, 2))
    lo, hi = pts.min(0) - margin_mm, pts.max(0) + margin_mm
    return lo, hi


def svg_text(shapes, margin_mm: float = 2.0, *, inline: bool = False) -> str:
    """The SVG document of a drawing (see the module doc): mm size, viewBox in mm, y up.
    ``inline``: an <svg> element for an HTML page (no XML declaration, no namespaces)."""
    _check("pattern.svg", shapes)
    lo, hi = _bounds(shapes, margin_mm)
    w, h = hi - lo
    head = "<svg" if inline else \
        f'<?xml version="1.0" encoding="UTF-8"?>\n<svg xmlns="{SVG_NS}" xmlns:inkscape="{INKSCAPE_NS}"'
    out = [f'{head} width="{w:.4f}mm" height="{h:.4f}mm" viewBox="{lo[0]:.4f} {-hi[1]:.4f} {w:.4f} {h:.4f}">']
    layers = list(dict.fromkeys(s.layer for s in shapes))
    for layer in layers:
        colour = SVG_COLOURS.get(layer.split("_")[0], "#000000")
        name = html.escape(layer, quote=True)
        ink = "" if inline else f' inkscape:groupmode="layer" inkscape:label="{name}"'
        out.append(f'<g id="{name}"{ink} fill="none" stroke="{colour}" stroke-width="{SVG_STROKE_MM}">')
        for s in shapes:
            if s.layer == layer:
                pts = " ".join(f"{x:.4f},{0.0 - y:.4f}" for x, y in np.asarray(s.points, float))
                out.append(f'<{"polygon" if s.closed else "polyline"} points="{pts}"/>')
        out.append("</g>")
    out.append("</svg>\n")
    return "\n".join(out)


def write_svg(path, shapes, margin_mm: float = 2.0) -> None:
    """SVG of a drawing with width/height in mm and a viewBox in mm (see the module doc)."""
    text = svg_text(shapes, margin_mm)
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)


def _mm(text: str) -> float:
    m = re.fullmatch(r"\s*([-+0-9.eE]+)\s*mm\s*", text or "")
    if not m:
        raise SelfshapeError(f"SVG size {text!r} is not in mm")
    return float(m.group(1))


def read_svg(path) -> tuple[list[Shape], dict]:
    """(shapes, {"width_mm", "height_mm", "viewbox"}) of an SVG written by :func:`write_svg`:
    each <polygon>/<polyline> with the id of its enclosing <g> as the layer, y up again.
    A file that is not such an SVG (a regular file, sizes in mm, finite x,y points) is a
    one-line SelfshapeError naming it: `view` reads the pattern.svg of any folder."""
    from shellfem.infiles import check_input_file
    check_input_file(path, "SVG file")
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        raise SelfshapeError(f"{path}: not a readable SVG file ({e})") from None
    try:
        info = {"width_mm": _mm(root.get("width")), "height_mm": _mm(root.get("height")),
                "viewbox": [float(v) for v in root.get("viewBox", "").split()]}
    except (SelfshapeError, ValueError) as e:
        raise SelfshapeError(f"{path}: not an SVG of selfshape ({e})") from None
    shapes = []
    for g in root.iter(f"{{{SVG_NS}}}g"):
        for el in g:
            tag = el.tag.split("}")[-1]
            if tag in ("polygon", "polyline"):
                try:
                    xy = np.array([[float(v) for v in p.split(",")] for p in el.get("points", "").split()], float)
                    xy = xy.reshape(-1, 2)
                except ValueError:
                    raise SelfshapeError(f"{path}: a <{tag}> has points that are not x,y pairs") from None
                if not np.isfinite(xy).all():
                    raise SelfshapeError(f"{path}: a <{tag}> has points that are not finite numbers")
                xy[:, 1] *= -1.0
                shapes.append(Shape(xy, g.get("id"), tag == "polygon"))
    return shapes, info


# ----------------------------------------------------------------------------- by suffix
def _suffix(path) -> str:
    return "." + str(path).rsplit(".", 1)[-1].lower() if "." in str(path) else ""


def write_drawing(path, shapes) -> None:
    """A flat drawing as DXF or SVG, by the suffix of ``path`` (see :func:`write_dxf`, :func:`write_svg`)."""
    fn = {".dxf": write_dxf, ".svg": write_svg}.get(_suffix(path))
    if fn is None:
        raise SelfshapeError(f"{path}: a flat pattern is written as .dxf or .svg")
    fn(path, shapes)


def read_drawing(path) -> list[Shape]:
    """The shapes of a DXF or SVG drawing, by the suffix of ``path`` (see :func:`read_dxf`, :func:`read_svg`)."""
    fn = {".dxf": read_dxf, ".svg": read_svg}.get(_suffix(path))
    if fn is None:
        raise SelfshapeError(f"{path}: a flat pattern is read from .dxf or .svg")
    return fn(path)[0]


def export_pattern_file(pattern_path, out_path) -> dict:
    """`selfshape export PATTERN -o OUT.dxf|.svg`: the flat drawing of a pattern file (.toml, or
    .gcode: geometry.patterns) without simulating it, for the laser cutter or CAD. The output is
    checked before the work (shellfem.outfiles.check_output_file: a .dxf or .svg file, not an
    input) and written atomically. Returns dict(path, n_shapes, layers)."""
    from geometry.patterns import load_pattern
    from shellfem.outfiles import check_output_file, write_atomic
    p = check_output_file(out_path, inputs=[pattern_path], what="export output (-o)")
    if _suffix(p) not in (".dxf", ".svg"):
        raise SelfshapeError(f"{p}: the export output (-o) must be a .dxf or .svg file")
    drawing = pattern_drawing(load_pattern(pattern_path))
    os.makedirs(os.path.dirname(os.path.abspath(p)), exist_ok=True)      # as predict: missing folders made
    write_atomic(p, lambda tmp: write_drawing(tmp, drawing))
    return {"path": p, "n_shapes": len(drawing), "layers": list(dict.fromkeys(s.layer for s in drawing))}


# ----------------------------------------------------------------------------- surfaces
def write_surface(path, points, triangles) -> None:
    """A triangulated surface, points (n, 3) mm and triangles (m, 3), as OBJ, STL or PLY (by the
    suffix; STL and PLY binary). NonFiniteOutput if a coordinate is not finite."""
    import meshio

    suffix = _suffix(path)
    if suffix not in SURFACE_FORMATS:
        raise SelfshapeError(f"{path}: a surface is written as {', '.join(SURFACE_FORMATS)}")
    pts = np.asarray(points, float)
    check_finite_arrays(f"deployed{suffix}", {"positions": pts})
    mesh = meshio.Mesh(pts, [("triangle", np.asarray(triangles, dtype=np.int32))])     # PLY: 32-bit indices
    if suffix == ".obj":
        meshio.write(path, mesh, file_format="obj")
    else:
        meshio.write(path, mesh, file_format=SURFACE_FORMATS[suffix], binary=True)


def read_surface(path) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) mm, triangles (m, 3)) of an OBJ, STL or PLY surface (meshio). STL stores
    each triangle's corners on their own; meshio merges the repeated points."""
    from shellfem.infiles import read_meshio
    m = read_meshio(path, "surface mesh")
    tri = np.vstack([c.data for c in m.cells if c.type == "triangle"])
    return np.asarray(m.points, float), tri

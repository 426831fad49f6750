""".msh files of meshed patterns (Gmsh format 4.1): written from the live Gmsh model, read back as a Sheet.

A pattern's .msh has one physical surface group per printed region, named "region_k" with
tag k, and "fabric" (tag K + 1) for bare fabric, and element data "region",
"thickness_front" and "thickness_back" (mm) per triangle.
"""
from __future__ import annotations

import os
import re

import numpy as np

from shellfem.errors import SelfshapeError
from shellfem.infiles import check_input_file, read_meshio
from shellfem.sheet import Sheet

ELEMENT_DATA = ("region", "thickness_front", "thickness_back")


def add_physical_groups(gmsh, region_surfaces: list, fabric_surfaces: list) -> None:
    """Name the meshed surfaces: region_surfaces[k - 1] the Gmsh surfaces of printed region k
    ("region_k", tag k), fabric_surfaces the bare fabric ("fabric", tag K + 1)."""
    k = len(region_surfaces)
    for r, tags in enumerate(region_surfaces, 1):
        gmsh.model.addPhysicalGroup(2, tags, tag=r, name=f"region_{r}")
    if fabric_surfaces:
        gmsh.model.addPhysicalGroup(2, fabric_surfaces, tag=k + 1, name="fabric")


def write_msh(gmsh, path, sheet: Sheet, element_tags) -> None:
    """Write the current Gmsh model's mesh to ``path`` (.msh 4.1, physical groups only) and
    append the element data of ``sheet`` (triangle j is Gmsh element element_tags[j])."""
    gmsh.option.setNumber("Mesh.SaveAll", 0)
    gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
    gmsh.option.setNumber("PostProcessing.SaveMesh", 0)
    gmsh.option.setNumber("PostProcessing.SaveInterpolationMatrices", 0)
    gmsh.write(path)
    order = np.argsort(element_tags)          # element data in the file's element order
    model = gmsh.model.getCurrent()
    for name, values in zip(ELEMENT_DATA, (sheet.region.astype(float), sheet.thickness_front, sheet.thickness_back)):
        v = gmsh.view.add(name)
        gmsh.view.addHomogeneousModelData(v, 0, model, "ElementData", element_tags[order].tolist(),
                                          values[order].tolist())
        gmsh.view.write(v, path, append=True)


def read_msh(path) -> Sheet:
    """Read a .msh written by mesh_pattern_file (or any planar triangle .msh) as a Sheet.

    Region ids come from the physical names ("fabric" -> 0, "region_k" -> k); without
    physical names every triangle is region 0. Thickness comes from the element data
    "thickness_front"/"thickness_back" when present, else 0.
    """
    path = os.fspath(path)
    check_input_file(path, "Gmsh mesh", path)
    with open(path, "rb") as f:
        if b"$MeshFormat" not in f.read(4096):
            raise SelfshapeError(f"{path}: cannot read the Gmsh mesh (no $MeshFormat header)")
    m = read_meshio(path, "Gmsh mesh", path, file_format="gmsh")
    for k in [k for k in m.cell_sets if k.startswith("gmsh:")]:
        del m.cell_sets[k]
    blocks = [i for i, c in enumerate(m.cells) if c.type == "triangle"]
    if not blocks:
        raise SelfshapeError(f"{path}: no triangles in the mesh")
    tri = np.vstack([m.cells[i].data for i in blocks])

    def cell_values(name, default):
        if name not in m.cell_data:
            return np.full(len(tri), default)
        return np.concatenate([np.asarray(m.cell_data[name][i]).reshape(-1) for i in blocks])

    names = {int(v[0]): k for k, v in m.field_data.items() if len(v) > 1 and int(v[1]) == 2}
    phys = cell_values("gmsh:physical", 0).astype(np.int64)
    region = np.zeros(len(tri), np.int64)
    if names:
        lut = {}
        for tag, name in names.items():
            mm = re.fullmatch(r"region_(\d+)", name)
            if name == "fabric":
                lut[tag] = 0
            elif mm:
                lut[tag] = int(mm.group(1))
            else:
                raise SelfshapeError(f"{path}: physical group {name!r} is neither \"fabric\" nor \"region_k\"")
        unknown = sorted(set(np.unique(phys)) - set(lut))
        if unknown:
            raise SelfshapeError(f"{path}: triangles in physical group {unknown[0]} which has no name")
        keys = np.array(sorted(lut))
        region = np.array([lut[k] for k in keys], np.int64)[np.searchsorted(keys, phys)]
    pts = np.asarray(m.points, float)
    if pts.shape[1] == 3:
        span = max(float(np.ptp(pts[:, :2], axis=0).max()), 1e-300)
        if np.abs(pts[:, 2]).max() > 1e-9 * span:
            raise SelfshapeError(f"{path}: the mesh is not flat (z != 0); a Sheet is a planar printed state")
    if not np.isfinite(pts).all():
        raise SelfshapeError(f"{path}: node {int(np.flatnonzero(~np.isfinite(pts).all(1))[0])} has a non-finite coordinate")
    thick = {}
    for name in ("thickness_front", "thickness_back"):
        v = np.asarray(cell_values(name, 0.0), float)
        bad = np.flatnonzero(~(np.isfinite(v) & (v >= 0.0)))
        if len(bad):
            raise SelfshapeError(f"{path}: element data {name} of triangle {int(bad[0])} is {v[bad[0]]!r} "
                                 f"(a plastic thickness is a finite number >= 0 mm)")
        thick[name] = v
    used, inv = np.unique(tri, return_inverse=True)
    P = pts[used, :2]
    T = inv.reshape(-1, 3)
    e1, e2 = P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]
    area2 = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    span = max(float(np.ptp(P, axis=0).max()), 1e-300)
    flat = np.flatnonzero(area2 <= 1e-12 * span * span)
    if len(flat):
        raise SelfshapeError(f"{path}: triangle {int(flat[0])} has zero area (repeated or collinear nodes)")
    return Sheet(P, T, region, thick["thickness_front"], thick["thickness_back"])

"""The seed's chapter-3 model: a fabric shell with discrete elastic rods on its vertices,
in one energy for shellfem.newton.

Total energy (N mm) = the bare fabric's shell energy (ShellModel.from_materials on a sheet
without printed triangles: the fabric's membrane model + bending k_B everywhere, gravity)
+ the rods' energy (shellfem.rods.energy) over the same vertex positions. The rods carry
the printed plastic: stiffness and rest curvature of the effective monolayer
(shellfem.rods.monolayer), the fabric below them is modelled twice (as fabric and inside
the monolayer), which the plastic/fabric stiffness ratio makes negligible (E2 h2^3 / (E1
h1^3) ~ 1e-2 at the seed's 1/3200 ratio... 1/69 for the default TPU on spandex).

Assembly: the rods' bending stencils have 21 position DOFs, the width of the shell's face
blocks, so they are appended to the face index set, and the 6-DOF stretching blocks are
padded to 21 (their DOFs repeated, zero entries): the solver's BlockScatter, relaxations
and sensitivities see one face set and one hinge set as with the shell alone. The edge
angles (shell DOFs) do not enter the rods' energy, so the edge-angle elimination of the
solver (EdgeAngleProblem) is the shell's.
"""
from __future__ import annotations

import numpy as np

from shellfem.model import ShellModel
from shellfem.rods.energy import RodNetwork, build_network
from shellfem.rods.monolayer import arm_section, offset_arm_section
from shellfem.sheet import Sheet


class RodShellModel:
    """ShellModel-compatible energy: shell + rods (the interface shellfem.newton uses)."""

    kind = "rods"          # what summary.json reports as the model
    contact = None         # no contact in the rods model yet (shellfem.contact is the shell's)
    contact_hessian = None

    def step_fraction(self, q0, q1) -> float:
        """1.0: no contact filters the solver's steps (ShellModel.step_fraction)."""
        return 1.0

    def trial_energy(self, q0, q1, below=None) -> float:
        """The energy at q1 (N mm; ShellModel.trial_energy without contact)."""
        return self.energy(q1)

    def __init__(self, shell: ShellModel, rods: RodNetwork):
        self.shell, self.rods = shell, rods
        self.sheet, self.topo = shell.sheet, shell.topo
        self.n_vertices, self.n_edges, self.n_dofs = shell.n_vertices, shell.n_edges, shell.n_dofs
        self.external_force = shell.external_force
        self.membrane_mask = shell.membrane_mask
        self._m = len(shell.face_dofs)
        self._nb = len(rods.weight)
        sd = rods.stretch_dofs
        self._ns = len(sd)
        pad = np.concatenate([sd, sd, sd, sd[:, :3]], 1)                       # (ns, 21)
        self.face_dofs = np.concatenate([shell.face_dofs, rods.bend_dofs, pad]).astype(np.int64)
        self.hinge_dofs = shell.hinge_dofs

    # --- the shell's interface, delegated -----------------------------------------------
    def split(self, q):
        return self.shell.split(q)

    def initial_state(self):
        return self.shell.initial_state()

    def edge_angle_problem(self, q):
        return self.shell.edge_angle_problem(q)

    def curvatures(self, q):
        return self.shell.curvatures(q)

    def fundamental_forms(self, q):
        return self.shell.fundamental_forms(q)

    def cartesian_forms(self, q):
        return self.shell.cartesian_forms(q)

    @property
    def edge_bending_form(self):
        return self.shell.edge_bending_form

    def printed_dofs(self) -> np.ndarray:
        """Positions of the rod vertices (the stiff part of this model)."""
        mask = np.zeros(self.n_dofs, bool)
        v = np.unique(self.rods.edges)
        mask[(3 * v[:, None] + np.arange(3)).ravel()] = True
        return mask

    # --- energy ---------------------------------------------------------------------------
    def energy(self, q, below=None) -> float:
        """Shell + rods energy at q (N mm); ``below`` is ShellModel.energy's (no contact here)."""
        x, _ = self.split(q)
        return self.shell.energy(q) + self.rods.energy(x)

    def gradient(self, q):
        g = self.shell.gradient(q)
        g[:3 * self.n_vertices] += self.rods.gradient(self.split(q)[0])
        return g

    def block_buffers(self):
        Hf, Hh = self.shell.block_buffers()
        return np.empty((self._m + self._nb + self._ns, 21, 21)), Hh

    def hessian_blocks(self, q, out=None):
        """(E, gradient, (face + rod blocks, hinge blocks)); see ShellModel.hessian_blocks."""
        m, nb = self._m, self._nb
        shell_out = None
        if out is not None:
            shell_out = (out[0][:m], out[1])
        E, g, (Hf, Hh) = self.shell.hessian_blocks(q, out=shell_out)
        Er, gr, Hs, Hb = self.rods.evaluate(self.split(q)[0], order=2)
        blocks = out[0] if out is not None else np.empty((m + nb + self._ns, 21, 21))
        if not np.shares_memory(Hf, blocks):
            blocks[:m] = Hf
        blocks[m:m + nb] = Hb
        rest = blocks[m + nb:]
        rest[:] = 0.0
        rest[:, :6, :6] = Hs
        g = g.copy()
        g[:3 * self.n_vertices] += gr
        return E + Er, g, (blocks, Hh)

    def rod_measures(self, q) -> np.ndarray:
        """(k1, k2, tau) per rod stencil (dimensionless integrated values; divide by the
        stencil's Voronoi length (l0 + l1) / 2 for 1/mm)."""
        return self.rods.measures(self.split(q)[0])


def arm_rods(sheet: Sheet, edges, plastic_thickness, width, fabric, plastic, side="front",
             offset: bool = False) -> RodNetwork:
    """Rods on mesh edges ``edges`` (ne, 2) of the sheet for printed arms of plastic thickness
    and width (mm, per edge or scalars): the effective monolayer of each edge
    (shellfem.rods.monolayer) with the fabric's misfit along the edge, 1 - t^T diag(1/sx^2,
    1/sy^2) t (t the printed edge direction), and the plastic set. Front plastic bends
    towards -z (rest k1 < 0: centre of curvature on the fabric side), back plastic towards +z;
    side: "front", "back" or per edge +1 (front) / -1 (back).
    offset: the arms as printed ON the fabric (shellfem.rods.monolayer.offset_arm_section:
    the plastic's rod with its centre line (h1 + h2) / 2 above the fabric's mid-surface,
    shellfem.rods.energy's offset term; the bilayer effect from the mesh's fabric, the rest
    curvature the plastic set only) instead of the seed's rods in the fabric (default)."""
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    P = sheet.points
    t = P[edges[:, 1]] - P[edges[:, 0]]
    t /= np.linalg.norm(t, axis=1)[:, None]
    sx, sy = fabric.stretch
    misfit_metric = t[:, 0] ** 2 / sx ** 2 + t[:, 1] ** 2 / sy ** 2
    s_edge = 1 / np.sqrt(misfit_metric)
    if offset:
        sec, height = offset_arm_section(plastic_thickness, width, fabric.thickness, plastic.young_modulus,
                                         plastic_poisson=plastic.poisson, plastic_set=plastic.rest_curvature)
    else:
        sec = arm_section(plastic_thickness, width, fabric.thickness, plastic.young_modulus, fabric.young_modulus,
                          s_edge, plastic_poisson=plastic.poisson, plastic_set=plastic.rest_curvature)
        height = 0.0
    if isinstance(side, str):
        if side not in ("front", "back"):
            raise ValueError(f"side must be 'front' or 'back', got {side!r}")
        sign = -1.0 if side == "front" else 1.0
    else:
        sign = -np.sign(np.asarray(side, float))
    # the neutral axis on the plastic's side: +d1 (+z flat) for front plastic, -d1 for back
    return build_network(P, edges, EA=sec.EA, B1=sec.B1, B2=sec.B2, T=sec.T, triangles=sheet.triangles,
                         normal_rest_curvature=sign * sec.rest_curvature, offset=-sign * height)


def rod_shell_model(sheet: Sheet, fabric, plastic, edges, plastic_thickness, width, side="front",
                    gravity: bool = True, offset: bool = False) -> RodShellModel:
    """Bare fabric on the whole sheet (its printed thicknesses ignored) + rods on ``edges``
    (offset: the arms on the fabric, see arm_rods)."""
    bare = Sheet(sheet.points, sheet.triangles, region=sheet.region)
    shell = ShellModel.from_materials(bare, fabric, plastic, gravity=gravity)
    return RodShellModel(shell, arm_rods(bare, edges, plastic_thickness, width, fabric, plastic, side, offset=offset))

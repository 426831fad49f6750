"""Discrete second fundamental forms: b per triangle from the mid-edge degrees of freedom.

A formulation maps each triangle's edge heights h_i (mm) and mid-edge tilt angles psi_i
(rad, shellfem.kinematics) to b = sum_i beta(h_i, psi_i) c_i c_i^T (edge-basis components, mm)
and supplies the derivatives of the edge coefficient beta. It knows nothing of materials:
the face energy (shellfem.face_energy) chains a material's dW/db through it.

- :mod:`shellfem.bending.midedge_tan`: beta = -2 tan(psi) h (libshell's MidedgeAngleTan).
"""

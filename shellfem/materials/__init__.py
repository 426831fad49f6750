"""Materials: the fabric and plastic records, and the fabric's membrane models.

    from shellfem.materials import Fabric, Plastic

The bare fabric's in-plane energy is a membrane model (shellfem.materials.base), chosen by
``Fabric.model`` (``[fabric] model`` in a pattern) from :data:`MEMBRANE_MODELS`. To add one,
write a module with a MembraneModel subclass (name, parameter schema, energy of a) and list
the class in the registration below; the pattern format, the Fabric record and ShellModel
pick it up from the registry.
"""
from shellfem.materials.base import (MEMBRANE_MODELS, MembraneModel, Parameter, RestState, membrane_model,
                                     register)
from shellfem.materials.neo_hookean import NeoHookean
from shellfem.materials.orthotropic import Orthotropic
from shellfem.materials.orthotropic_stvk import OrthotropicStVK
from shellfem.materials.records import Fabric, Plastic

for _model in (NeoHookean, Orthotropic, OrthotropicStVK):       # the registration
    register(_model)

__all__ = ["Fabric", "Plastic", "MEMBRANE_MODELS", "MembraneModel", "Parameter", "RestState", "membrane_model",
           "register"]

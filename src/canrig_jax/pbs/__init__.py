"""Patch blendshapes (PBS, CANRig section 4) for the whole head: a patch layout over the mesh
(geodesic Voronoi cells and their rings), a data-driven basis fitted per patch, the CANRig-PBS
networks that predict each patch's weights from handle displacements (three final variants,
Figure 8's rows) and the Shape Transformer baseline (``PBS_MODELS`` names them for
``PBSTrainOptions.model``), their training, and two handle rigs (``canrig.AbstractHandleRig``)
that every CANRig workflow runs on: ``PBSRig`` (a trained network with its basis) and
``LocalFitRig`` (local least-squares fits of the basis, no network).

Also importable here but not in ``__all__``: ``HANDLE_RIGS``, every final handle rig (the
family's contract test runs over it)."""

from ..canrig import HANDLE_RIGS as _ATTENTION_RIGS
from ._basis import PatchLayout, fit_pbs, local_pbs_fit, patch_layout, pbs_basis, pbs_shape
from ._local_fit import LocalFitRig, local_fit_rig
from ._model import AbstractCANRigPBS, PerPatchPBS
from ._rig import PBSRig, pbs_rig
from ._train import (
    PBS_MODELS,
    PBSTrainOptions,
    build_pbs_training_set,
    load_pbs_model,
    pbs_reconstruct,
    seed_distances,
    train_pbs,
)

HANDLE_RIGS = (*_ATTENTION_RIGS, LocalFitRig, PBSRig)
"""Every final handle rig (``canrig.AbstractHandleRig``): ``CANRig``,
``ShapePreservingCANRig``, ``LocalFitRig``, ``PBSRig`` (with any CANRig-PBS variant); the list
the family's contract test runs over (not in ``__all__``)."""

__all__ = [
    "PBS_MODELS",
    "AbstractCANRigPBS",
    "LocalFitRig",
    "PBSRig",
    "PBSTrainOptions",
    "PatchLayout",
    "PerPatchPBS",
    "build_pbs_training_set",
    "fit_pbs",
    "load_pbs_model",
    "local_fit_rig",
    "local_pbs_fit",
    "patch_layout",
    "pbs_basis",
    "pbs_reconstruct",
    "pbs_rig",
    "pbs_shape",
    "seed_distances",
    "train_pbs",
]

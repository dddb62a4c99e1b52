"""RigAnyFace auto-rigging: an ARKit blendshape rig with correctives for any neutral head.

- ``auto_rig`` (one head), ``auto_rig_heads`` (many, or across processes) and
  ``auto_rig_avatar`` (a whole-body FBX, GLB or VRM): the head's orientation decided from its
  face (``OrientationError`` when it cannot be), the ICT landmarks placed, the rig built by a
  method and the blinks closed; a ``Style`` fitted to a few example shapes (``fit_style``).
- The methods, one family (``AbstractAutoRigMethod``, every one in ``AUTO_RIG_METHODS``):
  ``Transfer`` (the default, ``DEFAULT_METHOD``; a ``Template`` of your own),
  ``RigAnyFaceNetwork`` and ``TransferResidual`` (``AbstractNetworkMethod``: ``generate``
  runs the network on a head in its convention, a ``GeneratedRig``).
- The rigger's checks of a rig under motion: ``check_rig`` (``RigCheck`` of ``Check`` rows
  against ``CHECK_LIMITS``) and ``plot_check_frames``; ``head_orientation`` reports which way
  a head faces.
- Heads sculpted by other people, with their artists' ARKit shapes: ``load_makehuman``,
  ``load_rocketbox_head``; the ICT source the methods carry (``ict_pose_source``).
- The network and its training: ``DiffusionNet`` (with ``heat_kernel_signature`` and
  ``hks_times`` as intrinsic inputs), the packaged model (``DEFAULT_CHECKPOINT``,
  ``load_riganyface``, ``export_riganyface``), ``train_riganyface`` on a ``training_set`` of
  ICT identities (``ict_autorig_dataset``) with ``RigAnyFaceTrainOptions``, and
  ``transfer_poses``, the deformation-transfer base of a residual network.

The evaluation of the paper (held-out splits, recipes, tables) is ``canrig_jax.papers.riganyface``.
"""

from ._any_head import AutoRig, auto_rig, auto_rig_heads
from ._avatar import AvatarRig, auto_rig_avatar
from ._data import ict_autorig_dataset, ict_pose_source, transfer_poses
from ._diffusion_net import DiffusionNet
from ._features import heat_kernel_signature, hks_times
from ._makehuman import load_makehuman
from ._methods import (
    AUTO_RIG_METHODS,
    DEFAULT_METHOD,
    AbstractAutoRigMethod,
    AbstractNetworkMethod,
    RigAnyFaceNetwork,
    Template,
    Transfer,
    TransferResidual,
)
from ._orientation import HeadOrientation, OrientationError, head_orientation
from ._rig import GeneratedRig
from ._rig_checks import LIMITS as CHECK_LIMITS
from ._rig_checks import Check, RigCheck, check_rig, plot_check_frames
from ._rocketbox import load_rocketbox_head
from ._style import Style, fit_style
from ._train import (
    DEFAULT_CHECKPOINT,
    RigAnyFaceTrainOptions,
    RigAnyFaceTrainResult,
    export_riganyface,
    load_riganyface,
    train_riganyface,
    training_set,
)

__all__ = [
    # auto-rigging a head, many heads, an avatar
    "AutoRig",
    "AvatarRig",
    "Style",
    "auto_rig",
    "auto_rig_avatar",
    "auto_rig_heads",
    "fit_style",
    "ict_pose_source",
    # the methods
    "AUTO_RIG_METHODS",
    "DEFAULT_METHOD",
    "AbstractAutoRigMethod",
    "AbstractNetworkMethod",
    "GeneratedRig",
    "RigAnyFaceNetwork",
    "Template",
    "Transfer",
    "TransferResidual",
    # orientation
    "HeadOrientation",
    "OrientationError",
    "head_orientation",
    # checking a rig
    "CHECK_LIMITS",
    "Check",
    "RigCheck",
    "check_rig",
    "plot_check_frames",
    # heads sculpted by other people
    "load_makehuman",
    "load_rocketbox_head",
    # the network, its model and its training
    "DEFAULT_CHECKPOINT",
    "DiffusionNet",
    "RigAnyFaceTrainOptions",
    "RigAnyFaceTrainResult",
    "export_riganyface",
    "heat_kernel_signature",
    "hks_times",
    "ict_autorig_dataset",
    "load_riganyface",
    "train_riganyface",
    "training_set",
    "transfer_poses",
]

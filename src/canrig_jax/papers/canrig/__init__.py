"""The CANRig evaluation (Mohammadi, Weiss et al.; ``experiments/canrig_*.py``): the held-out
data (``split_capture``: the capture's halves; ``held_out_poses``), the masks it evaluates
(``RADII_CM``, ``EVAL_FALLOFF_PER_CM``), the training script's options
(``add_training_options``, ``training_options_from_args``), and two modules of tables:

- ``canrig_jax.papers.canrig.workflows``: the workflows on the ICT face (Table 4's pose A to
  B, Figure 15's layers, Figure 10's clip edit, dialogue replacement and its baselines), on the
  trained network or the rig with no network (``experiments/canrig_workflows*.py``).
- ``canrig_jax.papers.canrig.whole_head``: patch blendshapes on the whole ICT head (Table 5,
  Table 6 and its sweep over mouth handles; ``experiments/canrig_pbs*.py``), with the check
  that a saved PBS model matches its run (``check_pbs_training_matches``) and Table 6's reach
  floor (``reach_floor``).
"""

from ...canrig._data import EVAL_FALLOFF_PER_CM, RADII_CM
from ._pbs_checks import check_pbs_training_matches, reach_floor
from ._splits import held_out_poses, split_capture
from ._training import add_training_options, training_options_from_args

__all__ = [
    "EVAL_FALLOFF_PER_CM",
    "RADII_CM",
    "add_training_options",
    "check_pbs_training_matches",
    "held_out_poses",
    "reach_floor",
    "split_capture",
    "training_options_from_args",
]

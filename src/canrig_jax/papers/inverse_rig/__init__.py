"""The inverse-rig evaluation (Racković et al. 2023; ``experiments/inverse_rig*.py``): the
alpha rule (``select_alpha``: the largest L1 weight within 5 % of the best training error),
the temporal rig's smoothness rule (``select_smoothness``, ``lowest_error_smoothness`` over a
``smoothness_curve`` on held-out motion, ``validation_split``; synthetic
``smooth_training_takes``) and its scores (``temporal_row``, ``temporal_targets``, the
take's ``take_objective``, the tables ``temporal_table`` and ``validation_split_table``),
the sparsity protocol (``alpha_sweep``, ``sparsest_alpha_within``, ``sparsity_verdict`` on
``noisy_meshes``), the NumPy reference of Algorithm 1 (``numpy_quartic_cd``, ``NumpyDenseRig``)
and of the authors' holistic solver (``numpy_holistic_cd``, ``holistic_lambdas``), the float64
minimum every method is measured against (``minimum``), and the timing harnesses
(``time_batched``, ``time_single_frames``, ``time_against_projection``,
``measure_reference``).
"""

from ...inverse._temporal import take_objective
from ._alpha import select_alpha
from ._reference import (
    NumpyDenseRig,
    decreasing_norm_order,
    measure_reference,
    minimum,
    numpy_quartic_cd,
    time_against_projection,
    time_batched,
    time_single_frames,
)
from ._sparsity import (
    SPARSITY_TARGET,
    alpha_sweep,
    noisy_meshes,
    sparsest_alpha_within,
    sparsity_verdict,
)
from ._temporal import (
    KEY_SPACING_S,
    lowest_error_smoothness,
    select_smoothness,
    smooth_training_takes,
    smoothness_curve,
    temporal_row,
    temporal_table,
    temporal_targets,
    validation_split,
    validation_split_table,
)
from ._temporal_reference import holistic_lambdas, numpy_holistic_cd

__all__ = [
    "KEY_SPACING_S",
    "SPARSITY_TARGET",
    "NumpyDenseRig",
    "alpha_sweep",
    "decreasing_norm_order",
    "holistic_lambdas",
    "lowest_error_smoothness",
    "measure_reference",
    "minimum",
    "noisy_meshes",
    "numpy_holistic_cd",
    "numpy_quartic_cd",
    "select_alpha",
    "select_smoothness",
    "smooth_training_takes",
    "smoothness_curve",
    "sparsest_alpha_within",
    "sparsity_verdict",
    "take_objective",
    "temporal_row",
    "temporal_table",
    "temporal_targets",
    "time_against_projection",
    "time_batched",
    "time_single_frames",
    "validation_split",
    "validation_split_table",
]

"""Inverse rig (Racković et al. 2023): weights from a mesh, one call shape for all methods.

    problem = inverse.prepare(rig)
    sol = inverse.solve(problem, target, inverse.QuarticCD(alpha=0.5))
    sol.weights, sol.objective, sol.history, sol.result, sol.stats

Every method is an ``AbstractInverseMethod`` (``METHODS`` lists the classes):
``QuarticCD``, ``LinearCD`` (coordinate descent, ``AbstractCoordinateDescent``),
``QuarticNewton`` (projected Gauss-Newton on the same objective), ``Seol``,
``Joshi``, ``Cetinaslan``, ``LMMM``, ``JaxoptLBFGSB``. Coordinate orders in ``ORDERS``;
mutually exclusive pairs, left/right ties and the production solver's terms (L2, a
previous-frame term in a ``Stream``, an active-shape mask, per-shape multipliers and offsets)
with ``Constrained`` (``rig.exclusive_pairs``, ``left_right_pairs``, ``pair_indices``), read
from an Audio2Face-3D solver configuration with ``from_audio2face_config``;
whole takes with ``solve_sequence``
(jointly and smooth in time with ``TemporalNewton``; its smoothness rule and scores:
``select_smoothness``, ``smoothness_curve``, ``validation_split``, ``temporal_row``,
``temporal_targets``);
a take carried onto another control set of the same mesh with ``retarget``;
live capture with ``Stream``; metrics
(``summarize``, ``roughness``, ``select_alpha``); the sparsity protocol (``alpha_sweep``,
``sparsest_alpha_within``, ``sparsity_verdict``); the NumPy reference of Algorithm 1
(``numpy_quartic_cd``, ``minimum``) for checks and speed ratios.
"""

from ._audio2face import from_audio2face_config
from ._base import AbstractInverseMethod, Iterate
from ._constraints import (
    Constrained,
    both_active,
    left_right_pairs,
    pair_indices,
)
from ._coordinate_descent import (
    ORDERS,
    AbstractCoordinateDescent,
    LinearCD,
    QuarticCD,
    Seol,
    objective,
    static_order,
)
from ._jaxopt_solver import JaxoptLBFGSB
from ._least_squares import Cetinaslan, Joshi
from ._lmmm import LMMM
from ._metrics import (
    CARDINALITY_TOL,
    frame_metrics,
    mm_per_unit,
    roughness,
    select_alpha,
    summarize,
)
from ._problem import InverseProblem, prepare
from ._projected_newton import QuarticNewton
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
from ._retarget import NEUTRAL_TOL_MM, retarget
from ._solution import Solution
from ._solve import FRAMES_PER_CALL, HISTORY_FRAMES, Stream, solve, solve_sequence
from ._sparsity import (
    SPARSITY_TARGET,
    alpha_sweep,
    noisy_meshes,
    sparsest_alpha_within,
    sparsity_verdict,
)
from ._temporal import (
    DEFAULT_SMOOTHNESS_CM2,
    AbstractTemporalMethod,
    TemporalNewton,
    take_objective,
)
from ._temporal_protocols import (
    lowest_error_smoothness,
    select_smoothness,
    smooth_training_takes,
    smoothness_curve,
    temporal_row,
    temporal_targets,
    validation_split,
)
from ._temporal_reference import holistic_lambdas, numpy_holistic_cd

METHODS = (
    QuarticCD,
    QuarticNewton,
    TemporalNewton,
    LinearCD,
    Seol,
    Joshi,
    Cetinaslan,
    LMMM,
    JaxoptLBFGSB,
    Constrained,
)
"""Every inverse-rig method class (each a final ``AbstractInverseMethod``)."""

__all__ = [
    "CARDINALITY_TOL",
    "SPARSITY_TARGET",
    "alpha_sweep",
    "noisy_meshes",
    "sparsest_alpha_within",
    "sparsity_verdict",
    "Constrained",
    "both_active",
    "left_right_pairs",
    "pair_indices",
    "from_audio2face_config",
    "NEUTRAL_TOL_MM",
    "retarget",
    "NumpyDenseRig",
    "decreasing_norm_order",
    "frame_metrics",
    "measure_reference",
    "minimum",
    "mm_per_unit",
    "numpy_quartic_cd",
    "roughness",
    "select_alpha",
    "summarize",
    "time_batched",
    "time_against_projection",
    "time_single_frames",
    "METHODS",
    "ORDERS",
    "AbstractCoordinateDescent",
    "AbstractInverseMethod",
    "AbstractTemporalMethod",
    "Cetinaslan",
    "InverseProblem",
    "Iterate",
    "JaxoptLBFGSB",
    "Joshi",
    "LMMM",
    "LinearCD",
    "QuarticCD",
    "QuarticNewton",
    "Seol",
    "Solution",
    "Stream",
    "FRAMES_PER_CALL",
    "HISTORY_FRAMES",
    "DEFAULT_SMOOTHNESS_CM2",
    "objective",
    "prepare",
    "solve",
    "solve_sequence",
    "static_order",
    "take_objective",
    "TemporalNewton",
    "holistic_lambdas",
    "numpy_holistic_cd",
    "lowest_error_smoothness",
    "select_smoothness",
    "smooth_training_takes",
    "smoothness_curve",
    "temporal_row",
    "temporal_targets",
    "validation_split",
]

"""Inverse rig (Racković et al. 2023): weights from a mesh, one call shape for all methods.

    problem = inverse.prepare(rig)
    sol = inverse.solve(problem, target, inverse.QuarticCD(alpha=0.5))
    sol.weights, sol.objective, sol.history, sol.result, sol.stats

Every method is an ``AbstractInverseMethod`` (``METHODS`` lists the classes):
``QuarticCD``, ``LinearCD`` (coordinate descent), ``QuarticNewton`` (projected Gauss-Newton on
the same objective), ``Seol``, ``Joshi``, ``Cetinaslan``, ``LMMM``, ``JaxoptLBFGSB``.
Coordinate orders in ``ORDERS``; mutually exclusive pairs, left/right ties and the production
solver's terms (L2, a previous-frame term in a ``Stream``, an active-shape mask, per-shape
multipliers and offsets) with ``Constrained`` (``rig.exclusive_pairs``, ``left_right_pairs``,
``pair_indices``, ``both_active``), read from an Audio2Face-3D solver configuration with
``from_audio2face_config``; whole takes with ``solve_sequence`` (jointly and smooth in time
with ``TemporalNewton``); a take carried onto another control set of the same mesh with
``retarget``; live capture with ``Stream``; metrics (``summarize``, ``roughness``).

The paper's evaluation (the alpha and smoothness rules, the sparsity protocol, the NumPy
reference of Algorithm 1, the timing harnesses) is ``canrig_jax.papers.inverse_rig``.
"""

from ._audio2face import from_audio2face_config
from ._base import AbstractInverseMethod, Iterate
from ._constraints import (
    Constrained,
    both_active,
    left_right_pairs,
    pair_indices,
)
from ._coordinate_descent import ORDERS, LinearCD, QuarticCD, Seol
from ._jaxopt_solver import JaxoptLBFGSB
from ._least_squares import Cetinaslan, Joshi
from ._lmmm import LMMM
from ._metrics import CARDINALITY_TOL, roughness, summarize
from ._problem import InverseProblem, prepare
from ._projected_newton import QuarticNewton
from ._retarget import retarget
from ._solution import Solution
from ._solve import FRAMES_PER_CALL, Stream, solve, solve_sequence
from ._temporal import DEFAULT_SMOOTHNESS_CM2, TemporalNewton

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
    "DEFAULT_SMOOTHNESS_CM2",
    "FRAMES_PER_CALL",
    "METHODS",
    "ORDERS",
    "AbstractInverseMethod",
    "Cetinaslan",
    "Constrained",
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
    "TemporalNewton",
    "both_active",
    "from_audio2face_config",
    "left_right_pairs",
    "pair_indices",
    "prepare",
    "retarget",
    "roughness",
    "solve",
    "solve_sequence",
    "summarize",
]

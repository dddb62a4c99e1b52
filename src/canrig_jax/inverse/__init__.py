"""Inverse rig (Racković et al. 2023): weights from a mesh, one call shape for all methods.

    problem = inverse.prepare(rig)
    sol = inverse.solve(problem, target, inverse.QuarticCD(alpha=0.5))
    sol.weights, sol.objective, sol.history, sol.result, sol.stats

Every method is an ``AbstractInverseMethod`` (``METHODS`` lists the classes):
``QuarticCD``, ``LinearCD`` (coordinate descent, ``AbstractCoordinateDescent``), ``Seol``,
``Joshi``, ``Cetinaslan``, ``LMMM``, ``JaxoptLBFGSB``. Coordinate orders in ``ORDERS``;
whole takes with ``solve_sequence``; live capture with ``Stream``; metrics in
``inverse.metrics``; the NumPy reference of Algorithm 1 in ``inverse.reference``.
"""

from .base import AbstractInverseMethod, Iterate
from .coordinate_descent import (
    ORDERS,
    AbstractCoordinateDescent,
    LinearCD,
    QuarticCD,
    Seol,
    objective,
    static_order,
)
from .jaxopt_solver import JaxoptLBFGSB
from .least_squares import Cetinaslan, Joshi
from .lmmm import LMMM
from .problem import InverseProblem, prepare
from .solution import Solution
from .solve import Stream, solve, solve_sequence

METHODS = (QuarticCD, LinearCD, Seol, Joshi, Cetinaslan, LMMM, JaxoptLBFGSB)
"""Every inverse-rig method class (each a final ``AbstractInverseMethod``)."""

__all__ = [
    "METHODS",
    "ORDERS",
    "AbstractCoordinateDescent",
    "AbstractInverseMethod",
    "Cetinaslan",
    "InverseProblem",
    "Iterate",
    "JaxoptLBFGSB",
    "Joshi",
    "LMMM",
    "LinearCD",
    "QuarticCD",
    "Seol",
    "Solution",
    "Stream",
    "objective",
    "prepare",
    "solve",
    "solve_sequence",
    "static_order",
]

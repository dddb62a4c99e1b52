"""Inverse rig (Racković et al. 2023): weights from a mesh, one call shape for all methods.

    problem = inverse.prepare(rig)
    sol = inverse.solve(problem, target, inverse.QuarticCD(alpha=0.5, passes=5))
    sol.weights, sol.objective, sol.history, sol.result

Methods: ``QuarticCD``, ``LinearCD``, ``Seol``, ``Joshi``, ``Cetinaslan``, ``LMMM``,
``JaxoptLBFGSB``; coordinate orders in ``ORDERS``; metrics in ``inverse.metrics``.
"""

from .coordinate_descent import ORDERS, LinearCD, QuarticCD, Seol, objective, static_order
from .jaxopt_solver import JaxoptLBFGSB
from .least_squares import Cetinaslan, Joshi
from .lmmm import LMMM
from .problem import InverseProblem, prepare
from .solution import Solution
from .solve import solve, solve_sequence

__all__ = [
    "ORDERS",
    "Cetinaslan",
    "InverseProblem",
    "JaxoptLBFGSB",
    "Joshi",
    "LMMM",
    "LinearCD",
    "QuarticCD",
    "Seol",
    "Solution",
    "objective",
    "prepare",
    "solve",
    "solve_sequence",
    "static_order",
]

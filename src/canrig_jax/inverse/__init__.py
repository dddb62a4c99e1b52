"""Inverse rig (Racković et al. 2023): weights from a mesh, one call shape for all methods.

    problem = inverse.prepare(rig)
    sol = inverse.solve(problem, target, inverse.QuarticCD(alpha=0.5, passes=5))
    sol.weights, sol.objective, sol.history, sol.result

Work in progress (issue 3): LMMM, the jaxopt bounded solver, the correlation and greedy
coordinate orders, metrics and the paper's experiment are not written yet.
"""

from .coordinate_descent import LinearCD, QuarticCD, Seol, objective
from .least_squares import Cetinaslan, Joshi
from .problem import InverseProblem, prepare
from .solution import Solution
from .solve import ORDERS, coordinate_order, solve, solve_sequence

__all__ = [
    "ORDERS",
    "Cetinaslan",
    "InverseProblem",
    "Joshi",
    "LinearCD",
    "QuarticCD",
    "Seol",
    "Solution",
    "coordinate_order",
    "objective",
    "prepare",
    "solve",
    "solve_sequence",
]

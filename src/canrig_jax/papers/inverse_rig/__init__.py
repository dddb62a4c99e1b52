"""The inverse-rig evaluation (Racković et al. 2023; ``experiments/inverse_rig*.py``): the
alpha rule (``select_alpha``: the largest L1 weight within 5 % of the best training error),
the sparsity protocol (``alpha_sweep``, ``sparsest_alpha_within``, ``sparsity_verdict`` on
``noisy_meshes``), the NumPy reference of Algorithm 1 (``numpy_quartic_cd``, ``NumpyDenseRig``)
and of the authors' holistic solver (``numpy_holistic_cd``, ``holistic_lambdas``), the float64
minimum every method is measured against (``minimum``), and the timing harnesses
(``time_batched``, ``time_single_frames``, ``time_against_projection``,
``measure_reference``).
"""

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
from ._temporal_reference import holistic_lambdas, numpy_holistic_cd

__all__ = [
    "SPARSITY_TARGET",
    "NumpyDenseRig",
    "alpha_sweep",
    "decreasing_norm_order",
    "holistic_lambdas",
    "measure_reference",
    "minimum",
    "noisy_meshes",
    "numpy_holistic_cd",
    "numpy_quartic_cd",
    "select_alpha",
    "sparsest_alpha_within",
    "sparsity_verdict",
    "time_against_projection",
    "time_batched",
    "time_single_frames",
]

"""The WPSE evaluation (Seol et al.; ``experiments/wpse.py``, ``experiments/wpse_timing.py``):
edits sculpted at the worst frames of a take (``select_edit_frames``), every other frame held
out, each method's error against the wanted mesh (``compare_methods``), few edits
(``few_edit_errors``), temporal smoothness, reuse by search, the probes of Figures 7, 9 and 10
(``locality_probe``, ``overshoot_sweep``, ``layering_probe``, ``search_by_region``), Table 1's
timings (``time_edit_model``, against the NumPy reference ``NumpyEditEvaluator``) and the
results table (``results_table``).
"""

from ._probes import layering_probe, locality_probe, overshoot_sweep, search_by_region
from ._protocol import retained_fraction, select_edit_frames
from ._protocols import (
    FEW_EDIT_VARIANTS,
    SWEEP_FACTORS,
    VARIANTS,
    MethodComparison,
    apply_frames,
    channel_region,
    compare_methods,
    error_summary,
    few_edit_errors,
    rest_pose_correction_mm,
    reuse_by_search,
    temporal_smoothness,
)
from ._reference import (
    NumpyEditEvaluator,
    reference_coefficients,
    reference_correction,
    reference_frames,
    reference_vertex_frames,
    time_runtime,
)
from ._report import results_table
from ._timing import time_edit_model

__all__ = [
    "FEW_EDIT_VARIANTS",
    "SWEEP_FACTORS",
    "VARIANTS",
    "MethodComparison",
    "NumpyEditEvaluator",
    "apply_frames",
    "channel_region",
    "compare_methods",
    "error_summary",
    "few_edit_errors",
    "layering_probe",
    "locality_probe",
    "overshoot_sweep",
    "reference_coefficients",
    "reference_correction",
    "reference_frames",
    "reference_vertex_frames",
    "rest_pose_correction_mm",
    "results_table",
    "retained_fraction",
    "reuse_by_search",
    "search_by_region",
    "select_edit_frames",
    "temporal_smoothness",
    "time_edit_model",
    "time_runtime",
]

"""Weighted pose space editing (Seol et al.), plain PSE, search, layering and the FSM baseline.

```python
from canrig_jax import wpse
data = wpse.prepare_edits(rig, poses, edits)          # (P, K) poses, (P, V, 3) sculpted offsets
fit = wpse.fit_width(data)                             # one-standard-error LOO width (few edits)
model = wpse.fit_prepared(data, fit.sigma)             # or wpse.fit_pose_space_edit(..., sigma=)
mesh = wpse.apply(model, w, evaluate(rig, w))          # jit / vmap over frames
```
"""

from ._frames import (
    LocalFrames,
    frame_matrices,
    local_frames,
    local_to_world,
    to_local,
    to_world,
)
from ._fsm import coactivation_pairs, fix_shape_rig
from ._layers import LayeredEdits, apply_layered, assign_layers, fit_layered
from ._metric import (
    blendshape_metric,
    dot_width,
    euclidean_metric,
    gaussian_kernel,
    pairwise_pose_distance_sq,
    pose_distance_sq,
)
from ._probes import layering_probe, locality_probe, overshoot_sweep, search_by_region
from ._protocol import retained_fraction, select_edit_frames, temporal_change
from ._protocols import (
    MethodComparison,
    apply_frames,
    channel_region,
    compare_methods,
    error_summary,
    few_edit_errors,
    reuse_by_search,
    temporal_smoothness,
)
from ._pse import (
    DUPLICATE_DISTANCE,
    EditData,
    PoseSpaceEdit,
    apply,
    basis_matrices,
    correction,
    duplicate_groups,
    edited_mesh,
    fit_pose_space_edit,
    fit_prepared,
    prepare_edits,
    solve_coefficients,
)
from ._reference import (
    NumpyEditEvaluator,
    reference_coefficients,
    reference_frames,
    reference_vertex_frames,
    time_runtime,
)
from ._report import results_table
from ._reuse import ReuseResult, reuse_edits
from ._search import SearchResult, region_energy, search_edits
from ._sigma import (
    GUI_MIN,
    GUI_OFFSET,
    GUI_SCALE,
    SigmaFit,
    fit_sigma,
    gui_from_sigma,
    loo_error,
    loo_residuals,
    sigma_from_gui,
)
from ._timing import time_edit_model
from ._width import WidthFit, default_width_grid, fit_width, loo_distance_per_edit

__all__ = [
    "NumpyEditEvaluator",
    "reference_coefficients",
    "reference_frames",
    "reference_vertex_frames",
    "time_runtime",
    "DUPLICATE_DISTANCE",
    "GUI_MIN",
    "GUI_OFFSET",
    "GUI_SCALE",
    "EditData",
    "LayeredEdits",
    "LocalFrames",
    "PoseSpaceEdit",
    "ReuseResult",
    "SearchResult",
    "SigmaFit",
    "WidthFit",
    "apply",
    "apply_layered",
    "assign_layers",
    "basis_matrices",
    "blendshape_metric",
    "coactivation_pairs",
    "correction",
    "duplicate_groups",
    "edited_mesh",
    "euclidean_metric",
    "fit_layered",
    "fit_pose_space_edit",
    "fit_prepared",
    "fit_sigma",
    "fit_width",
    "default_width_grid",
    "loo_distance_per_edit",
    "fix_shape_rig",
    "frame_matrices",
    "gaussian_kernel",
    "gui_from_sigma",
    "local_frames",
    "local_to_world",
    "loo_error",
    "loo_residuals",
    "dot_width",
    "pairwise_pose_distance_sq",
    "pose_distance_sq",
    "prepare_edits",
    "region_energy",
    "retained_fraction",
    "reuse_edits",
    "search_edits",
    "select_edit_frames",
    "temporal_change",
    "sigma_from_gui",
    "solve_coefficients",
    "to_local",
    "to_world",
    # the experiment's protocols (experiments/wpse.py, experiments/wpse_timing.py)
    "MethodComparison",
    "apply_frames",
    "channel_region",
    "compare_methods",
    "error_summary",
    "few_edit_errors",
    "layering_probe",
    "locality_probe",
    "overshoot_sweep",
    "results_table",
    "reuse_by_search",
    "search_by_region",
    "temporal_smoothness",
    "time_edit_model",
]

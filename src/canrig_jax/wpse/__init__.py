"""Weighted pose space editing (Seol et al.), plain PSE, search, layering and the FSM baseline.

```python
from canrig_jax import wpse
data = wpse.prepare_edits(rig, poses, edits)          # (P, K) poses, (P, V, 3) sculpted offsets
fit = wpse.fit_width(data)                             # one-standard-error LOO width (few edits)
model = wpse.fit_prepared(data, fit.sigma)             # or wpse.fit_pose_space_edit(..., sigma=)
mesh = wpse.apply(model, w, evaluate(rig, w))          # jit / vmap over frames
```

The paper's evaluation (held-out frames, probes, Table 1's timings) is
``canrig_jax.papers.wpse``.
"""

from ._fsm import coactivation_pairs, fix_shape_rig
from ._layers import apply_layered, fit_layered
from ._metric import blendshape_metric
from ._pse import PoseSpaceEdit, apply, fit_pose_space_edit, fit_prepared, prepare_edits
from ._reuse import reuse_edits
from ._search import search_edits
from ._sigma import fit_sigma, sigma_from_gui
from ._temporal import temporal_change
from ._width import fit_width

__all__ = [
    "PoseSpaceEdit",
    "apply",
    "apply_layered",
    "blendshape_metric",
    "coactivation_pairs",
    "fit_layered",
    "fit_pose_space_edit",
    "fit_prepared",
    "fit_sigma",
    "fit_width",
    "fix_shape_rig",
    "prepare_edits",
    "reuse_edits",
    "search_edits",
    "sigma_from_gui",
    "temporal_change",
]

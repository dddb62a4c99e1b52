"""The alpha rule of the inverse-rig evaluation (``papers.inverse_rig.select_alpha``) on
hand-made sweeps."""

from __future__ import annotations

import pytest

from canrig_jax.papers.inverse_rig import select_alpha


def test_select_alpha_takes_the_sparsest_row_within_tolerance_of_the_best():
    rows = [
        {"alpha": 0.0, "rmse_mean_mm": 0.40},
        {"alpha": 1.0, "rmse_mean_mm": 0.38},
        {"alpha": 2.0, "rmse_mean_mm": 0.395},
        {"alpha": 5.0, "rmse_mean_mm": 0.41},
    ]
    assert select_alpha(rows)["alpha"] == 2.0  # 0.395 <= 1.05 * 0.38, 0.41 is not
    assert select_alpha(rows, tolerance=0.0)["alpha"] == 1.0
    with pytest.raises(ValueError, match="sweep"):
        select_alpha([])
    failed = [*rows, {"alpha": 10.0, "rmse_mean_mm": float("nan")}]
    with pytest.raises(ValueError, match=r"'lmmm' at alpha \[10.0\]"):
        select_alpha(failed, method="lmmm")

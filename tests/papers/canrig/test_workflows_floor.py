"""The committed Table 4 results respect their floor: no result can beat the error at the
vertices that no handle reaches (``experiments/canrig_workflows_floor.py``)."""

from __future__ import annotations

import json
from itertools import pairwise
from pathlib import Path

import pytest

RESULTS = (
    Path(__file__).parents[3] / "experiments" / "results" / "canrig_workflows" / "results.json"
)


def test_every_committed_result_lies_above_its_floor():
    results = json.loads(RESULTS.read_text())
    if "a_to_b_floor" not in results:
        pytest.fail("results.json has no a_to_b_floor: run canrig_workflows_floor.py")
    floor = results["a_to_b_floor"]["random_vertices"]
    table = results["a_to_b"]["random_vertices"]
    assert floor.keys() == table.keys()
    for handles, row in floor.items():
        for radius, cell in row.items():
            result = table[handles][radius]
            assert (
                0.0
                <= cell["floor_mm"]
                <= result["fitted_mm"]
                <= result["direct_on_fitted_pairs_mm"]
            )
            assert cell["floor_mm"] <= result["direct_mm"]
            assert 0.0 <= cell["unreached_percent"] <= 100.0
        # a wider radius never leaves more vertices unreached (radii are small to large)
        assert all(
            a["floor_mm"] >= b["floor_mm"] and a["unreached_percent"] >= b["unreached_percent"]
            for a, b in pairwise(row.values())
        )

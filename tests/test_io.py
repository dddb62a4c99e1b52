"""Atomic writes: an interrupted save leaves the previous file, and files get the usual modes."""

import json
import os
import stat

import pytest

from canrig_jax._io import atomic_path, save_json, save_text


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_an_interrupted_save_keeps_the_previous_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "results.json"
    save_json(path, {"a": 1})
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_text("half a file")
        raise RuntimeError("interrupted")
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]


def test_new_files_get_the_mode_of_a_plain_open_and_replacements_keep_theirs(tmp_path):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")  # what open() gives under the current umask
    atomic = save_text(tmp_path / "atomic.txt", "x")
    assert _mode(atomic) == _mode(plain)  # not mkstemp's 0o600
    os.chmod(atomic, 0o640)
    save_text(atomic, "y")
    assert _mode(atomic) == 0o640 and atomic.read_text() == "y"


def test_sibling_scripts_share_one_results_file(tmp_path):
    """A script that owns results.json/table.md (``save_results``) and siblings that add keys
    and table sections (``update_results``) never erase each other's outputs, whatever the
    order they run in."""
    from canrig_jax._io import save_results, table_sections, update_results

    update_results(tmp_path, "temporal", {"rmse": 1.0}, table="## Temporal\n| a |\n")
    save_results(tmp_path, {"cases": {"x": 1}, "timing": {"batched": 2.0}}, "# Main\n| m |\n")
    update_results(tmp_path, "timing", {"projection_ms": 1.5}, merge=True, table="## Floor\n")
    update_results(tmp_path, "temporal", {"rmse": 0.5}, table="## Temporal v2\n")
    save_results(tmp_path, {"cases": {"x": 2}, "timing": {"batched": 3.0}}, "# Main 2\n")

    results = json.loads((tmp_path / "results.json").read_text())
    assert results["cases"] == {"x": 2}
    assert results["temporal"] == {"rmse": 0.5}
    assert results["timing"] == {"batched": 3.0, "projection_ms": 1.5}
    text = (tmp_path / "table.md").read_text()
    assert text.startswith("# Main 2\n")
    assert table_sections(text) == {"temporal": "## Temporal v2\n", "timing": "## Floor\n"}
    assert text.count("## Temporal") == 1 and "# Main\n" not in text

"""Experiment provenance: one command file convention, and results.json records where it
came from (command, git commit, package versions)."""

from __future__ import annotations

import importlib.metadata
import shlex
import subprocess
from pathlib import Path

import pytest

from canrig_jax._provenance import COMMAND_FILE, experiment_command, provenance

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
SCRIPTS = sorted(p.name for p in (ROOT / "experiments").glob("*.py"))
PENDING: set[str] = set()
"""Scripts whose owners adopt ``provenance`` in their own change (see issue 21)."""


def test_provenance_records_the_checkout_and_versions():
    command = experiment_command(ROOT / "experiments" / "wpse.py", ["--out", "a b", "--quick"])
    assert shlex.split(command) == ["python", "experiments/wpse.py", "--out", "a b", "--quick"]
    record = provenance(command)
    head = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()
    assert record["command"] == command
    assert record["git_commit"] == head
    assert record["versions"]["jax"] == importlib.metadata.version("jax")
    assert record["versions"]["equinox"] == importlib.metadata.version("equinox")
    with pytest.raises(ValueError, match="^command:"):
        provenance("")


@pytest.mark.parametrize(
    "folder", sorted(p.name for p in RESULTS.iterdir() if (p / "results.json").exists())
)
def test_each_committed_result_has_one_command_file(folder):
    """One convention: ``COMMAND`` (no ``command.txt``), each command a script that exists."""
    path = RESULTS / folder
    assert not (path / "command.txt").exists()
    lines = [
        line
        for line in (path / COMMAND_FILE).read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    assert lines, f"{folder}/{COMMAND_FILE} holds no command"
    for line in lines:
        words = shlex.split(line)
        assert words[0] == "python" and (ROOT / words[1]).is_file(), line


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_results_writer_records_provenance(script):
    source = (ROOT / "experiments" / script).read_text()
    if "results.json" not in source and "train.json" not in source:
        pytest.skip("writes no results file")
    if script in PENDING and "provenance(" not in source:
        pytest.xfail("adopted by the script's owner (issue 21)")
    assert "provenance(" in source and "experiment_command(" in source


def test_record_command_keeps_what_the_command_file_already_holds(tmp_path):
    """A re-run appends its command instead of overwriting the log of earlier refreshes."""
    from canrig_jax._provenance import record_command

    first = "python experiments/x.py --out results/x"
    path = record_command(tmp_path, first)
    assert path.read_text() == first + "\n"
    (tmp_path / COMMAND_FILE).write_text(path.read_text() + "# refreshed by hand:\npython y.py\n")
    record_command(tmp_path, first)  # already there: nothing changes
    assert path.read_text().splitlines() == [first, "# refreshed by hand:", "python y.py"]
    record_command(tmp_path, "python z.py", note="a view")
    assert path.read_text().splitlines()[-2:] == ["# a view", "python z.py"]

"""Experiments only orchestrate: what a test exercises lives in the library, so no test imports
or loads a module from ``experiments/`` (reading the committed ``experiments/results/**`` files,
or running a script's command line in a slow end-to-end test, is not importing it)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent

LOADERS = {
    "spec_from_file_location",  # importlib.util
    "module_from_spec",
    "exec_module",
    "SourceFileLoader",  # importlib.machinery
    "load_source",  # imp
    "run_path",  # runpy
    "run_module",
}
"""Calls that load a module from a file path or run it in this process: a test has no use for
them but to reach into a script."""


def _strings(node: ast.AST) -> list[str]:
    return [
        n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)
    ]


def _name(func: ast.expr) -> str | None:
    if isinstance(func, ast.Attribute):
        return func.attr
    return func.id if isinstance(func, ast.Name) else None


def script_imports(source: str) -> list[str]:
    """Each way ``source`` imports or loads an experiment script, as 'line N: what'."""
    found = []
    for node in ast.walk(ast.parse(source)):
        line = getattr(node, "lineno", 0)
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""]
            found += [f"line {line}: import {a.name}" for a in node.names if a.name in LOADERS]
        elif isinstance(node, ast.Call):
            name = _name(node.func)
            if name in LOADERS:
                found.append(f"line {line}: {name}")
            elif name == "import_module" and any(
                s.split(".")[0] == "experiments" for s in _strings(node)
            ):
                found.append(f"line {line}: import_module of experiments")
            elif (
                name in ("insert", "append")
                and "path" in ast.unparse(node.func)
                and any("experiments" in s for s in _strings(node))
            ):
                found.append(f"line {line}: experiments/ on sys.path")
            continue
        else:
            continue
        found += [f"line {line}: import {n}" for n in names if n.split(".")[0] == "experiments"]
    return found


@pytest.mark.parametrize(
    "source, flagged",
    [
        ("import importlib.util\nspec = importlib.util.spec_from_file_location('x', P)\n", True),
        ("from importlib.util import spec_from_file_location as s\ns('x', P)\n", True),
        ("import runpy\nrunpy.run_path('experiments/wpse.py')\n", True),
        ("from experiments import wpse\n", True),
        ("import experiments.autorig\n", True),
        ("import importlib\nimportlib.import_module('experiments.wpse')\n", True),
        ("import sys\nsys.path.insert(0, str(ROOT / 'experiments'))\n", True),
        # reading a committed result is not importing a script
        ("import json\njson.loads(open('experiments/results/wpse/results.json').read())\n", False),
        ("from canrig_jax.papers.canrig import reach_floor\n", False),
    ],
)
def test_the_scan_finds_each_way_of_loading_a_script(source, flagged):
    """The scan is not vacuous: each pattern of loading a script is found, reading results is
    not."""
    assert bool(script_imports(source)) is flagged


def test_no_test_imports_an_experiment_script():
    files = sorted(TESTS.rglob("*.py"))
    assert len(files) > 50  # the scan sees the test tree
    offenders = {
        str(path.relative_to(TESTS)): found
        for path in files
        if path != Path(__file__).resolve()
        and (found := script_imports(path.read_text(encoding="utf-8")))
    }
    assert not offenders, (
        "tests import experiment scripts; move what they test into the library "
        f"(a protocol into canrig_jax.papers) and test it there: {offenders}"
    )

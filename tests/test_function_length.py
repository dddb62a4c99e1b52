"""No function in ``src/canrig_jax`` is longer than ``MAX_LINES`` (a reader should be able to
follow one in a screen or two: long ones are split into named steps)."""

from __future__ import annotations

import ast
from pathlib import Path

MAX_LINES = 100
SOURCE = Path(__file__).resolve().parents[1] / "src" / "canrig_jax"

# Functions still over the limit, as "package/module.py:Qualified.name". The list only
# shrinks: an entry whose function is now short enough fails the test until it is removed.
ALLOWED: frozenset[str] = frozenset()


def function_lengths(source: str, module: str) -> dict[str, int]:
    """{"module:Qualified.name": lines from ``def`` to the last line of the body} of every
    function, method and nested function in ``source`` (decorators not counted)."""
    lengths: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                lengths[f"{module}:{name}"] = child.end_lineno - child.lineno + 1
                visit(child, f"{name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return lengths


def _all_lengths() -> dict[str, int]:
    lengths: dict[str, int] = {}
    for path in sorted(SOURCE.rglob("*.py")):
        module = path.relative_to(SOURCE).as_posix()
        lengths.update(function_lengths(path.read_text(encoding="utf-8"), module))
    return lengths


def test_the_length_counts_every_function_from_def_to_its_last_line():
    source = (
        "def short():\n    return 1\n\n"
        "class A:\n    @staticmethod\n    def method():\n"
        "        def nested():\n            x = 1\n            return x\n"
        "        return nested\n"
    )
    assert function_lengths(source, "m.py") == {
        "m.py:short": 2,
        "m.py:A.method": 5,
        "m.py:A.method.nested": 3,
    }


def test_no_function_is_longer_than_the_limit():
    lengths = _all_lengths()
    assert len(lengths) > 500, "the source tree was not found"
    too_long = {
        name: n for name, n in sorted(lengths.items()) if n > MAX_LINES and name not in ALLOWED
    }
    assert not too_long, (
        f"functions over {MAX_LINES} lines (split them into named steps): {too_long}"
    )


def test_the_allow_list_only_names_functions_still_too_long():
    lengths = _all_lengths()
    stale = {name: lengths.get(name) for name in ALLOWED if lengths.get(name, 0) <= MAX_LINES}
    assert not stale, f"remove from ALLOWED (now short enough, or gone): {stale}"

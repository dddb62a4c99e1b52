"""Types are checked, not only declared.

Statically (ast): every public function and method in ``src/canrig_jax`` annotates its
parameters and return value, an array with its dtype and shape (jaxtyping's ``Float[Array,
"V 3"]``, never a bare ``np.ndarray``, ``jax.Array`` or ``ArrayLike``), and so do the array
fields of public classes; no module postpones its annotations (``from __future__ import
annotations``), which would hide them from the run-time check.

At run time: ``tests/conftest.py`` installs jaxtyping's import hook with beartype before
``canrig_jax`` is imported, so every call in the test run checks its arguments and return
value against these annotations (``CANRIG_TYPECHECK=0`` turns it off).
"""

import ast
import sys
from pathlib import Path

import jaxtyping
import numpy as np
import pytest

SOURCE = Path(__file__).resolve().parents[1] / "src" / "canrig_jax"

BARE_ARRAYS = frozenset({"ndarray", "Array", "ArrayLike", "NDArray"})
"""Array types that say nothing of dtype and shape unless a jaxtyping dtype wraps them."""

JAXTYPING_DTYPES = frozenset(
    {
        "Shaped",
        "Num",
        "Real",
        "Inexact",
        "Float",
        "Float16",
        "Float32",
        "Float64",
        "Complex",
        "Integer",
        "Int",
        "Int8",
        "Int16",
        "Int32",
        "Int64",
        "UInt",
        "UInt8",
        "UInt32",
        "Bool",
        "Key",
    }
)

# Modules not annotated yet, as paths under src/canrig_jax. The list only shrinks: a module
# that passes fails the test until its entry is removed.
ALLOWED: frozenset[str] = frozenset()


def _bare_arrays(annotation: ast.expr) -> list[str]:
    """The bare array types in ``annotation`` (quoted parts parsed too), outside any jaxtyping
    dtype subscript."""
    found: list[str] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Subscript):
            base = node.value
            name = base.attr if isinstance(base, ast.Attribute) else getattr(base, "id", None)
            if name in JAXTYPING_DTYPES:
                return
        if isinstance(node, ast.Attribute) and node.attr in BARE_ARRAYS:
            found.append(ast.unparse(node))
            return
        if isinstance(node, ast.Name) and node.id in BARE_ARRAYS:
            found.append(node.id)
            return
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            try:
                visit(ast.parse(node.value, mode="eval").body)
            except SyntaxError:  # a jaxtyping shape string ("V 3")
                pass
            return
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(annotation)
    return found


def _is_public(name: str) -> bool:
    return not name.startswith("_") or name in ("__init__", "__call__")


def _function_problems(function: ast.FunctionDef, method: bool) -> list[str]:
    arguments = function.args
    parameters = [*arguments.posonlyargs, *arguments.args, *arguments.kwonlyargs]
    static = any(ast.unparse(d) == "staticmethod" for d in function.decorator_list)
    if method and not static and parameters and parameters[0].arg in ("self", "cls"):
        parameters = parameters[1:]
    problems = []
    for parameter in parameters:
        if parameter.annotation is None:
            problems.append(f"{parameter.arg}: not annotated")
    for parameter in [*parameters, arguments.vararg, arguments.kwarg]:
        if parameter is not None and parameter.annotation is not None:
            for bare in _bare_arrays(parameter.annotation):
                problems.append(f"{parameter.arg}: {bare} without dtype and shape")
    if function.returns is None and function.name != "__init__":
        problems.append("return: not annotated")
    elif function.returns is not None:
        for bare in _bare_arrays(function.returns):
            problems.append(f"return: {bare} without dtype and shape")
    return problems


def annotation_problems(source: str) -> dict[str, list[str]]:
    """{qualified name: problems} of the public functions, methods and class fields in
    ``source``, plus ``"<module>"`` when it postpones its annotations."""
    tree = ast.parse(source)
    found: dict[str, list[str]] = {}

    def add(name: str, problems: list[str]) -> None:
        if problems:
            found.setdefault(name, []).extend(problems)

    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module == "__future__":
            if any(alias.name == "annotations" for alias in node.names):
                add("<module>", ["from __future__ import annotations"])
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and _is_public(node.name):
            add(node.name, _function_problems(node, method=False))
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for member in node.body:
                if isinstance(member, ast.FunctionDef | ast.AsyncFunctionDef):
                    if _is_public(member.name):
                        add(f"{node.name}.{member.name}", _function_problems(member, True))
                elif isinstance(member, ast.AnnAssign) and isinstance(member.target, ast.Name):
                    bare = _bare_arrays(member.annotation)
                    add(
                        f"{node.name}.{member.target.id}",
                        [f"field: {b} without dtype and shape" for b in bare],
                    )
    return found


def _all_problems() -> dict[str, dict[str, list[str]]]:
    problems = {}
    for path in sorted(SOURCE.rglob("*.py")):
        module = path.relative_to(SOURCE).as_posix()
        found = annotation_problems(path.read_text(encoding="utf-8"))
        if found:
            problems[module] = found
    return problems


def test_the_check_finds_each_kind_of_missing_annotation():
    source = (
        "from __future__ import annotations\n"
        "def bare(x: np.ndarray) -> Float[Array, 'V 3']: ...\n"
        "def unannotated(x, *args, **kwargs): ...\n"
        "def quoted(x: 'jax.Array | None') -> tuple[Float[np.ndarray, 'V'], ArrayLike]: ...\n"
        "def good(x: Float[ArrayLike, 'V 3'], n: int = 0) -> Int[np.ndarray, ' V']: ...\n"
        "def _private(x): ...\n"
        "class Fields:\n"
        "    rotation: np.ndarray\n"
        "    scale: float\n"
        "    shaped: Float[np.ndarray, '3 3'] | None\n"
        "    def __init__(self, x: Float[Array, 'n']): ...\n"
        "    def method(self, y) -> None: ...\n"
        "    @staticmethod\n"
        "    def static(self: int) -> None: ...\n"
    )
    assert annotation_problems(source) == {
        "<module>": ["from __future__ import annotations"],
        "bare": ["x: np.ndarray without dtype and shape"],
        "unannotated": ["x: not annotated", "return: not annotated"],
        "quoted": [
            "x: jax.Array without dtype and shape",
            "return: ArrayLike without dtype and shape",
        ],
        "Fields.rotation": ["field: np.ndarray without dtype and shape"],
        "Fields.method": ["y: not annotated"],
    }


def test_every_public_array_is_annotated_with_dtype_and_shape():
    problems = _all_problems()
    assert len(list(SOURCE.rglob("*.py"))) > 100, "the source tree was not found"
    missing = {module: found for module, found in problems.items() if module not in ALLOWED}
    assert not missing, f"annotate these (jaxtyping dtype and shape for arrays): {missing}"


def test_the_allow_list_only_names_modules_still_unannotated():
    problems = _all_problems()
    stale = sorted(module for module in ALLOWED if module not in problems)
    assert not stale, f"remove from ALLOWED (annotated now, or gone): {stale}"


def _hook_installed() -> bool:
    return any(type(finder).__name__ == "_JaxtypingFinder" for finder in sys.meta_path)


@pytest.mark.skipif(not _hook_installed(), reason="the run-time check is off: CANRIG_TYPECHECK=0")
def test_the_test_run_checks_shapes_and_dtypes_at_run_time():
    """A call that contradicts the annotations fails in the test run: shapes that disagree
    on a shared axis, a wrong dtype, a dataclass field of the wrong shape; the same values in
    agreement pass."""
    from canrig_jax._metrics import per_vertex_distance
    from canrig_jax.data._head_file import HeadMesh
    from canrig_jax.mesh import mesh_edges

    a = np.zeros((4, 3))
    np.testing.assert_array_equal(per_vertex_distance(a, a + [0.0, 3.0, 4.0]), np.full(4, 5.0))
    with pytest.raises(jaxtyping.TypeCheckError, match="per_vertex_distance"):
        per_vertex_distance(a, np.zeros((5, 3)))  # the same "*batch" axes in both
    with pytest.raises(jaxtyping.TypeCheckError, match="faces"):
        mesh_edges(np.zeros((2, 3)))  # float faces: Int[ArrayLike, "F 3"]
    faces = np.array([[0, 1, 2]], np.int32)
    with pytest.raises(jaxtyping.TypeCheckError, match="vertices"):
        HeadMesh(np.zeros((3, 2), np.float32), faces, "cm", False, Path("head.obj"))

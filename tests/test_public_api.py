"""The public API is deliberate: every exported name is in a committed list.

``tests/public_api.txt`` holds the toolkit, one line per public name: ``canrig_jax.NAME`` for
the top level, ``canrig_jax.SUB.NAME`` for each subpackage's ``__all__`` (``watchdog``, a
module without ``__all__``: the public names it defines). ``tests/papers_api.txt`` holds the
papers' protocols apart (``canrig_jax.papers.PAPER.NAME``), which the experiments import and
the toolkit never does. Adding, renaming or removing a public name is a change of one of those
files in the same commit; regenerate them with

    python tests/test_public_api.py > tests/public_api.txt
    python tests/test_public_api.py --papers > tests/papers_api.txt

and review the diff (and add a CHANGELOG line for a rename or a removal).
"""

from __future__ import annotations

import ast
import importlib
import importlib.metadata
import inspect
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LISTING = Path(__file__).with_name("public_api.txt")
PAPERS_LISTING = Path(__file__).with_name("papers_api.txt")
SUBPACKAGES = (
    "autorig",
    "canrig",
    "data",
    "distributed",
    "inverse",
    "mesh",
    "pbs",
    "render",
    "rig",
    "viewer",
    "watchdog",
    "wpse",
)
PAPERS_SOURCE = ROOT / "src" / "canrig_jax" / "papers"


def paper_modules() -> list[str]:
    """The public modules of ``canrig_jax.papers``: one subpackage per paper and its modules
    without a leading underscore (``canrig.workflows``), as dotted paths below ``papers``."""
    found = []
    for path in sorted(PAPERS_SOURCE.rglob("*.py")):
        parts = path.relative_to(PAPERS_SOURCE).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if parts and not any(part.startswith("_") for part in parts):
            found.append(".".join(parts))
    return found


def exported(module) -> list[str]:
    """A module's public names: its ``__all__``, else the public names it defines itself."""
    names = getattr(module, "__all__", None)
    if names is not None:
        return list(names)
    return [
        name
        for name, value in vars(module).items()
        if not name.startswith("_")
        and (
            getattr(value, "__module__", None) == module.__name__
            or (not inspect.ismodule(value) and name.isupper())
        )
    ]


def public_api() -> list[str]:
    """Every public name, one ``canrig_jax[.SUB].NAME`` per entry, sorted."""
    import canrig_jax

    lines = [f"canrig_jax.{n}" for n in canrig_jax.__all__]
    for sub in SUBPACKAGES:
        module = importlib.import_module(f"canrig_jax.{sub}")
        lines += [f"canrig_jax.{sub}.{n}" for n in exported(module)]
    return sorted(lines)


def papers_api() -> list[str]:
    """Every name of the papers' protocols, one ``canrig_jax.papers.PAPER.NAME`` per entry."""
    lines = []
    for paper in paper_modules():
        module = importlib.import_module(f"canrig_jax.papers.{paper}")
        lines += [f"canrig_jax.papers.{paper}.{n}" for n in module.__all__]
    return sorted(lines)


def _committed(listing: Path) -> list[str]:
    return [line for line in listing.read_text().splitlines() if line and not line.startswith("#")]


@pytest.mark.parametrize(
    "listing, current, flag",
    [(LISTING, public_api, ""), (PAPERS_LISTING, papers_api, " --papers")],
    ids=["toolkit", "papers"],
)
def test_public_api_matches_the_committed_list(listing, current, flag):
    committed = _committed(listing)
    current = current()
    added = sorted(set(current) - set(committed))
    removed = sorted(set(committed) - set(current))
    assert not added and not removed, (
        f"public API changed: added {added}, removed {removed}; if deliberate, regenerate "
        f"tests/{listing.name} (python tests/test_public_api.py{flag} > tests/{listing.name})"
    )
    assert len(current) == len(set(current)), "a name is listed twice in one __all__"


@pytest.mark.parametrize("paper", paper_modules())
def test_every_paper_module_says_what_it_exports(paper):
    module = importlib.import_module(f"canrig_jax.papers.{paper}")
    names = getattr(module, "__all__", None)
    assert names is not None, f"canrig_jax.papers.{paper} has no __all__"
    missing = [n for n in names if not hasattr(module, n)]
    assert not missing, f"canrig_jax.papers.{paper}.__all__ names missing attributes: {missing}"


def test_the_toolkit_never_imports_the_papers():
    """Layers are one-way: ``canrig_jax.papers`` imports the toolkit, never the reverse."""
    source = ROOT / "src" / "canrig_jax"
    found = []
    for path in sorted(source.rglob("*.py")):
        if path.is_relative_to(source / "papers"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                parts = [*(node.module or "").split(".")] + [a.name for a in node.names]
            elif isinstance(node, ast.Import):
                parts = [p for a in node.names for p in a.name.split(".")]
            else:
                continue
            if "papers" in parts:
                found.append(f"{path.relative_to(source)}:{node.lineno}")
    assert not found, f"the toolkit imports canrig_jax.papers: {found}"


@pytest.mark.parametrize("sub", SUBPACKAGES)
def test_every_exported_name_exists(sub):
    module = importlib.import_module(f"canrig_jax.{sub}")
    missing = [n for n in exported(module) if not hasattr(module, n)]
    assert not missing, f"canrig_jax.{sub}.__all__ names missing attributes: {missing}"


def test_no_name_means_two_things():
    """A name exported by two subpackages (or a subpackage and the top level) is the same
    object in both: ``canrig.load_model`` and ``autorig.load_model`` returning different
    things under one name is what this forbids."""
    import canrig_jax

    where: dict[str, list[tuple[str, object]]] = {}
    for n in canrig_jax.__all__:
        if n not in SUBPACKAGES:
            where.setdefault(n, []).append(("canrig_jax", getattr(canrig_jax, n)))
    for sub in SUBPACKAGES:
        module = importlib.import_module(f"canrig_jax.{sub}")
        for n in exported(module):
            where.setdefault(n, []).append((f"canrig_jax.{sub}", getattr(module, n)))
    clashes = {
        n: [m for m, _ in owners]
        for n, owners in where.items()
        if len({id(obj) for _, obj in owners}) > 1
    }
    assert not clashes, f"one name, different objects: {clashes}"


def test_top_level_is_the_subpackages_and_a_few_names():
    import canrig_jax

    for sub in SUBPACKAGES:
        assert getattr(canrig_jax, sub) is importlib.import_module(f"canrig_jax.{sub}")
        assert sub in canrig_jax.__all__ and sub in dir(canrig_jax)
    assert issubclass(canrig_jax.CanrigWarning, UserWarning)
    with pytest.raises(AttributeError, match="atomic_path"):
        canrig_jax.atomic_path  # noqa: B018  (plumbing lives in canrig_jax._io)


def test_version_is_the_distribution_version():
    import canrig_jax

    pyproject = (ROOT / "pyproject.toml").read_text()
    declared = re.search(r'^version\s*=\s*"([^"]+)"', pyproject, re.M).group(1)
    assert canrig_jax.__version__ == importlib.metadata.version("canrig_jax") == declared


def test_importing_the_package_loads_no_subpackage_and_no_jax():
    """``import canrig_jax`` is cheap: the subpackages (and JAX) load on first use."""
    code = (
        "import sys, canrig_jax\n"
        "print(sorted(m for m in sys.modules if m == 'jax' or m.startswith('canrig_jax.')))\n"
        "canrig_jax.rig\n"
        "print('jax' in sys.modules)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    before, after = result.stdout.splitlines()
    assert before == "['canrig_jax._io', 'canrig_jax._warnings']", before
    assert after == "True"


if __name__ == "__main__":
    if sys.argv[1:] == ["--papers"]:
        print("# The papers' protocols, canrig_jax.papers (tests/test_public_api.py); regenerate")
        print("#   python tests/test_public_api.py --papers > tests/papers_api.txt")
        print("\n".join(papers_api()))
    else:
        print("# The public API of canrig_jax (tests/test_public_api.py); regenerate with")
        print("#   python tests/test_public_api.py > tests/public_api.txt")
        print("\n".join(public_api()))

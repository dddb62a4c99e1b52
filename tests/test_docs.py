"""The documentation: no issue-tracker references in README.md or docs/, and (``-m slow``) the
site builds with ``mkdocs build --strict`` and renders in headless Chromium.

The build needs the ``docs`` extra (``pip install -e .[docs]``; ``nox -s docs``) and the
screenshot a headless Chromium (``chromium-headless-shell`` or ``chromium``, as
``tests/viewer`` uses); each test skips, saying so, without them.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
ISSUE = re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE)
"""A reference to the project's issue tracker ("issue 19", "issues 3, 22", "Issue #4")."""
SEED_PAGES = ("inverse-rig", "wpse", "canrig", "riganyface")
API_PAGES = ("rig", "mesh", "inverse", "wpse", "canrig", "pbs", "autorig", "data", "render")
API_PAGES += ("viewer", "watchdog", "distributed")
PAPER_PAGES = ("inverse_rig", "wpse", "canrig", "riganyface")
"""The reference pages of ``canrig_jax.papers``, apart from the toolkit's."""


def issue_references(text: str) -> list[str]:
    return [m.group(0) for m in ISSUE.finditer(text)]


def test_issue_pattern_finds_references_and_nothing_else():
    text = "Fixed in issue 19; see issues 3, 22 and Issue #4. Known issues: none."
    assert issue_references(text) == ["issue 19", "issues 3", "Issue #4"]


def test_readme_and_docs_have_no_issue_numbers():
    sources = [ROOT / "README.md", ROOT / "mkdocs.yml"]
    sources += sorted(p for p in DOCS.rglob("*") if p.suffix in {".md", ".py", ".yml"})
    found = {
        p.relative_to(ROOT).as_posix(): refs
        for p in sources
        if (refs := issue_references(p.read_text(encoding="utf-8")))
    }
    assert not found, f"issue-tracker references in the documentation: {found}"


def _chromium() -> str | None:
    from canrig_jax.viewer import find_chromium

    return find_chromium()


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site built by ``mkdocs build --strict`` into a temporary folder."""
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed: pip install -e .[docs] (nox -s docs does)")
    out = tmp_path_factory.mktemp("site")
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        env=dict(os.environ, NO_MKDOCS_2_WARNING="1"),
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, f"mkdocs build --strict failed:\n{done.stderr[-6000:]}"
    return out


@pytest.mark.slow
def test_site_has_every_page_and_no_issue_numbers(site):
    for name in SEED_PAGES:
        page = (site / "results" / name / "index.html").read_text(encoding="utf-8")
        text = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", page))  # highlighting splits code
        assert "<table>" in page and "python experiments/" in text, name
    for name in API_PAGES:
        page = (site / "reference" / name / "index.html").read_text(encoding="utf-8")
        assert f'id="canrig_jax.{name}.' in page, f"API page of canrig_jax.{name} lists nothing"
    for name in PAPER_PAGES:
        page = (site / "reference" / "papers" / name / "index.html").read_text(encoding="utf-8")
        assert f'id="canrig_jax.papers.{name}.' in page, f"canrig_jax.papers.{name} lists nothing"
    assert (site / "tour" / "index.html").is_file()
    figures = list((site / "results" / "figures").rglob("*.png"))
    assert figures, "no result figures were copied into the site"
    pages = [p for p in site.rglob("*.html")]
    found = {
        p.relative_to(site).as_posix(): refs[:3]
        for p in pages
        if (refs := issue_references(re.sub(r"<[^>]+>", " ", p.read_text(encoding="utf-8"))))
    }
    assert not found, f"issue-tracker references in the built site: {found}"


@pytest.mark.slow
def test_cli_page_documents_every_subcommand_and_option(site):
    """The generated CLI page holds every subcommand and option of the parser itself."""
    from canrig_jax._commands import build_parser

    page = (site / "cli" / "index.html").read_text(encoding="utf-8")
    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert subparsers.choices
    for name, sub in subparsers.choices.items():
        assert f"canrig {name}" in page, name
        for action in sub._actions:
            for option in action.option_strings:
                assert option in page, f"canrig {name} {option}"


@pytest.mark.slow
def test_index_renders_in_headless_chromium(site, tmp_path):
    executable = _chromium()
    if executable is None:
        pytest.skip("no headless Chromium: apt-get install chromium-headless-shell")
    index = (site / "index.html").as_uri()
    common = [executable, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars"]
    dom = subprocess.run(
        [*common, "--dump-dom", index], capture_output=True, text=True, timeout=120
    ).stdout
    assert "<title>canrig_jax</title>" in dom
    assert "Quartic inverse rig" in dom and "RigAnyFace" in dom  # the page's own table
    shot = tmp_path / "index.png"
    subprocess.run(
        [*common, f"--screenshot={shot}", "--window-size=1024,768", index],
        capture_output=True,
        timeout=120,
    )
    from PIL import Image  # a dependency of matplotlib

    pixels = np.asarray(Image.open(shot).convert("RGB"))
    assert pixels.shape[:2] == (768, 1024)
    colours = np.unique(pixels.reshape(-1, 3), axis=0)
    assert len(colours) > 200, f"only {len(colours)} colours: the page did not render"
    header = pixels[:40].reshape(-1, 3).mean(axis=0)  # material's indigo header bar
    assert header[2] > header[0] + 40, f"no coloured header bar (mean RGB {header})"

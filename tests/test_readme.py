"""Every Python block of README.md, and of every page of docs/, runs as written, in order, in
one fresh process per file.

The blocks are concatenated into one script whose line numbers are the file's own (every
line outside a ```python block is blank, and each block's opening fence becomes a marker
print), so a traceback points at the file's line, and the last marker names the block.
Docs pages whose blocks train, build whole-head operators or compile large programs run
under ``-m slow`` (``SLOW_PAGES``); the others run by default.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
MARKER = "@@README-BLOCK"

SLOW_PAGES = {
    "getting-started.md": "builds or reads the ict-quartic rig; compiles its batched evaluation",
    "guides/inverse-rig.md": "compiles every inverse-rig path on the 180-frame take",
    "guides/wpse.md": "the nonlinear blend, a width fit, the fix-shape rig",
    "guides/canrig.md": "trains a CANRig network; fitted workflows",
    "guides/pbs.md": "whole-head patch layout and graphs",
    "guides/avatars.md": "rigs a whole-body Rocketbox avatar",
    "guides/rig-checks.md": "checks two rigs under the take",
    "guides/autorig.md": "remeshed ICT identities, RigAnyFace, landmark fitting",
    "guides/rendering.md": "compiles the soft and fast rasterisers and a gradient",
    "guides/mesh.md": "whole-head operators and a DiffusionNet",
    "guides/rig.md": "corrective synthesis through the nonlinear blend (about 10 s)",
}
"""Docs pages (relative to docs/) whose blocks run under ``-m slow``, and why."""


@dataclass(frozen=True)
class Block:
    heading: str  # the nearest heading above the block
    start: int  # 1-based README line of the opening fence
    source: str


def python_blocks(text: str) -> list[Block]:
    """The ```python blocks of a Markdown text, in order, each with its heading."""
    blocks, heading, fence, body, start = [], "(top of README)", None, [], 0
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if fence is None:
            if stripped.startswith("```"):
                fence, body, start = stripped[3:].strip().lower(), [], number
            elif re.match(r"#{1,6} ", line):
                heading = line.lstrip("#").strip()
        elif stripped.startswith("```"):
            if fence == "python":
                blocks.append(Block(heading, start, "\n".join(body)))
            fence = None
        else:
            body.append(line)
    if fence is not None:
        raise ValueError(f"README.md: code block opened at line {start} is never closed")
    return blocks


def readme_script(text: str, blocks: list[Block]) -> str:
    """One script of all blocks, each at its README line numbers, a marker on each fence."""
    lines = [""] * len(text.splitlines())
    for i, block in enumerate(blocks):
        lines[block.start - 1] = f"print({f'{MARKER} {i}'!r}, flush=True)"
        for offset, line in enumerate(block.source.splitlines(), start=1):
            lines[block.start - 1 + offset] = line
    return "\n".join(lines) + "\n"


def run_blocks(text: str, blocks: list[Block], folder: Path, timeout: float):
    """The blocks of ``text`` run as one script (``readme_script``) in a fresh process from
    the project root; the finished process."""
    script = folder / "blocks.py"
    script.write_text(readme_script(text, blocks))
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONUNBUFFERED="1")
    return subprocess.run(
        [sys.executable, str(script)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_python_blocks_are_found_with_their_headings():
    text = "# A\n```python\nx = 1\n```\n## B\n```bash\nls\n```\n```python\ny = x\n```\n"
    blocks = python_blocks(text)
    assert [(b.heading, b.start, b.source) for b in blocks] == [
        ("A", 2, "x = 1"),
        ("B", 9, "y = x"),
    ]
    script = readme_script(text, blocks).splitlines()
    assert script[2] == "x = 1" and script[9] == "y = x" and script[5] == ""
    with pytest.raises(ValueError, match="never closed"):
        python_blocks("```python\nx = 1\n")


def fail_unless_ran(name: str, blocks: list[Block], done) -> None:
    """Fail naming the block of ``name`` that raised (from the last marker printed)."""
    if done.returncode == 0:
        return
    reached = [int(m) for m in re.findall(rf"^{MARKER} (\d+)$", done.stdout, flags=re.M)]
    if not reached:
        where = "before the first block"
    else:
        block = blocks[reached[-1]]
        where = f"block {reached[-1] + 1} of {len(blocks)}, under '{block.heading}'"
        where += f" ({name} line {block.start})"
    pytest.fail(
        f"{name} python {where} failed (traceback line numbers are {name} lines):\n"
        f"{done.stderr[-6000:]}",
        pytrace=False,
    )


def docs_pages_with_python() -> list[str]:
    """Markdown pages under docs/ (relative paths) that hold at least one ```python block."""
    pages = sorted(p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md"))
    return [p for p in pages if python_blocks((DOCS / p).read_text())]


def _page_param(page: str):
    marks = (pytest.mark.slow,) if page in SLOW_PAGES else ()
    return pytest.param(page, marks=marks, id=page)


@pytest.mark.slow
def test_readme_python_blocks_run_in_order_in_a_fresh_process(tmp_path):
    text = README.read_text()
    blocks = python_blocks(text)
    assert blocks, "README.md has no ```python blocks"
    fail_unless_ran("README.md", blocks, run_blocks(text, blocks, tmp_path, timeout=3600))


@pytest.mark.parametrize("page", [_page_param(p) for p in docs_pages_with_python()])
def test_docs_python_blocks_run(page, tmp_path):
    """Each docs page's python blocks run as written, in order, in one fresh process."""
    text = (DOCS / page).read_text()
    blocks = python_blocks(text)
    fail_unless_ran(f"docs/{page}", blocks, run_blocks(text, blocks, tmp_path, timeout=1200))


def test_slow_pages_are_docs_pages_with_python_blocks():
    """A page renamed or emptied must leave SLOW_PAGES too (else its marker protects nothing)."""
    stale = sorted(set(SLOW_PAGES) - set(docs_pages_with_python()))
    assert not stale, f"SLOW_PAGES names pages without python blocks under docs/: {stale}"

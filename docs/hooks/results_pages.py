"""mkdocs hook: one "Reproducing the paper" page per system, generated at build time.

Each page is made from the committed experiment outputs under ``experiments/results/``: for
every folder of the system, its ``table.md`` (headings shifted under the folder's heading), the
exact commands of its ``COMMAND`` file (the command lines, without the file's comments) and its
small PNG figures, copied into the built site. Nothing is copied by hand, so a re-run of an
experiment updates its page at the next build.
"""

from __future__ import annotations

import fnmatch
import functools
import importlib.util
import re
import runpy
import sys
import types
from dataclasses import dataclass
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "experiments" / "results"
NOXFILE = ROOT / "noxfile.py"
PAGE_DIR = "results"
SMALL_FIGURE_BYTES = 500_000
"""PNG figures up to this size are copied into the site; larger ones are named, not shown."""
LARGE_OUTPUT_BYTES = 1_000_000
"""Outputs above this size (checkpoints, glTF files) are not kept in the repository."""


@dataclass(frozen=True)
class Seed:
    slug: str
    title: str
    patterns: tuple[str, ...]  # folder names or globs, in page order
    intro: str
    guide: str  # the guide page of the system, relative to docs/
    protocols: str = ""  # the reference page of its canrig_jax.papers module, if any


SEEDS = (
    Seed(
        "inverse-rig",
        "Quartic inverse rig (Racković et al. 2023)",
        ("build_quartic_rig", "inverse_rig"),
        "The ict-quartic rig (the ICT face with synthesised pair, triplet and quadruplet "
        "correctives), then every inverse-rig method on two heads driven by the Live Link take "
        "with noise: ict-quartic and the MakeHuman head (evaluation only). The weight of the L1 "
        "term is chosen per method on training poses only. Errors in mm against the clean mesh.",
        "guides/inverse-rig.md",
        "reference/papers/inverse_rig.md",
    ),
    Seed(
        "wpse",
        "Weighted pose space editing (Seol et al.)",
        ("wpse",),
        "PSE, WPSE and the fix-shape baseline on the linear ICT face rig, with the "
        "deformation-gradient blend as the sculpt: edits at the worst frames of the Live Link "
        "capture and random poses, scored on held-out frames (mm).",
        "guides/wpse.md",
        "reference/papers/wpse.md",
    ),
    Seed(
        "canrig",
        "CANRig (Mohammadi, Weiss et al.)",
        (
            "canrig",
            "canrig_workflows",
            "canrig_workflows*",
            "canrig_pbs_attached_local_prior",
            "canrig_pbs",
            "canrig_pbs*",
        ),
        "The masked cross-attention rig trained on ict-quartic shapes (`canrig`), its workflows "
        "(pose A to B, layers, clip editing, dialogue replacement) with the network and with "
        "the rig that has no network (`canrig_workflows_local_fit`), and patch blendshapes "
        "with CANRig-PBS on the whole head. `canrig_pbs_attached_local_prior` is the "
        "recommended whole-head configuration; the other `canrig_pbs*` folders are the "
        "paper's model and named variants.",
        "guides/canrig.md",
        "reference/papers/canrig.md",
    ),
    Seed(
        "riganyface",
        "RigAnyFace (Ma et al.)",
        ("any_head*", "autorig_half_balanced_long", "autorig", "autorig*", "mesh_foundations"),
        "RigAnyFace trained on ICT identities and evaluated on held-out identities at a "
        "resolution never trained on and on the MakeHuman head (evaluation only), against no "
        "motion and deformation transfer. `autorig_half_balanced_long` holds the default model "
        "(`canrig_jax.autorig.DEFAULT_CHECKPOINT`); `autorig` the standard run with the DT + "
        "residual models; the other `autorig*` folders are ablations and variants; "
        "`mesh_foundations` checks the geometry the network stands on. `any_head`, where "
        "present, compares the methods of `auto_rig` on heads from other sources.",
        "guides/autorig.md",
        "reference/papers/riganyface.md",
    ),
    Seed(
        "distributed",
        "Several processes (jax.distributed)",
        ("distributed",),
        "The inverse rig over the Live Link take, CANRig training steps and the auto-rig of two "
        "heads, run as one process and as two local processes on this project's 2-core "
        "machine, each result compared with one process's.",
        "guides/distributed.md",
    ),
)

_ISSUE = re.compile(r"\s*\((?:issues?|Issues?) \d+(?:\s*(?:,|and)\s*\d+)*\)|\b[Ii]ssues? \d+:\s*")


def clean(text: str) -> str:
    """``text`` without references to the project's issue tracker."""
    return _ISSUE.sub("", text)


def folders(seed: Seed) -> list[Path]:
    """The result folders of a seed, each once, in the order of its patterns."""
    present = sorted(p.name for p in RESULTS.iterdir() if p.is_dir()) if RESULTS.is_dir() else []
    chosen: list[str] = []
    for pattern in seed.patterns:
        for name in present:
            if fnmatch.fnmatchcase(name, pattern) and name not in chosen:
                chosen.append(name)
    return [RESULTS / name for name in chosen]


def commands(folder: Path) -> list[str]:
    """The command lines of a folder's ``COMMAND`` file (comments and blank lines dropped)."""
    path = folder / "COMMAND"
    if not path.is_file():
        return []
    lines = []
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if stripped and not stripped.startswith("#") and stripped not in lines:
            lines.append(stripped)
    return lines


def makes_large_outputs(folder: Path) -> bool:
    """Whether a folder's runs write checkpoints or glTF files (on disk or named in COMMAND)."""
    if any(folder.rglob("*.eqx")) or any(folder.rglob("*.glb")):
        return True
    command = folder / "COMMAND"
    text = command.read_text() if command.is_file() else ""
    return bool(re.search(r"\.eqx|\.glb|checkpoint|view_error\.py|--train|_train\.py", text))


@functools.cache
def _standard_experiments() -> tuple:
    """``STANDARD_EXPERIMENTS`` of noxfile.py ((script, *arguments) per run), read by running
    the noxfile with a stand-in for ``nox`` when nox is not installed; () if it has none."""
    if not NOXFILE.is_file():
        return ()
    saved = sys.modules.get("nox")
    if importlib.util.find_spec("nox") is None:
        stub = types.ModuleType("nox")
        stub.session = lambda *a, **k: a[0] if a and callable(a[0]) else (lambda f: f)
        stub.options = types.SimpleNamespace()
        sys.modules["nox"] = stub
    try:
        namespace = runpy.run_path(str(NOXFILE))
    finally:
        if saved is None:
            sys.modules.pop("nox", None)
        else:
            sys.modules["nox"] = saved
    return tuple(namespace.get("STANDARD_EXPERIMENTS", ()))


def standard_scripts(folder: Path) -> list[str]:
    """Experiment scripts that ``nox -s experiments`` runs into this folder."""
    target = f"experiments/results/{folder.name}"
    scripts = []
    for script, *arguments in _standard_experiments():
        if any(a == target or a.startswith(target + "/") for a in map(str, arguments)):
            if script not in scripts:
                scripts.append(script)
    return scripts


def _demote(markdown: str, top: int) -> str:
    """Headings of an included table shifted so that its highest becomes level ``top``
    (at most h6; the order of levels is kept), and a blank line before each list."""
    out, fence, levels = [], False, []
    for line in markdown.splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
        match = None if fence else re.match(r"^(#{1,6}) ", line)
        levels.append(len(match.group(1)) if match else 0)
    shift = top - min((n for n in levels if n), default=top)
    previous, fence = "", False
    for line, level in zip(markdown.splitlines(), levels, strict=True):
        if line.lstrip().startswith("```"):
            fence = not fence
        if level:
            line = "#" * min(6, level + shift) + line[level:]
        list_start = not fence and _starts_list(line)
        if list_start and previous.strip() and not _starts_list(previous):
            out.append("")  # Markdown starts a list only after a blank line
        out.append(line)
        previous = line
    return "\n".join(out)


def _starts_list(line: str) -> bool:
    return bool(re.match(r"\s*(?:[-*+]|\d+\.) ", line))


def figures(folder: Path) -> tuple[list[Path], list[Path]]:
    """(small, large) PNG figures at the top of a results folder."""
    pngs = sorted(folder.glob("*.png"))
    small = [p for p in pngs if p.stat().st_size <= SMALL_FIGURE_BYTES]
    return small, [p for p in pngs if p not in small]


def figure_uri(folder: Path, png: Path) -> str:
    return f"{PAGE_DIR}/figures/{folder.name}/{png.name}"


def folder_section(folder: Path) -> str:
    rel = folder.relative_to(ROOT).as_posix()
    parts = [f"## `{folder.name}`\n", f"Outputs: `{rel}/`.\n"]
    table = folder / "table.md"
    if table.is_file():
        parts.append(_demote(clean(table.read_text()).strip(), 3) + "\n")
    else:
        parts.append("This folder holds no `table.md`.\n")
    lines = commands(folder)
    if lines:
        parts.append("Made by (from the project root; the commands of `COMMAND`):\n")
        parts.append("```bash\n" + "\n".join(lines) + "\n```\n")
    if makes_large_outputs(folder):
        text = (
            f"Checkpoints and glTF files over {LARGE_OUTPUT_BYTES // 1_000_000} MB are not kept "
            "in the repository: the commands above regenerate them"
        )
        scripts = standard_scripts(folder)
        if scripts:
            text += (
                "; `python3 -m nox -s experiments -- "
                + " ".join(scripts)
                + "` runs this folder's standard configuration (with the other standard "
                "configurations of "
                + ("that script" if len(scripts) == 1 else "those scripts")
                + ")"
            )
        parts.append(text + ".\n")
    small, large = figures(folder)
    for png in small:
        caption = png.stem.replace("_", " ")
        parts.append(f"![{caption}](figures/{folder.name}/{png.name})\n")
    if large:
        names = ", ".join(f"`{rel}/{p.name}`" for p in large)
        parts.append(f"Larger figures, in the repository: {names}.\n")
    return "\n".join(parts)


def seed_page(seed: Seed) -> str:
    parts = [
        f"# Reproducing the paper: {seed.title}\n",
        seed.intro + "\n",
        f"How to use the system: [the guide](../{seed.guide}). This page is generated when the "
        "site is built, from each folder's `table.md`, `COMMAND` and figures.\n",
    ]
    if seed.protocols:
        module = Path(seed.protocols).stem
        parts.append(
            f"The evaluation's protocols: [`canrig_jax.papers.{module}`](../{seed.protocols}).\n"
        )
    found = folders(seed)
    if not found:
        parts.append("No results are committed for this system.\n")
    for folder in found:
        parts.append(folder_section(folder))
    return "\n".join(parts)


def on_files(files, config):
    for seed in SEEDS:
        files.append(File.generated(config, f"{PAGE_DIR}/{seed.slug}.md", content=seed_page(seed)))
        for folder in folders(seed):
            for png in figures(folder)[0]:
                files.append(File.generated(config, figure_uri(folder, png), abs_src_path=str(png)))
    return files

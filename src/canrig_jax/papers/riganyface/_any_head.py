"""The any-head experiment's protocols (``experiments/any_head*.py``): heads sculpted by other
people with their artist's ARKit shapes, ``auto_rig``'s methods scored against those shapes
with k example shapes given (few-shot style), a fit on the face crop, every axis-aligned
orientation of a head, the command line's end-to-end time, and the rule that picks the default
method from the validation rows.

Heads are as stored: +y up, facing +z, centimetres; errors in millimetres on the skin (the
largest component).
"""

import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
from jaxtyping import ArrayLike, Float, Int

from ...autorig._any_head import auto_rig
from ...autorig._data import AutorigDataset, ict_autorig_dataset
from ...autorig._evaluation import sculpted_target_errors, shared_shape_matrix
from ...autorig._landmarks import place_landmarks
from ...autorig._methods import AUTO_RIG_METHODS, DEFAULT_METHOD, Template, Transfer
from ...autorig._orientation import OrientationError, axis_rotations, decide_orientation
from ...autorig._rocketbox import SculptedHead
from ...data import ARKIT_NAMES, save_obj
from ...rig import BlendshapeRig
from ...watchdog import progress as tick
from ._crops import face_crop

EXAMPLE_ORDER = ("jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "browInnerUp", "mouthFunnel")
"""The order in which few-shot examples are asked for (and measured): the largest motions of
the jaw, the mouth corners, the lids, the brows and the lips."""
FEW_SHOT_KS = (0, 1, 3, 5)
"""How many example shapes (``EXAMPLE_ORDER``'s first k) the few-shot protocol gives."""

Log = Callable[[str], None]


def ict_sculpted_heads(n: int, data_dir: str | os.PathLike | None = None) -> list[SculptedHead]:
    """The first ``n`` held-out ICT identities at the unseen resolution
    (``ict_autorig_dataset``'s test heads), their 53 ICT shapes as 51 ARKit ones (the halves
    summed, ``shared_shape_matrix``); named ``ict_<head name>``."""
    dataset = ict_autorig_dataset(data_dir, n_train=1, n_test=n, progress=False)
    basis = list(dataset.poses.basis_names)
    target = list(ARKIT_NAMES)
    index, matrix = shared_shape_matrix(basis, target)
    heads = []
    for head in dataset.test["unseen_topology"]:
        singles = head.displacements[: len(basis)]
        deltas = np.einsum("sk,kvc->svc", matrix, singles)
        names = [target[i] for i in index]
        heads.append(SculptedHead(f"ict_{head.name}", head.vertices, head.faces, deltas, names))
    return heads


def sculpted_head_errors(rig: BlendshapeRig, head: SculptedHead, names: Sequence[str]) -> dict:
    """Skin errors (mm) of ``rig``'s shapes ``names`` against the head's artist's
    (``sculpted_target_errors``): skin MAE and q95, active MAE, median amplitude ratio."""
    rig_names = list(rig.names)
    predicted = np.stack([np.asarray(rig.deltas[rig_names.index(n)]) for n in names])
    found = sculpted_target_errors(predicted, head.shapes(names), head.skin)
    return {
        "skin_mae_mm": found["skin_mae_mm"],
        "skin_q95_mm": found["skin_q95_mm"],
        "active_mae_mm": found["active_mae_mm"],
        "amplitude_median": found["amplitude_ratio_median"],
    }


def _no_motion_errors(head: SculptedHead, names: Sequence[str]) -> dict:
    """``sculpted_head_errors`` of a rig that does not move (the reference to beat)."""
    zero = BlendshapeRig(head.vertices, np.zeros_like(head.shapes(names)), (), tuple(names))
    return sculpted_head_errors(zero, head, names)


def _mean_rows(rows: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """The mean of each key over ``rows`` (dicts with the first row's keys)."""
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def few_shot_rows(
    head: SculptedHead, dataset: AutorigDataset, log: Log = print
) -> tuple[dict, dict, dict]:
    """Every ``auto_rig`` method on ``head`` with k = each of ``FEW_SHOT_KS`` example shapes
    given (the first k of ``EXAMPLE_ORDER``, never chosen by error), each scored on the shapes
    not given beside no motion on the same shapes, under the method's name; the orientation
    and landmarks of a first ``Transfer()`` call are shared by all.

    Returns (row -> errors at k = 0 on every scored shape, ``"no_motion"`` first; method ->
    str(k) -> errors with their ``"no_motion"``, ``"style"`` and ``"seconds"``; the landmark
    fit {"ok", "by", "rms_cm"})."""
    first = auto_rig(head.vertices, head.faces, method=Transfer(), dataset=dataset)
    scored = [n for n in head.names if n in first.rig.names]
    methods = {"no_motion": _no_motion_errors(head, scored)}
    few: dict = {}
    for method_class in AUTO_RIG_METHODS:
        method = method_class.name
        few[method] = {}
        for k in FEW_SHOT_KS:
            given = list(EXAMPLE_ORDER[:k])
            rest = [n for n in scored if n not in given]
            examples = {n: head.shapes([n])[0] for n in given} or None
            t = time.perf_counter()
            result = auto_rig(
                head.vertices,
                head.faces,
                method=method_class(),
                examples=examples,
                dataset=dataset,
                orientation=first.orientation,
                landmarks=first.landmarks,
            )
            row = sculpted_head_errors(result.rig, head, rest)
            row["no_motion"] = _no_motion_errors(head, rest)
            row["style"] = dataclasses.asdict(result.style)
            row["seconds"] = time.perf_counter() - t
            few[method][str(k)] = row
            tick(f"{head.name} {method} k={k}")
            log(
                f"{head.name:34s} {method:18s} k={k}: skin {row['skin_mae_mm']:.3f} "
                f"(none {row['no_motion']['skin_mae_mm']:.3f}) active "
                f"{row['active_mae_mm']:.2f} (none {row['no_motion']['active_mae_mm']:.2f})"
            )
            if k == 0:
                methods[method] = sculpted_head_errors(result.rig, head, scored)
    fit = {"ok": True, "by": first.fit["by"], "rms_cm": first.fit["rms_cm"]}
    return methods, few, fit


def face_crop_fit(head: SculptedHead, dataset: AutorigDataset) -> dict:
    """``place_landmarks`` on the head's face crop (``face_crop``): {"ok", "by", "rms_cm",
    "vertices"}, or {"ok": False, "error": its message, "vertices"} when it refuses."""
    vertices, faces = face_crop(head.vertices, head.faces)
    try:
        _, fit, by = place_landmarks(dataset, vertices, faces)
        return {"ok": True, "by": by, "rms_cm": float(fit.rms), "vertices": len(vertices)}
    except ValueError as error:
        return {"ok": False, "error": str(error)[:300], "vertices": len(vertices)}


def orientation_cases(
    heads: Mapping[str, tuple[Float[ArrayLike, "_V 3"], Int[np.ndarray, "_F 3"]]],
    dataset: AutorigDataset | None,
    log: Log = print,
) -> dict:
    """``decide_orientation`` on every axis-aligned rotation (``axis_rotations``) of each head
    (name -> (vertices, faces)) and of its mirror image (x flipped, triangles reversed): a
    case is recovered (the decision undoes the turn; a mirror image is recognised as one),
    refused (``OrientationError``) or silently wrong. ``dataset``: ``decide_orientation``'s
    (None: the packaged template).

    Returns {"per_head": name -> counts of "cases", "recovered", "refused",
    "silently_wrong"}, the same summed over heads, and "refused_fraction_full_heads" (heads
    whose name does not end in ``_face_crop``)."""
    mirror = np.diag([-1.0, 1.0, 1.0])
    out: dict = {"per_head": {}}
    for name, (vertices, faces) in heads.items():
        counts = {"cases": 0, "recovered": 0, "refused": 0, "silently_wrong": 0}
        for mirrored in (False, True):
            for rotation in axis_rotations():
                turn = rotation @ mirror if mirrored else rotation
                moved = np.asarray(vertices, np.float64) @ turn.T
                tris = faces[:, ::-1] if mirrored else faces
                expected = mirror if mirrored else np.eye(3)
                counts["cases"] += 1
                try:
                    decision = decide_orientation(dataset, moved, tris)
                except OrientationError:
                    counts["refused"] += 1
                    continue
                if np.allclose(decision.rotation @ turn, expected, atol=1e-6):
                    counts["recovered"] += 1
                else:
                    counts["silently_wrong"] += 1
        tick(f"orientation {name}")
        log(f"orientation {name:34s} {counts}")
        out["per_head"][name] = counts
    for key in ("cases", "recovered", "refused", "silently_wrong"):
        out[key] = sum(c[key] for c in out["per_head"].values())
    full = [c for n, c in out["per_head"].items() if not n.endswith("_face_crop")]
    out["refused_fraction_full_heads"] = sum(c["refused"] for c in full) / max(
        1, sum(c["cases"] for c in full)
    )
    return out


def _cli_seconds(head: SculptedHead, out_dir: Path, env: Mapping[str, str]) -> float:
    """``canrig autorig`` on the head written as an OBJ, end to end in a fresh process (s)."""
    obj = out_dir / f"{head.name.replace('/', '_')}.obj"
    save_obj(obj, head.vertices, head.faces)
    start = time.perf_counter()
    run = subprocess.run(
        [str(Path(sys.executable).with_name("canrig")), "autorig", str(obj), "--units", "cm"]
        + ["-o", str(obj.with_suffix(".glb")), "--quiet"],
        capture_output=True,
        text=True,
        env=dict(env),
        check=False,
    )
    if run.returncode != 0:
        raise RuntimeError(f"canrig autorig {obj}: {run.stderr[-2000:]}")
    return time.perf_counter() - start


def measure_cli_seconds(heads: Mapping[str, SculptedHead], log: Log = print) -> dict:
    """``canrig autorig`` (its default method) per head, in fresh processes: warm (the second
    of two runs), and on the ``"makehuman"`` head (which must be among ``heads``) once more
    with an empty model cache (``cold_cache_s``). Returns name -> {"vertices", "warm_s"} and
    "method": the default method."""
    if "makehuman" not in heads:
        raise ValueError("heads: expected a 'makehuman' head (the cold-cache run)")
    seconds: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, CANRIG_WATCHDOG="600")
        for name, head in heads.items():
            _cli_seconds(head, Path(tmp), env)  # warm the operating system's caches
            seconds[name] = {
                "vertices": len(head.vertices),
                "warm_s": _cli_seconds(head, Path(tmp), env),
            }
            log(f"canrig autorig {name}: {seconds[name]['warm_s']:.1f} s")
        cold = dict(env, CANRIG_CACHE=str(Path(tmp) / "empty_cache"))
        seconds["makehuman"]["cold_cache_s"] = _cli_seconds(heads["makehuman"], Path(tmp), cold)
    seconds["method"] = DEFAULT_METHOD.name
    return seconds


def choose_default_method(
    few: Mapping[str, Mapping],
    cases: Sequence[tuple[str, str]],
    tie: float,
    preference: Sequence[str],
) -> tuple[str, dict[str, float]]:
    """The default-method rule on validation rows: per method, the worst over ``cases``
    ((head, k) pairs of ``few``: head -> method -> str(k) -> errors) of max(skin MAE ratio,
    active MAE ratio) to no motion; the method with the smallest wins, and among those within
    ``tie`` (relative) of it the first in ``preference``. Returns (the method, method -> its
    worst ratio)."""
    worst = {}
    for method in (cls.name for cls in AUTO_RIG_METHODS):
        ratios = []
        for head, k in cases:
            row = few[head][method][k]
            ratios.append(
                max(
                    row["skin_mae_mm"] / row["no_motion"]["skin_mae_mm"],
                    row["active_mae_mm"] / row["no_motion"]["active_mae_mm"],
                )
            )
        worst[method] = float(max(ratios))
    best = min(worst.values())
    tied = [m for m in preference if worst[m] <= best * (1 + tie)]
    return tied[0], worst


def any_head_table(r: Mapping) -> str:
    """The markdown ``table.md`` of the any-head results.json: every method at k = 0, few-shot
    style, the template of the same style, orientation (when measured), landmark fits and the
    command line's end-to-end seconds."""
    lines = [
        "# Any head: generated ARKit shapes against the artist's (skin, mm)",
        "",
        f"Default method by the committed rule: **{r['default_method']}** (worst validation "
        "ratio to no motion per method: "
        + ", ".join(f"{m} {v:.3f}" for m, v in r["rule_worst_ratio"].items())
        + ").",
        "",
        "## Every method, no examples (k = 0)",
        "",
        "| head | method | skin MAE | skin q95 | active MAE | amplitude |",
        "|---|---|---|---|---|---|",
    ]
    for head, methods in r["heads"].items():
        for method, row in methods.items():
            lines.append(
                f"| {head} | {method} | {row['skin_mae_mm']:.3f} | {row['skin_q95_mm']:.3f} | "
                f"{row['active_mae_mm']:.3f} | {row['amplitude_median']:.2f} |"
            )
    lines += [
        "",
        "## Few-shot style: k of the artist's shapes given (jawOpen, mouthSmileLeft, "
        "eyeBlinkLeft, browInnerUp, mouthFunnel in that order), scored on the others",
        "",
        "| head | method | k | skin MAE | no motion | active MAE | no motion |",
        "|---|---|---|---|---|---|---|",
    ]
    for head, by_method in r["few_shot_by_method"].items():
        for method, by_k in by_method.items():
            for k, row in by_k.items():
                lines.append(
                    f"| {head} | {method} | {k} | {row['skin_mae_mm']:.3f} | "
                    f"{row['no_motion']['skin_mae_mm']:.3f} | {row['active_mae_mm']:.3f} | "
                    f"{row['no_motion']['active_mae_mm']:.3f} |"
                )
    lines += ["", "## Template of the same style (Rocketbox, leave one out)", ""]
    lines += ["| head | skin MAE | no motion | active MAE | no motion |", "|---|---|---|---|---|"]
    for head, row in r["template_loo"].items():
        lines.append(
            f"| {head} | {row['skin_mae_mm']:.3f} | {row['no_motion']['skin_mae_mm']:.3f} | "
            f"{row['active_mae_mm']:.3f} | {row['no_motion']['active_mae_mm']:.3f} |"
        )
    if "orientation" in r:
        o = r["orientation"]
        lines += [
            "",
            "## Orientation (24 rotations x mirror, heads and face crops)",
            "",
            f"{o['cases']} cases: {o['recovered']} recovered, {o['refused']} refused, "
            f"{o['silently_wrong']} silently wrong; refused on full heads "
            f"{100 * o['refused_fraction_full_heads']:.1f} %.",
            "",
            "| head | cases | recovered | refused | wrong |",
            "|---|---|---|---|---|",
        ]
        for head, c in o["per_head"].items():
            lines.append(
                f"| {head} | {c['cases']} | {c['recovered']} | {c['refused']} | "
                f"{c['silently_wrong']} |"
            )
    lines += ["", "## Landmark fit", "", "| head | ok | by | RMS (cm) |", "|---|---|---|---|"]
    for head, f in r["fit"].items():
        rms = f"{f['rms_cm']:.3f}" if f.get("ok") else f.get("error", "")[:80]
        lines.append(f"| {head} | {f['ok']} | {f.get('by', '')} | {rms} |")
    method = r["seconds"].get("method", "transfer")
    lines += ["", f"## canrig autorig end to end (--method {method}, the default; a fresh process)"]
    lines += ["", "| head | vertices | warm cache (s) |", "|---|---|---|"]
    for head, s in r["seconds"].items():
        if isinstance(s, dict):
            lines.append(f"| {head} | {s['vertices']} | {s['warm_s']:.1f} |")
    if "cold_cache_s" in r["seconds"].get("makehuman", {}):
        lines.append(
            f"\nCold (empty cache, MakeHuman): {r['seconds']['makehuman']['cold_cache_s']:.1f} s."
        )
    return "\n".join(lines) + "\n"


def template_row(
    target: SculptedHead, source: SculptedHead, dataset: AutorigDataset
) -> tuple[dict, BlendshapeRig]:
    """``source``'s artist's shapes (those ``target`` has too) carried onto ``target`` as a
    ``Template`` of the same style (``Transfer(template=)``), scored against ``target``'s own
    beside no motion. Returns (errors with their ``"no_motion"``, the generated rig)."""
    names = [n for n in source.names if n in target.names]
    rig = BlendshapeRig(source.vertices, source.shapes(names), (), names, source.faces)
    template = Template.from_rig(dataset, rig, source.name)
    result = auto_rig(target.vertices, target.faces, method=Transfer(template), dataset=dataset)
    scored = [n for n in target.names if n in result.rig.names]
    row = sculpted_head_errors(result.rig, target, scored)
    row["no_motion"] = _no_motion_errors(target, scored)
    return row, result.rig


def mean_few_shot(per_head: Sequence[tuple[dict, dict, dict]]) -> tuple[dict, dict]:
    """The mean over heads of ``few_shot_rows``' results: (row -> mean errors at k = 0,
    method -> str(k) -> mean errors with the mean ``"no_motion"``; the style and seconds are
    left out)."""
    methods = {m: _mean_rows([p[0][m] for p in per_head]) for m in per_head[0][0]}
    keys = list(per_head[0][0]["no_motion"])
    few = {
        method: {
            k: {
                **_mean_rows([{x: p[1][method][k][x] for x in keys} for p in per_head]),
                "no_motion": _mean_rows([p[1][method][k]["no_motion"] for p in per_head]),
            }
            for k in per_head[0][1][method]
        }
        for method in (cls.name for cls in AUTO_RIG_METHODS)
    }
    return methods, few

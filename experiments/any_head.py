"""Any head as a product: ``autorig.auto_rig``'s three methods on heads sculpted by other
people, few-shot style, a template of the same style, orientation and landmark fits.

    python experiments/any_head.py --out experiments/results/any_head

Heads (each as stored: +y up, facing +z, centimetres; ``auto_rig`` decides the orientation):
held-out ICT identities (``ict_autorig_dataset`` test heads, the unseen 1,300-vertex
remeshing; validation), the two Rocketbox heads (validation) and the MakeHuman head
(evaluation only: nothing is chosen on it). Every generated ARKit shape is compared with the
artist's (ICT's for ICT identities) by ``autorig.sculpted_target_errors`` on the skin (the
largest component), in mm.

Protocols:
- ``heads``: every method at k = 0 on all 52 shapes the truth has (tongueOut, which ICT
  lacks, is left out for every method alike), beside no motion.
- ``few_shot``: k = 0, 1, 3, 5 example shapes given in ``autorig.EXAMPLE_ORDER`` (never chosen
  by error), each k scored on the shapes not given, beside no motion on the same shapes.
- ``template_loo``: Rocketbox female carried onto the male with ``Template`` and vice versa.
- ``orientation``: the 24 axis-aligned rotations and their mirror images of an ICT head,
  MakeHuman, both Rocketbox heads and the face crops of each: recovered, refused or wrong.
- ``fit``: ``place_landmarks`` on each head and its face crop.
- ``seconds``: ``canrig autorig`` end to end (a fresh process) on each head as an OBJ.

The default method is chosen from the validation rows by the rule in ``COMMAND``, written
before this ran.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from canrig_jax._io import save_json, save_text  # noqa: E402
from canrig_jax._provenance import experiment_command, provenance, record_command  # noqa: E402
from canrig_jax.autorig import (  # noqa: E402
    AUTO_RIG_METHODS,
    DEFAULT_METHOD,
    EXAMPLE_ORDER,
    OrientationError,
    Template,
    auto_rig,
    axis_rotations,
    decide_orientation,
    face_crop,
    ict_autorig_dataset,
    load_makehuman,
    place_landmarks,
    sculpted_target_errors,
    shared_shape_matrix,
    skin_of,
)
from canrig_jax.data import ARKIT_NAMES, data_file, read_arrays, save_obj  # noqa: E402
from canrig_jax.rig import BlendshapeRig  # noqa: E402
from canrig_jax.watchdog import progress as tick  # noqa: E402
from canrig_jax.watchdog import run_watched  # noqa: E402

VALIDATION = ("ict_heldout", "rocketbox_female", "rocketbox_male")
RULE_CASES = (("ict_heldout", "0"), ("rocketbox_female", "3"), ("rocketbox_male", "3"))
TIE = 0.02
PREFERENCE = ("transfer", "transfer-residual", "raf")
KS = (0, 1, 3, 5)


class Head:
    """A head with its artist's ARKit shapes (cm, +y up, facing +z)."""

    def __init__(self, name, vertices, faces, deltas, names):
        self.name = name
        self.vertices = np.asarray(vertices, np.float32)
        self.faces = np.asarray(faces, np.int32)
        self.deltas = np.asarray(deltas, np.float32)
        self.names = [str(n) for n in names]
        self.skin = skin_of(self.vertices, self.faces)

    def shapes(self, names):
        return np.stack([self.deltas[self.names.index(n)] for n in names])


def rocketbox(data_dir, name) -> Head:
    path = data_file(f"rocketbox/{name}_head.npz", data_dir)
    z = read_arrays(path, ("neutral", "faces", "deltas", "names"))
    return Head(name, z["neutral"], z["faces"], z["deltas"], z["names"])


def ict_heads(data_dir, n: int) -> list[Head]:
    """Held-out ICT identities, their 53 ICT shapes as 51 ARKit shapes (halves summed)."""
    dataset = ict_autorig_dataset(data_dir, n_train=1, n_test=n, progress=False)
    basis = list(dataset.poses.basis_names)
    target = list(ARKIT_NAMES)
    index, matrix = shared_shape_matrix(basis, target)
    heads = []
    for head in dataset.test["unseen_topology"]:
        singles = head.displacements[: len(basis)]
        deltas = np.einsum("sk,kvc->svc", matrix, singles)
        names = [target[i] for i in index]
        heads.append(Head(f"ict_{head.name}", head.vertices, head.faces, deltas, names))
    return heads


def errors(rig, head: Head, names) -> dict:
    """Skin errors of a rig's shapes ``names`` against the head's (mm)."""
    rig_names = list(rig.names)
    predicted = np.stack([np.asarray(rig.deltas[rig_names.index(n)]) for n in names])
    found = sculpted_target_errors(predicted, head.shapes(names), head.skin)
    return {
        "skin_mae_mm": found["skin_mae_mm"],
        "skin_q95_mm": found["skin_q95_mm"],
        "active_mae_mm": found["active_mae_mm"],
        "amplitude_median": found["amplitude_ratio_median"],
    }


def no_motion(head: Head, names) -> dict:
    zero = BlendshapeRig(head.vertices, np.zeros_like(head.shapes(names)), (), names)
    return errors(zero, head, names)


def mean_rows(rows: list[dict]) -> dict:
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def run_head(head: Head, dataset, log) -> tuple[dict, dict, dict]:
    """(methods at k = 0, few-shot per method and k, fit) of one head."""
    first = auto_rig(head.vertices, head.faces, method="transfer", dataset=dataset)
    common = dict(dataset=dataset, orientation=first.orientation, landmarks=first.landmarks)
    scored = [n for n in head.names if n in first.rig.names]
    methods = {"no_motion": no_motion(head, scored)}
    few: dict = {}
    for method in AUTO_RIG_METHODS:
        few[method] = {}
        for k in KS:
            given = list(EXAMPLE_ORDER[:k])
            rest = [n for n in scored if n not in given]
            examples = {n: head.shapes([n])[0] for n in given} or None
            t = time.perf_counter()
            result = auto_rig(head.vertices, head.faces, method=method, examples=examples, **common)
            row = errors(result.rig, head, rest)
            row["no_motion"] = no_motion(head, rest)
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
                methods[method] = errors(result.rig, head, scored)
    fit = {"ok": True, "by": first.fit["by"], "rms_cm": first.fit["rms_cm"]}
    return methods, few, fit


def crop_fit(head: Head, dataset) -> dict:
    vertices, faces = face_crop(head.vertices, head.faces)
    try:
        _, fit, by = place_landmarks(dataset, vertices, faces)
        return {"ok": True, "by": by, "rms_cm": float(fit.rms), "vertices": len(vertices)}
    except ValueError as error:
        return {"ok": False, "error": str(error)[:300], "vertices": len(vertices)}


def orientation_cases(heads: dict, dataset, log) -> dict:
    """Every axis-aligned rotation and its mirror image of each head and its face crop."""
    mirror = np.diag([-1.0, 1.0, 1.0])
    out = {"per_head": {}}
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


def cli_seconds(head: Head, out_dir: Path, env: dict) -> float:
    """``canrig autorig`` end to end in a fresh process (seconds)."""
    obj = out_dir / f"{head.name.replace('/', '_')}.obj"
    save_obj(obj, head.vertices, head.faces)
    start = time.perf_counter()
    run = subprocess.run(
        [str(Path(sys.executable).with_name("canrig")), "autorig", str(obj), "--units", "cm"]
        + ["-o", str(obj.with_suffix(".glb")), "--quiet"],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    if run.returncode != 0:
        raise RuntimeError(f"canrig autorig {obj}: {run.stderr[-2000:]}")
    return time.perf_counter() - start


def measure_seconds(heads: dict, log) -> dict:
    """``canrig autorig`` (its default method) per head: warm (a second fresh process), and
    on MakeHuman once with an empty cache."""
    seconds = {}
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, CANRIG_WATCHDOG="600")
        for name, head in heads.items():
            cli_seconds(head, Path(tmp), env)  # warm the operating system's caches
            seconds[name] = {
                "vertices": len(head.vertices),
                "warm_s": cli_seconds(head, Path(tmp), env),
            }
            log(f"canrig autorig {name}: {seconds[name]['warm_s']:.1f} s")
        cold = dict(env, CANRIG_CACHE=str(Path(tmp) / "empty_cache"))
        seconds["makehuman"]["cold_cache_s"] = cli_seconds(heads["makehuman"], Path(tmp), cold)
    seconds["method"] = DEFAULT_METHOD
    return seconds


def choose_default(heads: dict, few: dict) -> tuple[str, dict]:
    """The rule in COMMAND, on the validation rows only."""
    worst = {}
    for method in AUTO_RIG_METHODS:
        ratios = []
        for head, k in RULE_CASES:
            row = few[head][method][k]
            ratios.append(
                max(
                    row["skin_mae_mm"] / row["no_motion"]["skin_mae_mm"],
                    row["active_mae_mm"] / row["no_motion"]["active_mae_mm"],
                )
            )
        worst[method] = float(max(ratios))
    best = min(worst.values())
    tied = [m for m in PREFERENCE if worst[m] <= best * (1 + TIE)]
    return tied[0], worst


def figure(path: Path, head: Head, rig, shapes=("jawOpen", "mouthSmileLeft", "browInnerUp")):
    """Generated vs artist displacement length on the skin, front view, per shape."""
    fig, axes = plt.subplots(2, len(shapes), figsize=(2.2 * len(shapes), 4.4))
    v = head.vertices
    names = list(rig.names)
    for j, shape in enumerate(shapes):
        truth = np.linalg.norm(head.shapes([shape])[0], axis=1)
        made = np.linalg.norm(np.asarray(rig.deltas[names.index(shape)]), axis=1)
        top = max(truth.max(), 1e-6)
        for i, (values, label) in enumerate(((made, "generated"), (truth, "artist"))):
            ax = axes[i, j]
            front = v[:, 2] > np.median(v[:, 2])
            ax.scatter(v[front, 0], v[front, 1], c=values[front], s=1.5, cmap="magma", vmin=0,
                       vmax=top)  # fmt: skip
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{shape}\n{label}" if i == 0 else label, fontsize=7)
    fig.suptitle(head.name, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="experiments/results/any_head")
    parser.add_argument("--data-dir")
    parser.add_argument("--ict-heads", type=int, default=3)
    parser.add_argument("--skip-orientation", action="store_true")
    parser.add_argument(
        "--seconds-only",
        action="store_true",
        help="re-measure only canrig autorig end to end (the library's default method now) "
        "and rewrite results.json and table.md",
    )
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    start = time.perf_counter()

    def log(message):
        print(f"[{time.perf_counter() - start:7.1f} s] {message}", flush=True)

    warnings.simplefilter("ignore")
    from canrig_jax.autorig import ict_pose_source

    dataset = ict_pose_source(args.data_dir, progress=False)
    if args.seconds_only:
        ict = ict_heads(args.data_dir, 1)
        mh = load_makehuman(args.data_dir)
        heads = {
            "ict_heldout": ict[0],
            "rocketbox_female": rocketbox(args.data_dir, "Female_Adult_01"),
            "rocketbox_male": rocketbox(args.data_dir, "Male_Adult_08"),
            "makehuman": Head("makehuman", mh.neutral, mh.faces, mh.deltas, mh.names),
        }
        results = json.loads((out / "results.json").read_text())
        results["seconds"] = measure_seconds(heads, log)
        results["library_default"] = DEFAULT_METHOD
        results["provenance_seconds"] = provenance(command)
        save_json(out / "results.json", results)
        save_text(out / "table.md", table(results))
        record_command(out, command, "re-measured the command's time with its new default")
        return
    ict = ict_heads(args.data_dir, args.ict_heads)
    mh = load_makehuman(args.data_dir)
    heads = {
        "rocketbox_female": rocketbox(args.data_dir, "Female_Adult_01"),
        "rocketbox_male": rocketbox(args.data_dir, "Male_Adult_08"),
        "makehuman": Head("makehuman", mh.neutral, mh.faces, mh.deltas, mh.names),
    }
    log(f"loaded {len(ict)} ICT held-out heads, Rocketbox, MakeHuman")

    results: dict = {"heads": {}, "few_shot_by_method": {}, "fit": {}}
    per_ict = []
    for head in ict:
        per_ict.append(run_head(head, dataset, log))
    results["heads"]["ict_heldout"] = {
        m: mean_rows([p[0][m] for p in per_ict]) for m in per_ict[0][0]
    }
    results["few_shot_by_method"]["ict_heldout"] = {
        method: {
            k: {
                **mean_rows([{x: p[1][method][k][x] for x in p[0]["no_motion"]} for p in per_ict]),
                "no_motion": mean_rows([p[1][method][k]["no_motion"] for p in per_ict]),
            }
            for k in per_ict[0][1][method]
        }
        for method in AUTO_RIG_METHODS
    }
    results["fit"]["ict_heldout"] = per_ict[0][2]
    results["fit"]["ict_heldout_face_crop"] = crop_fit(ict[0], dataset)
    for name, head in heads.items():
        methods, few, fit = run_head(head, dataset, log)
        results["heads"][name] = methods
        results["few_shot_by_method"][name] = few
        results["fit"][name] = fit
        results["fit"][f"{name}_face_crop"] = crop_fit(head, dataset)

    default, worst = choose_default(results["heads"], results["few_shot_by_method"])
    rule = (out / "COMMAND").read_text() if (out / "COMMAND").exists() else ""
    results["rule"] = "\n".join(
        line[2:] for line in rule.splitlines() if line.startswith("#   ") or "RULE" in line
    )
    results["default_method"] = default
    results["rule_worst_ratio"] = worst
    results["library_default"] = DEFAULT_METHOD
    for name in results["heads"]:
        results["heads"][name]["default"] = results["heads"][name][default]
    results["few_shot"] = {
        name: {
            k: {x: row[x] for x in ("skin_mae_mm", "active_mae_mm")}
            | {"no_motion_skin_mae_mm": row["no_motion"]["skin_mae_mm"]}
            | {"no_motion_active_mae_mm": row["no_motion"]["active_mae_mm"]}
            for k, row in by_method[default].items()
        }
        for name, by_method in results["few_shot_by_method"].items()
    }

    # template of the same style, leave one out
    results["template_loo"] = {}
    pairs = (("rocketbox_female", "rocketbox_male"), ("rocketbox_male", "rocketbox_female"))
    for target, source in pairs:
        src = heads[source]
        names = [n for n in src.names if n in heads[target].names]
        rig = BlendshapeRig(src.vertices, src.shapes(names), (), names, src.faces)
        template = Template.from_rig(dataset, rig, source)
        head = heads[target]
        result = auto_rig(head.vertices, head.faces, template=template, dataset=dataset)
        scored = [n for n in head.names if n in result.rig.names]
        row = errors(result.rig, head, scored)
        row["no_motion"] = no_motion(head, scored)
        results["template_loo"][target] = row
        log(f"template {source} -> {target}: {row['skin_mae_mm']:.3f} "
            f"(none {row['no_motion']['skin_mae_mm']:.3f})")  # fmt: skip
        figure(out / f"shapes_{target}_template.png", head, result.rig)

    # figures of the default at k = 0 and k = 3
    for name in ("rocketbox_female", "rocketbox_male", "makehuman"):
        head = heads[name]
        rig0 = auto_rig(head.vertices, head.faces, method=default, dataset=dataset).rig
        figure(out / f"shapes_{name}_k0.png", head, rig0)
        examples = {n: head.shapes([n])[0] for n in EXAMPLE_ORDER[:3]}
        rig3 = auto_rig(
            head.vertices, head.faces, method=default, dataset=dataset, examples=examples
        ).rig
        figure(out / f"shapes_{name}_k3.png", head, rig3, ("mouthFunnel", "browInnerUp",
               "mouthSmileRight"))  # fmt: skip

    if not args.skip_orientation:
        cases = {"ict_heldout": (ict[0].vertices, ict[0].faces)}
        cases.update({n: (h.vertices, h.faces) for n, h in heads.items()})
        cases.update({f"{n}_face_crop": face_crop(*c) for n, c in list(cases.items())})
        results["orientation"] = orientation_cases(cases, dataset, log)

    results["seconds"] = measure_seconds({"ict_heldout": ict[0], **heads}, log)

    results["provenance"] = provenance(command)
    results["total_s"] = time.perf_counter() - start
    save_json(out / "results.json", results)
    save_text(out / "table.md", table(results))
    record_command(out, command)
    log(f"default method by the rule: {default} (worst ratios {worst})")


def table(r: dict) -> str:
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


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)

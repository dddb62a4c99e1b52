"""Any head as a product: ``autorig.auto_rig``'s three methods on heads sculpted by other
people, few-shot style, a template of the same style, orientation and landmark fits.

    python experiments/any_head.py --out experiments/results/any_head

Heads (each as stored: +y up, facing +z, centimetres; ``auto_rig`` decides the orientation):
held-out ICT identities (``ict_autorig_dataset`` test heads, the unseen 1,300-vertex
remeshing; validation), the two Rocketbox heads (validation) and the MakeHuman head
(evaluation only: nothing is chosen on it). Every generated ARKit shape is compared with the
artist's (ICT's for ICT identities) by ``papers.riganyface.sculpted_head_errors`` on the skin
(the largest component), in mm.

Protocols:
- ``heads``: every method at k = 0 on all 52 shapes the truth has (tongueOut, which ICT
  lacks, is left out for every method alike), beside no motion.
- ``few_shot``: k = 0, 1, 3, 5 example shapes given in ``papers.riganyface.EXAMPLE_ORDER``
  (never chosen by error), each k scored on the shapes not given, beside no motion on the same
  shapes.
- ``template_loo``: Rocketbox female carried onto the male with ``Template`` and vice versa.
- ``orientation``: the 24 axis-aligned rotations and their mirror images of an ICT head,
  MakeHuman, both Rocketbox heads and the face crops of each: recovered, refused or wrong.
- ``fit``: ``place_landmarks`` on each head and its face crop.
- ``seconds``: ``canrig autorig`` end to end (a fresh process) on each head as an OBJ
  (``experiments/any_head_seconds.py`` re-measures only this).

The default method is chosen from the validation rows by the rule in ``COMMAND``, written
before this ran.
"""

from __future__ import annotations

import argparse
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
    auto_rig,
    ict_pose_source,
    load_makehuman,
    load_rocketbox_head,
)
from canrig_jax.papers.riganyface import (  # noqa: E402
    EXAMPLE_ORDER,
    SculptedHead,
    any_head_table,
    choose_default_method,
    face_crop,
    face_crop_fit,
    few_shot_rows,
    ict_sculpted_heads,
    mean_few_shot,
    measure_cli_seconds,
    orientation_cases,
    template_row,
)
from canrig_jax.watchdog import run_watched  # noqa: E402

RULE_CASES = (("ict_heldout", "0"), ("rocketbox_female", "3"), ("rocketbox_male", "3"))
"""The validation cases of the default-method rule in COMMAND: (head, k)."""
TIE = 0.02
PREFERENCE = ("transfer", "transfer-residual", "raf")


def figure(
    path: Path, head: SculptedHead, rig, shapes=("jawOpen", "mouthSmileLeft", "browInnerUp")
):
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


def other_heads(data_dir) -> dict[str, SculptedHead]:
    """The two Rocketbox heads (validation) and the MakeHuman head (evaluation only)."""
    mh = load_makehuman(data_dir)
    return {
        "rocketbox_female": load_rocketbox_head("Female_Adult_01", data_dir),
        "rocketbox_male": load_rocketbox_head("Male_Adult_08", data_dir),
        "makehuman": SculptedHead("makehuman", mh.neutral, mh.faces, mh.deltas, mh.names),
    }


def score_heads(ict, heads, dataset, log) -> dict:
    """Every method at k = 0, few-shot, and the landmark fits (head and face crop) of the ICT
    heads (their mean) and of each other head."""
    results: dict = {"heads": {}, "few_shot_by_method": {}, "fit": {}}
    per_ict = [few_shot_rows(head, dataset, log) for head in ict]
    results["heads"]["ict_heldout"], results["few_shot_by_method"]["ict_heldout"] = mean_few_shot(
        per_ict
    )
    results["fit"]["ict_heldout"] = per_ict[0][2]
    results["fit"]["ict_heldout_face_crop"] = face_crop_fit(ict[0], dataset)
    for name, head in heads.items():
        methods, few, fit = few_shot_rows(head, dataset, log)
        results["heads"][name] = methods
        results["few_shot_by_method"][name] = few
        results["fit"][name] = fit
        results["fit"][f"{name}_face_crop"] = face_crop_fit(head, dataset)
    return results


def apply_rule(results: dict, out: Path) -> str:
    """The default method by the rule in COMMAND (validation rows only), recorded."""
    default, worst = choose_default_method(
        results["few_shot_by_method"], RULE_CASES, TIE, PREFERENCE
    )
    rule = (out / "COMMAND").read_text() if (out / "COMMAND").exists() else ""
    results["rule"] = "\n".join(
        line[2:] for line in rule.splitlines() if line.startswith("#   ") or "RULE" in line
    )
    results["default_method"] = default
    results["rule_worst_ratio"] = worst
    results["library_default"] = DEFAULT_METHOD.name
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
    return default


def templates_and_figures(results, heads, dataset, default, out, log) -> None:
    """The template of the same style, leave one out (Rocketbox), and figures of the default
    at k = 0 and k = 3."""
    results["template_loo"] = {}
    pairs = (("rocketbox_female", "rocketbox_male"), ("rocketbox_male", "rocketbox_female"))
    for target, source in pairs:
        row, rig = template_row(heads[target], heads[source], dataset)
        results["template_loo"][target] = row
        log(f"template {source} -> {target}: {row['skin_mae_mm']:.3f} "
            f"(none {row['no_motion']['skin_mae_mm']:.3f})")  # fmt: skip
        figure(out / f"shapes_{target}_template.png", heads[target], rig)
    (method_class,) = (cls for cls in AUTO_RIG_METHODS if cls.name == default)  # the rule's
    for name in ("rocketbox_female", "rocketbox_male", "makehuman"):
        head = heads[name]
        rig0 = auto_rig(head.vertices, head.faces, method=method_class(), dataset=dataset).rig
        figure(out / f"shapes_{name}_k0.png", head, rig0)
        examples = {n: head.shapes([n])[0] for n in EXAMPLE_ORDER[:3]}
        rig3 = auto_rig(
            head.vertices, head.faces, method=method_class(), dataset=dataset, examples=examples
        ).rig
        figure(out / f"shapes_{name}_k3.png", head, rig3, ("mouthFunnel", "browInnerUp",
               "mouthSmileRight"))  # fmt: skip


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="experiments/results/any_head")
    parser.add_argument("--data-dir")
    parser.add_argument("--ict-heads", type=int, default=3)
    parser.add_argument("--skip-orientation", action="store_true")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    start = time.perf_counter()

    def log(message):
        print(f"[{time.perf_counter() - start:7.1f} s] {message}", flush=True)

    warnings.simplefilter("ignore")
    dataset = ict_pose_source(args.data_dir, progress=False)
    ict = ict_sculpted_heads(args.ict_heads, args.data_dir)
    heads = other_heads(args.data_dir)
    log(f"loaded {len(ict)} ICT held-out heads, Rocketbox, MakeHuman")
    results = score_heads(ict, heads, dataset, log)
    default = apply_rule(results, out)
    templates_and_figures(results, heads, dataset, default, out, log)
    if not args.skip_orientation:
        cases = {"ict_heldout": (ict[0].vertices, ict[0].faces)}
        cases.update({n: (h.vertices, h.faces) for n, h in heads.items()})
        cases.update({f"{n}_face_crop": face_crop(*c) for n, c in list(cases.items())})
        results["orientation"] = orientation_cases(cases, dataset, log)
    results["seconds"] = measure_cli_seconds({"ict_heldout": ict[0], **heads}, log)
    results["provenance"] = provenance(command)
    results["total_s"] = time.perf_counter() - start
    save_json(out / "results.json", results)
    save_text(out / "table.md", any_head_table(results))
    record_command(out, command)
    log(f"default method by the rule: {default} (worst ratios {results['rule_worst_ratio']})")


if __name__ == "__main__":
    run_watched(main, Path(__file__).name)

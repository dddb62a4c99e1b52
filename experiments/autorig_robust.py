"""Can a retrained RigAnyFace become the default? Each candidate model rigs the validation
heads at k = 0 and is driven, beside the artist's rig, by the data folder's Live Link capture;
the rule in ``RULE.md`` (committed before any arm trained) picks among them.

    python experiments/autorig_robust.py --out experiments/results/autorig_robust \\
        --arm plain=/tmp/autorig_robust/plain/checkpoint_raf.eqx ...
    python experiments/autorig_robust.py --out experiments/results/autorig_robust --evaluate \\
        --arm ...   # once, after the choice: MakeHuman (evaluation only), appended

Candidates: ``transfer`` (the library default), ``raf`` (the packaged model) and every
``--arm NAME=CHECKPOINT`` (``auto_rig(method=RigAnyFaceNetwork(model=...))``). Heads (cm, +y
up, facing +z): the two Rocketbox head crops (validation); with ``--evaluate`` MakeHuman
instead, whose rows are stored under ``evaluation`` and change nothing. Per head and
candidate: skin distance to the artist's animation (mean, p95, max; mm) beside no motion's,
flipped skin triangles per frame (and the artist rig's), new self-intersections per frame,
``check_rig``'s checks.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from canrig_jax._io import save_results  # noqa: E402
from canrig_jax._provenance import experiment_command, provenance, record_command  # noqa: E402
from canrig_jax.autorig import (  # noqa: E402
    CHECK_LIMITS,
    DEFAULT_METHOD,
    RigAnyFaceNetwork,
    Transfer,
    auto_rig,
    check_rig,
    ict_pose_source,
    load_makehuman,
    load_riganyface,
    load_rocketbox_head,
    plot_check_frames,
)
from canrig_jax.data import load_livelinkface  # noqa: E402
from canrig_jax.data._paths import resolve_data_dir
from canrig_jax.mesh import flipped_triangles, self_intersections  # noqa: E402
from canrig_jax.papers.riganyface import SculptedHead  # noqa: E402
from canrig_jax.rig import UNIT_IN_CM, BlendshapeRig, evaluate_batch  # noqa: E402

HARD = {name for name, (_, _, hard) in CHECK_LIMITS.items() if hard}
VALIDATION = {"rocketbox_female": "Female_Adult_01", "rocketbox_male": "Male_Adult_08"}


def frames_of(rig: BlendshapeRig, take: np.ndarray) -> np.ndarray:
    """(T, V, 3) cm: the rig driven by (T, K) weights in its own order."""
    out = evaluate_batch(rig, np.asarray(take, np.float32), chunk=64)
    return np.asarray(out, np.float64) * UNIT_IN_CM[rig.units]


def distances(frames, truth, skin) -> dict:
    d = 10.0 * np.linalg.norm(frames[:, skin] - truth[:, skin], axis=-1)
    return {"mean_mm": float(d.mean()), "p95_mm": float(np.quantile(d, 0.95)),
            "max_mm": float(d.max())}  # fmt: skip


def run_head(name, head: SculptedHead, candidates, dataset, capture, out: Path, log) -> dict:
    """candidate -> row for one head."""
    artist = BlendshapeRig(head.vertices, head.deltas, (), tuple(head.names), head.faces, "cm")
    truth = frames_of(artist, capture.weights_for(artist.names, missing="zero"))
    skin_faces = head.skin[head.faces].all(axis=1)
    art_checks = check_rig(artist, capture.weights_for(artist.names, missing="zero"))
    no_motion = distances(np.broadcast_to(head.vertices, truth.shape), truth, head.skin)
    art_flips = float(flipped_triangles(truth, head.vertices, head.faces, mask=skin_faces)
                      .sum(1).mean())  # fmt: skip
    rows = {"_artist": {"checks": art_checks.as_dict(), "flips_per_frame": art_flips,
                        "no_motion_mean_mm": no_motion["mean_mm"]}}  # fmt: skip
    for label, method in candidates.items():
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = auto_rig(head.vertices, head.faces, method=method, dataset=dataset,
                              up="+y", forward="+z")  # fmt: skip
        seconds = time.perf_counter() - t
        take = capture.weights_for(result.rig.names, missing="zero")
        made = frames_of(result.rig, take)
        flips = flipped_triangles(made, head.vertices, head.faces, mask=skin_faces).sum(1)
        crossings = self_intersections(made, head.vertices, head.faces, mask=skin_faces)
        checks = check_rig(result.rig, take)
        failed = [n for n, c in checks.as_dict().items()
                  if n in HARD and art_checks.as_dict()[n]["ok"] and not c["ok"]]  # fmt: skip
        row = {**distances(made, truth, head.skin), "no_motion_mean_mm": no_motion["mean_mm"],
               "flips_per_frame": float(flips.mean()), "flips_max": int(flips.max()),
               "flips_series": flips.astype(int).tolist(),
               "artist_flips_per_frame": art_flips,
               "intersections_per_frame": float(crossings.mean()),
               "checks": checks.as_dict(), "hard_failed": failed, "seconds": seconds}  # fmt: skip
        rows[label] = row
        log(f"{name} {label}: {row['mean_mm']:.2f} mm (no motion {no_motion['mean_mm']:.2f}), "
            f"flips {row['flips_per_frame']:.1f} (artist {art_flips:.1f}), hard failed: "
            f"{', '.join(failed) or 'none'} [{seconds:.0f} s]")  # fmt: skip
        plot_check_frames(result.rig, checks, out / f"{name}_{label}.png", n=4,
                          title=f"{name}, {label}: {checks.summary()}")  # fmt: skip
    return rows


def eligible(rows_by_head: dict, label: str) -> bool:
    """RULE.md 1: no hard check failed that the artist passes, flips <= artist + 2, on every
    head."""
    return all(not r[label]["hard_failed"]
               and r[label]["flips_per_frame"] <= r[label]["artist_flips_per_frame"] + 2
               for r in rows_by_head.values())  # fmt: skip


def ratio(rows_by_head: dict, label: str) -> float:
    return float(np.mean([r[label]["mean_mm"] / r[label]["no_motion_mean_mm"]
                          for r in rows_by_head.values()]))  # fmt: skip


def apply_rule(rows_by_head: dict, arms: list[str]) -> dict:
    """RULE.md 2-3: the eligible arm of the lowest mean distance ratio to no motion; it
    replaces transfer only if transfer is ineligible or has a higher ratio."""
    report = {label: {"eligible": eligible(rows_by_head, label),
                      "ratio_to_no_motion": ratio(rows_by_head, label),
                      "hard_failed": sum(len(r[label]["hard_failed"])
                                         for r in rows_by_head.values())}
              for label in ("transfer", "raf", *arms)}  # fmt: skip
    ok = [a for a in arms if report[a]["eligible"]]
    chosen = min(ok, key=lambda a: report[a]["ratio_to_no_motion"]) if ok else None
    default = "transfer"
    if chosen is not None and (
        not report["transfer"]["eligible"]
        or report[chosen]["ratio_to_no_motion"] < report["transfer"]["ratio_to_no_motion"]
    ):
        default = f"raf ({chosen})"
    return {"candidates": report, "chosen_arm": chosen, "default": default}


def table(results: dict) -> str:
    lines = [
        "Under the data folder's 180-frame Live Link capture, k = 0; skin vertices; mm. flips: "
        "flipped skin triangles per frame; crossings: new self-intersections per frame; hard "
        "failed: hard checks of `autorig.check_rig` failed that the artist's rig passes.",
        "",
        "| head | role | candidate | mean mm | p95 mm | max mm | no motion mm | flips (max) | "
        "artist flips | crossings | hard failed |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    sections = [("validation", results["heads"])]
    if results.get("evaluation"):
        sections.append(("evaluation", results["evaluation"]))
    for role, heads in sections:
        for head, rows in heads.items():
            for label, r in rows.items():
                if label.startswith("_"):
                    continue
                lines.append(
                    f"| {head} | {role} | {label} | {r['mean_mm']:.2f} | {r['p95_mm']:.2f} | "
                    f"{r['max_mm']:.1f} | {r['no_motion_mean_mm']:.2f} | "
                    f"{r['flips_per_frame']:.1f} ({r['flips_max']}) | "
                    f"{r['artist_flips_per_frame']:.1f} | {r['intersections_per_frame']:.1f} | "
                    f"{', '.join(r['hard_failed']) or 'none'} |"
                )
    rule = results["rule_outcome"]
    lines += ["", "| candidate | eligible (RULE.md 1) | hard checks failed (both heads) | "
              "mean ratio to no motion |", "|---|---|---|---|"]  # fmt: skip
    for label, r in rule["candidates"].items():
        lines.append(f"| {label} | {r['eligible']} | {r['hard_failed']} | "
                     f"{r['ratio_to_no_motion']:.2f} |")  # fmt: skip
    lines += ["", f"Chosen arm: **{rule['chosen_arm'] or 'none eligible'}**; default by the "
              f"rule: **{rule['default']}** (library default when this ran: "
              f"{results['library_default']}).", ""]  # fmt: skip
    return "\n".join(lines) + "\n"


def flips_figure(results: dict, path: Path) -> None:
    """Flipped skin triangles per frame under the capture, each candidate beside the artist."""
    heads = {**results["heads"], **results.get("evaluation", {})}
    fig, axes = plt.subplots(1, len(heads), figsize=(4.2 * len(heads), 3), squeeze=False)
    for ax, (head, rows) in zip(axes[0], heads.items(), strict=True):
        for label, r in rows.items():
            if not label.startswith("_"):
                ax.plot(r["flips_series"], lw=1, label=label)
        ax.axhline(rows["_artist"]["flips_per_frame"], color="k", ls="--", lw=1,
                   label="artist (mean)")  # fmt: skip
        ax.set_title(head, fontsize=9)
        ax.set_xlabel("frame (60 fps)")
        ax.set_ylabel("flipped skin triangles")
        ax.set_yscale("symlog", linthresh=10)
    axes[0][0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="experiments/results/autorig_robust")
    parser.add_argument("--data", default=None)
    parser.add_argument("--arm", action="append", default=[], metavar="NAME=CHECKPOINT")
    parser.add_argument("--evaluate", action="store_true",
                        help="MakeHuman (evaluation only), after the choice")  # fmt: skip
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    log = lambda m: print(m, flush=True)  # noqa: E731
    data_dir = resolve_data_dir(args.data)
    capture = load_livelinkface(data_dir)
    warnings.filterwarnings("ignore", message=".*(TongueOut|stay at weight 0)")
    dataset = ict_pose_source(data_dir, progress=False)
    candidates = {"transfer": Transfer(), "raf": RigAnyFaceNetwork().loaded()}
    arms = []
    for spec in args.arm:
        label, _, path = spec.partition("=")
        if not path:
            parser.error(f"--arm: expected NAME=CHECKPOINT, got {spec!r}")
        candidates[label] = RigAnyFaceNetwork(model=load_riganyface(path)[:2])
        arms.append(label)
    if not args.evaluate:
        record_command(out, command)
        results = {"heads": {}}
        for name, file in VALIDATION.items():
            head = load_rocketbox_head(file, data_dir)
            results["heads"][name] = run_head(name, head, candidates, dataset, capture, out, log)
        results["arms"] = {a: args.arm[i] for i, a in enumerate(arms)}
        results["rule_outcome"] = apply_rule(results["heads"], arms)
        results["rule"] = (out / "RULE.md").read_text() if (out / "RULE.md").exists() else ""
        results["library_default"] = DEFAULT_METHOD.name
        results["provenance"] = provenance(command)
    else:
        results = json.loads((out / "results.json").read_text())
        mh = load_makehuman(data_dir)
        head = SculptedHead("makehuman", mh.neutral, mh.faces, mh.deltas, mh.names)
        results["evaluation"] = {
            "makehuman": run_head("makehuman", head, candidates, dataset, capture, out, log)
        }
        results["evaluation_provenance"] = provenance(command)
        record_command(out, command, note="evaluation (MakeHuman), after the choice was fixed")
    flips_figure(results, out / "flips.png")
    save_results(out, results, table(results))
    log(f"rule: chosen arm {results['rule_outcome']['chosen_arm']}, default "
        f"{results['rule_outcome']['default']}")  # fmt: skip


if __name__ == "__main__":
    main()

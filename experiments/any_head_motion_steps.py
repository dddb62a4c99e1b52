"""The default auto-rig's steps judged one by one in motion, as ``RULE.md`` states: each
step against the rig without it, transfer at k = 0 under the data folder's capture, on the
validation heads (ICT held-out identities, both Rocketbox crops), MakeHuman after
(evaluation).

    python experiments/any_head_motion_steps.py --out experiments/results/any_head_motion

    python experiments/any_head_motion_steps.py --step weld \
        --out experiments/results/any_head_motion

Steps:

- "slits" (closest points that never cross the mouth or a lid: ``autorig._slits``). Rows:
  "plain" (without it) and "slits". Writes ``steps.json`` and ``steps.md``.
- "weld" (clumps of vertices a fraction of a millimetre apart move as one:
  ``autorig._weld``). Rows: "slits" (without it) and "weld_<tau>" for each candidate tau;
  the rule's verdict is computed here. Writes ``steps_weld.json`` and ``steps_weld.md``.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np
from any_head_motion import HARD, artist_rig, distances, frames_of, load_heads

import canrig_jax.autorig._slits as slits
import canrig_jax.autorig._weld as weld
from canrig_jax._io import save_text
from canrig_jax.autorig import (
    Transfer,
    auto_rig,
    check_rig,
    ict_pose_source,
    load_makehuman,
    load_rocketbox_head,
)
from canrig_jax.data import load_livelinkface
from canrig_jax.data._paths import resolve_data_dir
from canrig_jax.mesh import flipped_triangles
from canrig_jax.papers.riganyface import SculptedHead

STEPS = {"slits": ("plain", "slits"), "weld": ("slits", "weld_0.1", "weld_0.2", "weld_0.3")}
VALIDATION = ("ict_heldout_0", "ict_heldout_1", "rocketbox_female", "rocketbox_male")
ROCKETBOX = ("rocketbox_female", "rocketbox_male")
MEAN_RISE_MM = 0.05


def _set_variant(variant: str, original) -> None:
    slits.slit_sides = original if variant != "plain" else (lambda v, f, lm: np.full(len(v), -1))
    weld.WELD_TAU = float(variant.split("_")[1]) if variant.startswith("weld_") else 0.0


def verdict(out: dict, base: str, candidates: tuple[str, ...]) -> tuple[str | None, list[str]]:
    """RULE.md's judgement of a step: each candidate against ``base`` on the validation
    heads ((a) no new hard failure, (b) fewer flips on both Rocketbox crops, (c) mean rise
    <= 0.05 mm); among qualifying, the fewest flips summed over the Rocketbox crops (ties:
    the earlier candidate). Returns (adopted or None, one line per candidate)."""
    lines, qualifying = [], []
    for c in candidates:
        new_fail = sorted(
            {
                h
                for h in VALIDATION
                if set(out[h][c]["hard_failed"]) - set(out[h][base]["hard_failed"])
            }
        )
        fewer = all(
            out[h][c]["flips_per_frame"] < out[h][base]["flips_per_frame"] for h in ROCKETBOX
        )
        rise = max(out[h][c]["mean_mm"] - out[h][base]["mean_mm"] for h in VALIDATION)
        ok = not new_fail and fewer and rise <= MEAN_RISE_MM
        flips = sum(out[h][c]["flips_per_frame"] for h in ROCKETBOX)
        lines.append(
            f"- {c}: (a) new hard failures {new_fail or 'none'}; (b) fewer flips on both "
            f"Rocketbox crops: {fewer}; (c) largest mean rise {rise:+.3f} mm; "
            f"Rocketbox flips summed {flips:.2f}: {'qualifies' if ok else 'does not qualify'}"
        )
        if ok:
            qualifying.append((flips, c))
    return (min(qualifying)[1] if qualifying else None), lines  # fmt: skip


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="experiments/results/any_head_motion")
    parser.add_argument("--data", default=None)
    parser.add_argument("--step", choices=tuple(STEPS), default="slits")
    args = parser.parse_args(argv)
    data = resolve_data_dir(args.data)
    capture = load_livelinkface(data)
    dataset = ict_pose_source(data, progress=False)
    heads = {n: h for n, (h, _) in load_heads(data, 2, True).items()}
    heads["rocketbox_male"] = load_rocketbox_head("Male_Adult_08", data)
    mh = load_makehuman(data)
    heads["makehuman"] = SculptedHead("makehuman", mh.neutral, mh.faces, mh.deltas, mh.names)
    originals = slits.slit_sides
    out: dict = {}
    for name, head in heads.items():
        art = artist_rig(head)
        take = capture.weights_for(art.names, missing="zero")
        weights = {n: take[:, i] for i, n in enumerate(art.names)}
        truth = frames_of(art, weights)
        skin_faces = head.skin[head.faces].all(axis=1)
        artist_flips = flipped_triangles(truth, head.vertices, head.faces, mask=skin_faces)
        for variant in STEPS[args.step]:
            _set_variant(variant, originals)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                made_rig = auto_rig(head.vertices, head.faces, method=Transfer(),
                                    dataset=dataset, up="+y", forward="+z").rig  # fmt: skip
                checks = check_rig(made_rig, capture.weights_for(made_rig.names, missing="zero"))
            made = frames_of(made_rig, weights)
            flips = flipped_triangles(made, head.vertices, head.faces, mask=skin_faces)
            row = {"mean_mm": distances(made, truth, head.skin)["mean_mm"],
                   "flips_per_frame": float(flips.sum(1).mean()),
                   "artist_flips_per_frame": float(artist_flips.sum(1).mean()),
                   "hard_failed": sorted(n for n, c in checks.as_dict().items()
                                         if not c["ok"] and n in HARD)}  # fmt: skip
            out.setdefault(name, {})[variant] = row
            print(name, variant, row, flush=True)
    _set_variant("slits", originals)
    lines = ["Each step of the default (transfer, k = 0) against the rig without it, under the "
             "data folder's capture; skin; mm. MakeHuman: evaluation only.", "",
             "| head | variant | mean mm | flips / frame | artist flips | hard checks failed |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for name, rows in out.items():
        for variant, r in rows.items():
            failed = ", ".join(r["hard_failed"]) or "none"
            lines.append(f"| {name} | {variant} | {r['mean_mm']:.3f} | {r['flips_per_frame']:.2f} "
                         f"| {r['artist_flips_per_frame']:.2f} | {failed} |")  # fmt: skip
    stem = "steps" if args.step == "slits" else f"steps_{args.step}"
    if args.step != "slits":
        base, *candidates = STEPS[args.step]
        adopted, judged = verdict(out, base, tuple(candidates))
        ending = (
            f"**Adopted: {adopted}.**" if adopted else "**None qualifies: the step stays out.**"
        )
        judged_by = (f"Judged by `RULE.md` (part written before the step was measured), "
                     f"against `{base}` on the validation heads:")  # fmt: skip
        lines += ["", judged_by, "", *judged, "", ending]
        out["verdict"] = {"adopted": adopted, "lines": judged}
    target = Path(args.out)
    save_text(target / f"{stem}.json", json.dumps(out, indent=1) + "\n")
    save_text(target / f"{stem}.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()

"""Auto-rigs judged in motion: each head's generated rig and its artist's rig driven by the
data folder's Live Link capture (and by random sparse combinations of the ARKit shapes),
with the rigger's checks (``autorig.check_rig``).

    python experiments/any_head_motion.py --out experiments/results/any_head_motion

Heads (cm, +y up, facing +z): held-out ICT identities (``ict_sculpted_heads``, validation),
both Rocketbox head crops (validation) and the head meshes of the two whole-body Rocketbox FBX
files (``rig.load_fbx_rig(crop="head")``: the skinned mesh with the artist's shapes, cut at
the neck; validation), MakeHuman (evaluation only: nothing is chosen on it).

For every method of ``autorig.AUTO_RIG_METHODS`` and k = 0, 1, 3 examples (the first k of
``papers.riganyface.EXAMPLE_ORDER``): skin distance to the artist's animation (mean, p95, max over
frames and skin vertices, mm) beside no motion's, flipped skin triangles per frame (and the
artist rig's), new self-intersections per frame, and the checks. The default method is
chosen by ``RULE.md`` (committed before this ran), on the validation heads at k = 0.
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

from canrig_jax._io import save_results, save_text  # noqa: E402
from canrig_jax._provenance import experiment_command, provenance, record_command  # noqa: E402
from canrig_jax.autorig import (  # noqa: E402
    AUTO_RIG_METHODS,
    CHECK_LIMITS,
    DEFAULT_METHOD,
    auto_rig,
    check_rig,
    ict_pose_source,
    load_makehuman,
    load_rocketbox_head,
    plot_check_frames,
)
from canrig_jax.data import load_livelinkface  # noqa: E402
from canrig_jax.data._paths import resolve_data_dir
from canrig_jax.mesh import flipped_triangles, self_intersections  # noqa: E402
from canrig_jax.papers.riganyface import (  # noqa: E402
    EXAMPLE_ORDER,
    SculptedHead,
    ict_sculpted_heads,
)
from canrig_jax.rig import (  # noqa: E402
    UNIT_IN_CM,
    BlendshapeRig,
    Corrective,
    evaluate_batch,
    load_fbx_rig,
    random_sparse_poses,
)

KS = (0, 1, 3)
METHOD_NAMES = tuple(cls.name for cls in AUTO_RIG_METHODS)
"""Each method's name, as results are keyed."""
HARD = {name for name, (_, _, hard) in CHECK_LIMITS.items() if hard}
VALIDATION = ("ict_heldout_0", "ict_heldout_1", "rocketbox_female", "rocketbox_male")
"""The validation heads of the rule (``RULE.md``): the ICT held-out identities and the
Rocketbox crops; the FBX head meshes and MakeHuman are reported beside them."""


def load_heads(data_dir, n_ict: int, quick: bool) -> dict[str, tuple[SculptedHead, str]]:
    """name -> (head with its artist's shapes, "validation" or "evaluation")."""
    heads = {}
    for i, head in enumerate(ict_sculpted_heads(n_ict, data_dir)):
        heads[f"ict_heldout_{i}"] = (head, "validation")
    heads["rocketbox_female"] = (load_rocketbox_head("Female_Adult_01", data_dir), "validation")
    if quick:
        return heads
    heads["rocketbox_male"] = (load_rocketbox_head("Male_Adult_08", data_dir), "validation")
    for name, file in (("female", "Female_Adult_01"), ("male", "Male_Adult_08")):
        fbx = load_fbx_rig(Path(data_dir) / "rocketbox" / f"{file}_facial.fbx", crop="head")
        scale = UNIT_IN_CM[fbx.units]
        head = SculptedHead(
            f"{file}_fbx_head", np.asarray(fbx.neutral) * scale, np.asarray(fbx.faces),
            np.asarray(fbx.deltas) * scale, list(fbx.names),
        )  # fmt: skip
        heads[f"rocketbox_{name}_fbx"] = (head, "validation (reported)")
    mh = load_makehuman(data_dir)
    heads["makehuman"] = (
        SculptedHead("makehuman", mh.neutral, mh.faces, mh.deltas, mh.names),
        "evaluation",
    )
    return heads


def artist_rig(head: SculptedHead) -> BlendshapeRig:
    return BlendshapeRig(head.vertices, head.deltas, (), tuple(head.names), head.faces, "cm")


def frames_of(rig: BlendshapeRig, weights_by_name: dict[str, np.ndarray]) -> np.ndarray:
    """(T, V, 3) cm: the rig driven by {ARKit name: (T,) weights} (absent names at 0)."""
    n = len(next(iter(weights_by_name.values())))
    w = np.zeros((n, rig.n_blendshapes), np.float32)
    for k, name in enumerate(rig.names):
        if name in weights_by_name:
            w[:, k] = weights_by_name[name]
    return np.asarray(evaluate_batch(rig, w, chunk=64), np.float64) * UNIT_IN_CM[rig.units]


def distances(frames: np.ndarray, truth: np.ndarray, skin: np.ndarray) -> dict[str, float]:
    d = 10.0 * np.linalg.norm(frames[:, skin] - truth[:, skin], axis=-1)
    return {"mean_mm": float(d.mean()), "p95_mm": float(np.quantile(d, 0.95)),
            "max_mm": float(d.max())}  # fmt: skip


def score(rig, head, artist, drives, skin_faces) -> dict:
    """One generated rig against the artist's under each drive (take, random)."""
    out = {}
    for drive, weights in drives.items():
        made, truth = frames_of(rig, weights), artist[drive]
        flips = flipped_triangles(made, head.vertices, head.faces, mask=skin_faces).sum(1)
        row = distances(made, truth, head.skin)
        row["flips_per_frame"], row["flips_max"] = float(flips.mean()), int(flips.max())
        if drive == "take":
            crossings = self_intersections(made, head.vertices, head.faces, mask=skin_faces)
            row["intersections_per_frame"] = float(crossings.mean())
        out[drive] = row
    return out


PRIOR_GAINS = (1.0, 0.8, 0.6, 0.5, 0.4)
"""The amplitude prior's gains (``RULE.md``, second part)."""


def scaled(rig: BlendshapeRig, gain: float) -> BlendshapeRig:
    """Every shape and corrective times ``gain``, the blinks as they are."""
    deltas = np.array(rig.deltas)
    blink = np.array([n.startswith("eyeBlink") for n in rig.names])
    deltas[~blink] *= gain
    correctives = tuple(
        Corrective(c.indices, c.vertices, np.asarray(c.deltas) * gain) for c in rig.correctives
    )
    return BlendshapeRig(rig.neutral, deltas, correctives, rig.names, rig.faces, rig.units)


def prior_rows(rig, head, artist, drives, skin_faces) -> dict[str, dict]:
    """str(gain) -> mean mm and flips per frame under the take, of the rig scaled."""
    rows = {}
    for gain in PRIOR_GAINS:
        take = score(scaled(rig, gain), head, {"take": artist["take"]},
                     {"take": drives["take"]}, skin_faces)["take"]  # fmt: skip
        rows[str(gain)] = {"mean_mm": take["mean_mm"], "flips_per_frame": take["flips_per_frame"]}
    return rows


def choose_prior(results: dict) -> float:
    """``RULE.md``'s amplitude prior: the largest gain with transfer (k = 0) below no motion
    and within the artist's flips + 2 on every validation head; else 1.0."""
    heads = [h for h in VALIDATION if h in results["heads"]]
    for gain in PRIOR_GAINS:
        ok = True
        for h in heads:
            row = results["heads"][h]["transfer"]["0"]
            prior = row["amplitude_prior"][str(gain)]
            ok &= prior["mean_mm"] < row["no_motion_mean_mm"]
            ok &= prior["flips_per_frame"] <= row["artist_flips_per_frame"] + 2
        if ok:
            return gain
    return 1.0


def run_head(name, head, dataset, capture, quick, log, sheets: Path) -> tuple[dict, dict]:
    """(method -> str(k) -> row, the artist rig's checks) for one head."""
    art = artist_rig(head)
    take = capture.weights_for(art.names, missing="zero")
    rng = np.random.default_rng(0)
    poses = random_sparse_poses(rng, 60, list(art.names))
    drives = {
        "take": {n: take[:, i] for i, n in enumerate(art.names)},
        "random": {n: poses[:, i] for i, n in enumerate(art.names)},
    }
    artist = {d: frames_of(art, w) for d, w in drives.items()}
    skin_faces = head.skin[head.faces].all(axis=1)
    art_checks = check_rig(art, take)
    no_motion = {d: distances(np.broadcast_to(head.vertices, f.shape), f, head.skin)["mean_mm"]
                 for d, f in artist.items()}  # fmt: skip
    art_flips = {d: float(flipped_triangles(f, head.vertices, head.faces, mask=skin_faces)
                          .sum(1).mean()) for d, f in artist.items()}  # fmt: skip
    rows: dict = {}
    for method_class in AUTO_RIG_METHODS:
        method = method_class.name
        rows[method] = {}
        for k in KS if not quick else (0,):
            given = [n for n in EXAMPLE_ORDER[:k] if n in head.names]
            examples = {n: head.shapes([n])[0] for n in given} or None
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                result = auto_rig(head.vertices, head.faces, method=method_class(),
                                  dataset=dataset, examples=examples, up="+y",
                                  forward="+z")  # fmt: skip
            seconds = time.perf_counter() - t
            scores = score(result.rig, head, artist, drives, skin_faces)
            checks = check_rig(result.rig, capture.weights_for(result.rig.names, missing="zero"))
            row = {**scores["take"], "no_motion_mean_mm": no_motion["take"],
                   "artist_flips_per_frame": art_flips["take"],
                   "random": {**scores["random"], "no_motion_mean_mm": no_motion["random"],
                              "artist_flips_per_frame": art_flips["random"]},
                   "checks": checks.as_dict(), "checks_ok": checks.ok,
                   "blink_gain": result.fit.get("blink_gain"), "seconds": seconds}  # fmt: skip
            rows[method][str(k)] = row
            log(f"{name} {method} k={k}: {row['mean_mm']:.2f} mm (no motion "
                f"{no_motion['take']:.2f}), flips {row['flips_per_frame']:.1f} (artist "
                f"{art_flips['take']:.1f}), {checks.summary()}")  # fmt: skip
            if k == 0 and method == "transfer":
                row["amplitude_prior"] = prior_rows(result.rig, head, artist, drives, skin_faces)
            if k == 0:
                plot_check_frames(result.rig, checks, sheets / f"{name}_{method}.png", n=4,
                                  title=f"{name}, {method}: {checks.summary()}")  # fmt: skip
    return rows, art_checks.as_dict()


def apply_rule(results: dict) -> tuple[str, dict]:
    """``RULE.md``: eligible methods on the validation heads at k = 0, then the lowest mean
    distance ratio to no motion; else the fewest failed hard checks."""
    heads = [h for h in VALIDATION if h in results["heads"]]
    report = {}
    for method in METHOD_NAMES:
        failed, ratios, eligible = 0, [], True
        for h in heads:
            row = results["heads"][h][method]["0"]
            artist = results["artist_checks"][h]
            hard = [n for n, c in row["checks"].items() if n in HARD and artist[n]["ok"]]
            failed += sum(not row["checks"][n]["ok"] for n in hard)
            eligible &= all(row["checks"][n]["ok"] for n in hard)
            eligible &= row["flips_per_frame"] <= row["artist_flips_per_frame"] + 2
            ratios.append(row["mean_mm"] / row["no_motion_mean_mm"])
        report[method] = {"eligible": bool(eligible), "failed_hard": failed,
                          "mean_ratio_to_no_motion": float(np.mean(ratios))}  # fmt: skip
    eligible = [m for m in METHOD_NAMES if report[m]["eligible"]]
    if eligible:
        return min(eligible, key=lambda m: report[m]["mean_ratio_to_no_motion"]), report
    key = lambda m: (report[m]["failed_hard"], report[m]["mean_ratio_to_no_motion"])  # noqa: E731
    return min(METHOD_NAMES, key=key), report


def table(results: dict) -> str:
    lines = [
        "Under the data folder's 180-frame Live Link capture; skin vertices; mm. flips: "
        "flipped skin triangles per frame; crossings: new self-intersections per frame; "
        "checks: hard checks failed (`autorig.check_rig`).",
        "",
        "| head | role | method | k | mean mm | p95 mm | max mm | no motion mm | flips (max) "
        "| artist flips | crossings | hard checks failed |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for head, methods in results["heads"].items():
        for method, ks in methods.items():
            for k, r in ks.items():
                failed = [n for n, c in r["checks"].items() if n in HARD and not c["ok"]]
                lines.append(
                    f"| {head} | {results['roles'][head]} | {method} | {k} | {r['mean_mm']:.2f} "
                    f"| {r['p95_mm']:.2f} | {r['max_mm']:.1f} | {r['no_motion_mean_mm']:.2f} "
                    f"| {r['flips_per_frame']:.1f} ({r['flips_max']}) "
                    f"| {r['artist_flips_per_frame']:.1f} | {r['intersections_per_frame']:.1f} "
                    f"| {', '.join(failed) or 'none'} |"
                )
    lines += ["", f"Default by the rule: **{results['default_method']}** "
              f"(library default when this ran: {results['library_default']}).", ""]  # fmt: skip
    lines += ["| method | eligible | hard checks failed (validation) | mean ratio to no motion |",
              "|---|---|---|---|"]  # fmt: skip
    for m, r in results["rule_report"].items():
        lines.append(f"| {m} | {r['eligible']} | {r['failed_hard']} | "
                     f"{r['mean_ratio_to_no_motion']:.2f} |")  # fmt: skip
    gains = [str(g) for g in PRIOR_GAINS]
    lines += ["", "Amplitude prior (transfer, k = 0, every shape but the blinks times g): "
              "mean mm / flips per frame under the capture; chosen g: "
              f"**{results['amplitude_prior_gain']}**.", "",
              "| head | no motion mm | artist flips | " + " | ".join(f"g = {g}" for g in gains)
              + " |", "|---|---|---|" + "---|" * len(gains)]  # fmt: skip
    for head, methods in results["heads"].items():
        row = methods["transfer"]["0"]
        cells = [f"{row['amplitude_prior'][g]['mean_mm']:.2f} / "
                 f"{row['amplitude_prior'][g]['flips_per_frame']:.1f}" for g in gains]  # fmt: skip
        head_cells = f"| {head} | {row['no_motion_mean_mm']:.2f} | "
        head_cells += f"{row['artist_flips_per_frame']:.1f} | "
        lines.append(head_cells + " | ".join(cells) + " |")
    lines += ["", "Artists' rigs through the checks (hard checks failed):", ""]
    for head, checks in results["artist_checks"].items():
        failed = [n for n, c in checks.items() if n in HARD and not c["ok"]]
        lines.append(f"- {head}: {', '.join(failed) or 'none'}")
    return "\n".join(lines) + "\n"


def flips_figure(results: dict, path: Path) -> None:
    """Flipped skin triangles per frame at k = 0, each method beside the artist's rig."""
    heads = list(results["heads"])
    fig, ax = plt.subplots(figsize=(8, 3))
    width = 0.8 / (len(METHOD_NAMES) + 1)
    for j, method in enumerate(("artist", *METHOD_NAMES)):
        values = [results["heads"][h][METHOD_NAMES[0]]["0"]["artist_flips_per_frame"]
                  if method == "artist" else results["heads"][h][method]["0"]["flips_per_frame"]
                  for h in heads]  # fmt: skip
        ax.bar(np.arange(len(heads)) + j * width, values, width, label=method)
    ax.set_xticks(np.arange(len(heads)) + 0.4 - width / 2, heads, rotation=20, fontsize=7)
    ax.set_ylabel("flipped triangles / frame")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="experiments/results/any_head_motion")
    parser.add_argument("--data", default=None)
    parser.add_argument("--n-ict", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="one ICT head, Rocketbox F, k=0")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    record_command(out, command)
    data_dir = resolve_data_dir(args.data)
    log = lambda m: print(m, flush=True)  # noqa: E731
    capture = load_livelinkface(data_dir)
    warnings.filterwarnings("ignore", message=".*(TongueOut|stay at weight 0)")
    dataset = ict_pose_source(data_dir, progress=False)
    heads = load_heads(data_dir, 1 if args.quick else args.n_ict, args.quick)
    results: dict = {"heads": {}, "artist_checks": {}, "roles": {}}
    for name, (head, role) in heads.items():
        rows, art = run_head(name, head, dataset, capture, args.quick, log, out)
        results["heads"][name], results["artist_checks"][name] = rows, art
        results["roles"][name] = role
    results["default_method"], results["rule_report"] = apply_rule(results)
    results["amplitude_prior_gain"] = choose_prior(results)
    results["rule"] = (out / "RULE.md").read_text() if (out / "RULE.md").exists() else ""
    results["library_default"] = DEFAULT_METHOD.name
    results["provenance"] = provenance(command)
    flips_figure(results, out / "flips.png")
    save_results(out, results, table(results))
    save_text(out / "summary.txt", f"default: {results['default_method']}\n")
    log(f"default by the rule: {results['default_method']}")


if __name__ == "__main__":
    main()

"""Whole avatars in, the same avatars with a face rig out: ``canrig autorig`` on the two
Rocketbox whole-body FBX files (GLB and VRM out), on a GLB avatar (the male FBX written as
GLB first, then rigged in place) and on each body as a plain GLB without a skeleton (its head
found by geometry).

    python experiments/avatar.py --out experiments/results/avatar

Per avatar: ``ok``, ``seconds`` (the command, end to end), ``head_meshes``,
``vertices_rigged``, ``kept`` (nodes, skins, joints, materials, textures, animations of the
output equal to the input's glTF: for an FBX, the GLB ``rig.avatar_from_fbx`` makes of it),
``validator_errors`` (Khronos glTF validator), ``three_js_loaded`` (three.js GLTFLoader in
Node, the face mesh's targets by name), ``vrm_loaded`` (@pixiv/three-vrm, every expression
present; where a .vrm is written), ``checks`` (the rigger's checks of the face rig,
``autorig.check_rig``, as ``canrig autorig`` runs them) and ``motion``: the written face
targets against the artist's own shapes of the same FBX (ignored when rigging), both driven by
the data folder's Live Link capture, over the vertices either rig moves (mean/p95/max mm,
no motion's mean, flipped triangles per frame of each). A screenshot per avatar
(``canrig view --screenshot``) at the capture's most active frame. ``--quick`` runs the male
FBX only.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import trimesh

from canrig_jax import run_command
from canrig_jax._io import save_results
from canrig_jax._provenance import experiment_command, record_command, with_provenance
from canrig_jax.autorig import auto_rig_avatar
from canrig_jax.data import arkit_name_of, data_file, load_fbx, load_fbx_scene, load_livelinkface
from canrig_jax.mesh import flipped_triangles
from canrig_jax.rig import (
    VRM_PRESETS,
    accessor_array,
    avatar_from_fbx,
    find_gltf_validator,
    mesh_vertices,
    read_gltf_avatar,
    validate_gltf,
    write_gltf_avatar,
)

REPO = Path(__file__).resolve().parents[1]
CLIENT = REPO / "tests" / "clients" / "load_avatar.mjs"
KEPT = ("nodes", "skins", "materials", "textures", "animations")


def _three(path: Path) -> dict | None:
    modules = REPO / "node_modules" / "@pixiv" / "three-vrm"
    if shutil.which("node") is None or not modules.is_dir():
        return None
    done = subprocess.run(
        ["node", str(CLIENT), str(path)], capture_output=True, text=True, timeout=300, check=False
    )
    return json.loads(done.stdout) if done.returncode == 0 else {"error": done.stderr[-500:]}


def _kept(source: dict, rigged: dict) -> dict:
    kept = {key: source.get(key) == rigged.get(key) for key in KEPT}
    joints = lambda d: [s.get("joints") for s in d.get("skins", [])]  # noqa: E731
    kept["joints"] = joints(source) == joints(rigged)
    return kept


def _one(name: str, source: Path, reference: dict, out: Path, log) -> dict:
    """``auto_rig_avatar(SOURCE, OUT)`` (what ``canrig autorig SOURCE -o OUT`` runs) and what
    the output keeps and loads in."""
    start = time.perf_counter()
    try:
        result = auto_rig_avatar(source, out, extras=("visemes", "rpm"))
    except ValueError as error:
        log(f"{name}: refused: {error}")
        return {"input": source.name, "output": out.name, "ok": False, "error": str(error)}
    seconds = time.perf_counter() - start
    log(f"{name}: {result.checks.summary() if result.checks else ''} in {seconds:.1f} s")
    entry = {"input": source.name, "output": out.name, "ok": True, "seconds": seconds}
    if result.checks is not None:
        entry["checks"] = result.checks.as_dict()
        entry["hard_checks_failed"] = list(result.checks.failed)
    rigged = read_gltf_avatar(out).document
    face = [m for m in rigged["meshes"] if m.get("extras", {}).get("canrig")]
    entry["head_meshes"] = [m.get("name") for m in face]
    entry["targets"] = len(face[0]["extras"]["targetNames"]) if face else 0
    entry["kept"] = _kept(reference, rigged)
    if find_gltf_validator() is not None:
        copy = out.with_name(out.stem + "_validate.glb")
        copy.write_bytes(out.read_bytes())
        entry["validator_errors"] = validate_gltf(copy)["issues"]["numErrors"]
        copy.unlink()
    seen = _three(out)
    if seen is not None and "error" not in seen:
        names = set(face[0]["extras"]["targetNames"]) if face else set()
        entry["three_js_loaded"] = any(set(m["targets"]) == names for m in seen["meshes"])
        if out.suffix == ".vrm":
            expressions = set((seen.get("vrm") or {}).get("expressions", {}))
            entry["vrm_loaded"] = set(VRM_PRESETS) <= expressions
    return entry


def _face_rig(out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """The written face mesh as (V, 3) neutral cm, (F, 3) triangles, (K, V, 3) targets cm in
    the world, and the target names (the first mesh ``auto_rig_avatar`` rigged)."""
    avatar = read_gltf_avatar(out)
    layout = next(v for v in mesh_vertices(avatar)
                  if avatar.document["meshes"][v.mesh].get("extras", {}).get("canrig"))  # fmt: skip
    mesh = avatar.document["meshes"][layout.mesh]
    local = np.stack([accessor_array(avatar, t["POSITION"])
                      for t in mesh["primitives"][0]["targets"]])  # fmt: skip
    world = np.einsum("vij,kvj->kvi", layout.to_world, local) * 100.0
    return layout.world * 100.0, layout.faces, world, list(mesh["extras"]["targetNames"])


def _motion(out: Path, fbx: Path, capture) -> dict:
    """The written targets against the artist's shapes of ``fbx`` under the capture."""
    neutral, faces, targets, names = _face_rig(out)
    artist = load_fbx(fbx)
    theirs = np.asarray(artist.deltas, np.float64)  # cm, the GLB world's frame
    arkit = [arkit_name_of(n) for n in artist.names]
    keep = [i for i, n in enumerate(arkit) if n is not None]
    driven = [i for i, n in enumerate(names) if arkit_name_of(n) is not None]  # not extras
    ours = capture.weights_for([names[i] for i in driven], missing="zero")
    their_weights = capture.weights_for([arkit[i] for i in keep], missing="zero")
    targets = targets[driven]
    made = neutral + np.einsum("tk,kvc->tvc", ours, targets)
    truth = neutral + np.einsum("tk,kvc->tvc", their_weights, theirs[keep])
    moved = (np.linalg.norm(targets, axis=-1).max(0) > 1e-4) | (
        np.linalg.norm(theirs[keep], axis=-1).max(0) > 1e-4
    )
    d = 10.0 * np.linalg.norm(made[:, moved] - truth[:, moved], axis=-1)
    still = 10.0 * np.linalg.norm(neutral[moved] - truth[:, moved], axis=-1)
    region = moved[faces].all(axis=1)
    flips = flipped_triangles(made, neutral, faces, mask=region).sum(1)
    artist_flips = flipped_triangles(truth, neutral, faces, mask=region).sum(1)
    return {
        "vertices": int(moved.sum()), "frames": int(len(ours)),
        "mean_mm": float(d.mean()), "p95_mm": float(np.quantile(d, 0.95)),
        "max_mm": float(d.max()), "no_motion_mean_mm": float(still.mean()),
        "flips_per_frame": float(flips.mean()), "flips_max": int(flips.max()),
        "artist_flips_per_frame": float(artist_flips.mean()),
    }  # fmt: skip


def _screenshot(out: Path, png: Path, frame: dict[str, float]) -> bool:
    """``canrig view OUT --screenshot PNG --face`` holding the capture frame's weights."""
    morph = [a for n, w in frame.items() if w > 0.02 for a in ("--morph", f"{n}={w:.3f}")]
    argv = ["view", str(out), "--screenshot", str(png), "--size", "480x640", "--face", *morph]
    return run_command(argv) == 0


def _vertices_rigged(out: Path) -> int:
    avatar = read_gltf_avatar(out)
    moved = 0
    for mesh in avatar.document["meshes"]:
        if not mesh.get("extras", {}).get("canrig"):
            continue
        for primitive in mesh["primitives"][:1]:
            norms = [np.linalg.norm(accessor_array(avatar, t["POSITION"]), axis=1)
                     for t in primitive.get("targets", [])]  # fmt: skip
            moved += int((np.max(norms, axis=0) > 1e-8).sum()) if norms else 0
    return moved


def _table(avatars: dict, seconds_cli: float | None) -> str:
    lines = [
        "| avatar | ok | seconds | head meshes | vertices rigged | targets | kept (all) | "
        "validator errors | three.js | three-vrm | hard checks failed | motion mean / p95 / "
        "max mm | no motion mm | flips / frame (artist's) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, a in avatars.items():
        kept, m = a.get("kept", {}), a.get("motion") or {}
        motion = still = flips = ""
        if m:
            motion = f"{m['mean_mm']:.2f} / {m['p95_mm']:.2f} / {m['max_mm']:.1f}"
            still = f"{m['no_motion_mean_mm']:.2f}"
            flips = f"{m['flips_per_frame']:.1f} ({m['artist_flips_per_frame']:.1f})"
        failed = ", ".join(a.get("hard_checks_failed", [])) or "none"
        lines.append(
            f"| {name} | {a['ok']} | {a.get('seconds', 0):.1f} | "
            f"{', '.join(a.get('head_meshes', []))} | {a.get('vertices_rigged', '')} | "
            f"{a.get('targets', '')} | {all(kept.values()) if kept else ''} | "
            f"{a.get('validator_errors', 'n/a')} | {a.get('three_js_loaded', 'n/a')} | "
            f"{a.get('vrm_loaded', 'n/a')} | {failed} | {motion} | {still} | {flips} |"
        )  # fmt: skip
    cli = f"{seconds_cli:.1f} s" if seconds_cli is not None else "not measured"
    lines += [
        "",
        "`seconds`: `autorig.auto_rig_avatar` (what `canrig autorig AVATAR -o OUT` runs) in this "
        "one process, one avatar after another (the first run compiles); a fresh `canrig "
        f"autorig` process on the male Rocketbox FBX, end to end: {cli}. The default method, "
        "the artist's blend shapes ignored; targets: 51 ARKit shapes + 20 extras (`--extras "
        "visemes,rpm`). Checks: `autorig.check_rig` on the face rig under random sparse poses "
        "of its shapes. Motion: the written face targets against the artist's own shapes of "
        "the FBX, both driven by the data folder's 180-frame Live Link capture, over the "
        "vertices either rig moves.",
    ]
    return "\n".join(lines) + "\n"


def _cli_seconds(fbx: Path, out: Path) -> float | None:
    """A fresh ``canrig autorig`` process on ``fbx``, end to end (s)."""
    start = time.perf_counter()
    canrig = Path(sys.executable).with_name("canrig")  # the console script beside Python
    done = subprocess.run([str(canrig), "autorig", str(fbx), "-o", str(out), "--quiet"],
                          capture_output=True, check=False)  # fmt: skip
    return time.perf_counter() - start if done.returncode == 0 else None


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="experiments/results/avatar")
    parser.add_argument("--data-dir")
    parser.add_argument("--quick", action="store_true", help="the male FBX only")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = experiment_command(__file__, argv)
    start = time.perf_counter()

    def log(message):
        print(f"[{time.perf_counter() - start:7.1f} s] {message}", flush=True)

    warnings.simplefilter("ignore")
    work = out / "files"
    work.mkdir(exist_ok=True)
    people = ("Male_Adult_08",) if args.quick else ("Male_Adult_08", "Female_Adult_01")
    avatars = {}
    for person in people:
        fbx = data_file(f"rocketbox/{person}_facial.fbx", args.data_dir)
        reference = avatar_from_fbx(load_fbx_scene(fbx))
        key = person.split("_")[0].lower()
        for suffix in (".glb", ".vrm"):
            name = f"rocketbox_{key}_fbx_to_{suffix[1:]}"
            avatars[name] = _one(name, fbx, reference.document, work / f"{name}{suffix}", log)
        if person == "Male_Adult_08":
            glb = write_gltf_avatar(reference, work / "rocketbox_male_input.glb")
            name = "rocketbox_male_glb_in_place"
            avatars[name] = _one(name, glb, reference.document, work / f"{name}.glb", log)
        # the same body as a plain GLB (bind pose, no skeleton): the head found by geometry
        [layout] = mesh_vertices(reference)
        static = work / f"rocketbox_{key}_static_input.glb"
        trimesh.Trimesh(layout.world, layout.faces, process=False).export(static)
        name = f"rocketbox_{key}_static_glb"
        document = read_gltf_avatar(static).document
        avatars[name] = _one(name, static, document, work / f"{name}.glb", log)
    capture = load_livelinkface(args.data_dir)
    active = int(np.argmax(capture.weights.sum(axis=1)))
    frame = {arkit_name_of(n): float(w) for n, w in zip(capture.names, capture.weights[active],
             strict=True) if arkit_name_of(n) is not None}  # fmt: skip
    for name, entry in avatars.items():
        if not entry["ok"]:
            continue
        rigged = work / entry["output"]
        entry["vertices_rigged"] = _vertices_rigged(rigged)
        person = "Male_Adult_08" if "_male_" in name else "Female_Adult_01"
        entry["motion"] = _motion(rigged, data_file(f"rocketbox/{person}_facial.fbx",
                                                    args.data_dir), capture)  # fmt: skip
        if rigged.suffix == ".glb":
            png = out / f"{name}.png"
            entry["screenshot"] = png.name if _screenshot(rigged, png, frame) else None
        log(f"{name}: motion {entry['motion']['mean_mm']:.2f} mm mean")
    fbx = data_file("rocketbox/Male_Adult_08_facial.fbx", args.data_dir)
    seconds_cli = _cli_seconds(fbx, work / "cli.glb")
    results = with_provenance({"avatars": avatars, "cli_seconds_male_fbx": seconds_cli}, command)
    save_results(out, results, _table(avatars, seconds_cli))
    shutil.rmtree(work)  # the avatars are re-made by the command; only the numbers are kept
    record_command(out, command)
    log(f"wrote {out / 'results.json'} and {out / 'table.md'}")
    return results


if __name__ == "__main__":
    main()

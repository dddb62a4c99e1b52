"""Whole avatars in, the same avatars with a face rig out: ``canrig autorig`` on the two
Rocketbox whole-body FBX files (GLB and VRM out) and on a GLB avatar (the male FBX written as
GLB first, then rigged in place).

    python experiments/avatar.py --out experiments/results/avatar

Per avatar: ``ok``, ``seconds`` (the command, end to end), ``head_meshes``,
``vertices_rigged``, ``kept`` (nodes, skins, joints, materials, textures, animations of the
output equal to the input's glTF: for an FBX, the GLB ``rig.avatar_from_fbx`` makes of it),
``validator_errors`` (Khronos glTF validator), ``three_js_loaded`` (three.js GLTFLoader in
Node, the face mesh's targets by name), ``vrm_loaded`` (@pixiv/three-vrm, every expression
present; where a .vrm is written). ``motion`` (the rig against the artist's shapes in motion)
is not measured here. ``--quick`` runs the male FBX only.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import time
import warnings
from pathlib import Path

from canrig_jax import run_command
from canrig_jax._io import save_results
from canrig_jax._provenance import experiment_command, record_command, with_provenance
from canrig_jax.data import data_file, load_fbx_scene
from canrig_jax.rig import (
    VRM_PRESETS,
    avatar_from_fbx,
    find_gltf_validator,
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
    """``canrig autorig SOURCE -o OUT`` and what the output keeps and loads in."""
    start = time.perf_counter()
    status = run_command(["autorig", str(source), "-o", str(out), "--quiet", "--extras",
                          "visemes,rpm"])  # fmt: skip
    seconds = time.perf_counter() - start
    log(f"{name}: exit {status} in {seconds:.1f} s")
    entry = {"input": source.name, "output": out.name, "ok": status == 0, "seconds": seconds}
    if status != 0:
        return entry
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


def _vertices_rigged(out: Path) -> int:
    import numpy as np

    from canrig_jax.rig import accessor_array

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


def _table(avatars: dict) -> str:
    lines = [
        "| avatar | ok | seconds | head meshes | vertices rigged | targets | kept (all) | "
        "validator errors | three.js | three-vrm |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, a in avatars.items():
        kept = a.get("kept", {})
        lines.append(
            f"| {name} | {a['ok']} | {a['seconds']:.1f} | {', '.join(a.get('head_meshes', []))} "
            f"| {a.get('vertices_rigged', '')} | {a.get('targets', '')} | "
            f"{all(kept.values()) if kept else ''} | {a.get('validator_errors', 'n/a')} | "
            f"{a.get('three_js_loaded', 'n/a')} | {a.get('vrm_loaded', 'n/a')} |"
        )
    lines += [
        "",
        "`seconds`: `canrig autorig` run in this one process, one avatar after another (the "
        "first run compiles; a fresh `canrig autorig` process on a Rocketbox body took about "
        "11 s on this 2-core machine). `motion` is not measured here. The artist's blend "
        "shapes are ignored; targets: 51 RigAnyFace ARKit shapes + 20 extras (`--extras "
        "visemes,rpm`).",
    ]
    return "\n".join(lines) + "\n"


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
    for entry in avatars.values():
        if entry["ok"]:
            entry["vertices_rigged"] = _vertices_rigged(work / entry["output"])
        entry["motion"] = None  # not measured here
    results = with_provenance({"avatars": avatars}, command)
    save_results(out, results, _table(avatars))
    shutil.rmtree(work)  # the avatars are re-made by the command; only the numbers are kept
    record_command(out, command)
    log(f"wrote {out / 'results.json'} and {out / 'table.md'}")
    return results


if __name__ == "__main__":
    main()

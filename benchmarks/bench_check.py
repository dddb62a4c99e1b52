"""Speed of the rigger's checks under a take (target: ``canrig check RIG --take CSV`` <= 10 s
end to end on a ~5,000-vertex rig with a 300-frame take).

    python benchmarks/bench_check.py [--repeats 3] [--out FILE]

The rig: ``canrig autorig``'s (``auto_rig``, the default method) of the MakeHuman head (4,920
vertices, 51 shapes and 42 correctives), written as a .glb. The take: the data folder's Live
Link capture (180 frames) played forward and then back for 120 frames (300 frames, no jump),
written as a Live Link Face CSV. Rows, one process, median over ``--repeats`` after one
warm-up call (compilation):

- **check_rig, one call** (every check, the take's 300 frames): the latency a user waits for
  in Python;
- its parts: the rig evaluated at every frame, flipped triangles, self-intersections (the
  compiled test over the near pairs, the neutral's broad phase kept from the call before),
  the broad phase itself (built once per neutral), and the checks of single shapes (blink,
  jaw, eyes, teeth, symmetry, locality: the rest);
- **reference: self-intersections by the NumPy test**, every near pair of the broad phase in
  every frame (what the compiled, frame-batched test computes): against it, the compiled test;
- **canrig check RIG --take CSV**, end to end in a fresh process, warm (the second of two
  runs: the operating system's caches and the compiled programs kept), against the target.

A Markdown table is printed (and written to ``--out``); the load average is stated with it.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from canrig_jax._io import save_text
from canrig_jax.autorig import auto_rig, check_rig, load_makehuman
from canrig_jax.autorig._rig_checks import _head
from canrig_jax.data import capture_from_weights, load_livelinkface, write_livelink_csv
from canrig_jax.mesh import _motion as motion
from canrig_jax.mesh import edge_stretch, flipped_triangles, self_intersections
from canrig_jax.rig import UNIT_IN_CM, evaluate_batch, export_gltf, load_gltf_rig

TARGET_S = 10.0
TAKE_FRAMES = 300


def median_seconds(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def take_of(frames: int, data_dir=None):
    """The capture forward, then back, for ``frames`` frames (a ``LiveLinkCapture``)."""
    capture = load_livelinkface(data_dir)
    weights = np.asarray(capture.weights)
    back = weights[::-1][1 : frames - len(weights) + 1]
    return capture_from_weights(np.concatenate([weights, back]), list(capture.names), capture.fps)


def cli_seconds(rig_path: Path, take_path: Path) -> float:
    """``canrig check RIG --take CSV`` in a fresh process (s); exit 0 or 1 (a failed check)."""
    script = Path(sys.executable).with_name("canrig")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "canrig_jax._commands"]
    start = time.perf_counter()
    run = subprocess.run(
        command + ["check", str(rig_path), "--take", str(take_path), "--quiet"],
        capture_output=True,
        text=True,
        check=False,
    )
    seconds = time.perf_counter() - start
    if run.returncode not in (0, 1):
        raise RuntimeError(f"canrig check: {run.stderr[-2000:]}")
    return seconds


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")

    head = load_makehuman(args.data_dir)
    with tempfile.TemporaryDirectory() as tmp:
        rig_path, take_path = Path(tmp) / "makehuman.glb", Path(tmp) / "take.csv"
        export_gltf(auto_rig(head.neutral, head.faces).rig, rig_path)
        take = take_of(TAKE_FRAMES, args.data_dir)
        write_livelink_csv(take_path, take)
        rig = load_gltf_rig(rig_path)  # what canrig check reads
        poses = take.weights_for(rig.names, missing="zero")

        check_rig(rig, poses)  # compiles, builds the broad phase
        total = median_seconds(lambda: check_rig(rig, poses), args.repeats)
        parts = _head(rig, "+y", "+z")
        scale = UNIT_IN_CM[rig.units]
        frames = np.asarray(evaluate_batch(rig, poses, chunk=64), np.float64) * scale
        mesh = (frames, parts.neutral, parts.faces)
        skin = parts.skin_faces
        evaluate_s = median_seconds(
            lambda: np.asarray(evaluate_batch(rig, poses, chunk=64)), args.repeats
        )
        flips_s = median_seconds(lambda: flipped_triangles(*mesh, mask=skin), args.repeats)
        crossings_s = median_seconds(lambda: self_intersections(*mesh, mask=skin), args.repeats)
        stretch_s = median_seconds(
            lambda: edge_stretch(frames, parts.neutral, parts.faces[skin]), args.repeats
        )
        skin_faces = np.ascontiguousarray(parts.faces[skin])
        broad_s = median_seconds(
            lambda: motion._build_near_pairs(parts.neutral, skin_faces, 0.5), args.repeats
        )
        pairs = motion._build_near_pairs(parts.neutral, skin_faces, 0.5)
        seg, tri = pairs.edges[pairs.e], pairs.faces[pairs.f]
        x32 = frames.astype(np.float32)
        numpy_s = median_seconds(
            lambda: [motion._segment_crosses_triangle(f[seg], f[tri]).sum() for f in x32], 1
        )
        shapes_s = total - evaluate_s - flips_s - crossings_s - stretch_s

        cli_seconds(rig_path, take_path)  # warms the caches and keeps the compiled programs
        cli_s = statistics.median(cli_seconds(rig_path, take_path) for _ in range(args.repeats))

    def share(seconds):
        return f"{seconds:.3f} ({seconds / total:.0%} of the call)"

    rows = [
        f"# canrig check under a take: {rig.n_vertices} vertices, {rig.n_blendshapes} shapes, "
        f"{len(poses)} frames",
        "",
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
        f"{os.getloadavg()[0]:.1f}; median of {args.repeats}; seconds",
        "",
        "| step | seconds |",
        "|---|---|",
        f"| check_rig, one call (every check, {len(poses)} frames) | {total:.3f} |",
        f"| rig evaluated at every frame | {share(evaluate_s)} |",
        f"| flipped triangles | {share(flips_s)} |",
        f"| self-intersections, compiled ({len(pairs.e):,} near pairs) | {share(crossings_s)} |",
        f"| edge stretch | {share(stretch_s)} |",
        f"| checks of single shapes (blink, jaw, eyes, teeth, symmetry, locality) "
        f"| {share(shapes_s)} |",
        f"| self-intersections' broad phase (once per neutral, then kept) | {broad_s:.3f} |",
        f"| reference: self-intersections by the NumPy test of every near pair | {numpy_s:.3f} "
        f"(the compiled test {numpy_s / crossings_s:.1f}x faster) |",
        f"| canrig check RIG --take CSV, fresh process, warm | {cli_s:.3f} "
        f"({cli_s / TARGET_S:.0%} of the {TARGET_S:g} s target) |",
        "",
        f"- <= {TARGET_S:g} s end to end: {'met' if cli_s <= TARGET_S else 'NOT met'}.",
    ]
    text = "\n".join(rows) + "\n"
    print(text)
    if args.out is not None:
        save_text(args.out, text)


if __name__ == "__main__":
    main()

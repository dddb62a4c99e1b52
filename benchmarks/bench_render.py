"""Speed of the differentiable rasteriser (issue 25: "256^2 at ~1,750 vertices fast enough to
train with on this CPU").

    python benchmarks/bench_render.py [--size 256] [--repeats 5] [--views 4] [--out FILE]

The generic ICT head (all 17 parts) decimated to ~1,750 vertices, a perspective camera 60 cm
in front. Rows (median over ``--repeats``, warm jit, one process):

- **forward**: ``rasterise`` silhouette + depth, one view;
- **forward + backward**: value and gradient of a silhouette loss with respect to the
  vertices, one view (frames per second = 1 / latency);
- **batched forward + backward**: the same loss over ``--views`` views at once
  (``jax.vmap`` over cameras), frames per second = views / latency;
- **forward, dense schedule**: every triangle at every pixel (the reference schedule the
  tiles wrap), one view, for scale;
- the largest candidate count of a tile (> ``faces_per_tile`` means far triangles were
  dropped in that tile) and the settings.

On the shared 2-core VM timings vary with the other jobs; the table prints the load average.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from canrig_jax import save_text
from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate
from canrig_jax.render import RasterSettings, orbit_cameras, rasterise


def median_seconds(function, repeats: int) -> float:
    jax.block_until_ready(function())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--vertices", type=int, default=1750)
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-dense", action="store_true", help="skip the dense-schedule row")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    ict = load_ict(None, parts=None)
    d = decimate(ict.neutral, ict.faces, args.vertices)
    vertices = jnp.asarray(d.vertices, jnp.float32)
    faces = jnp.asarray(d.faces, jnp.int32)
    centre = np.asarray(vertices.mean(0))
    yaws = np.linspace(-30.0, 30.0, args.views)
    cameras = orbit_cameras(centre, 60.0, yaws, image_size=args.size)
    front = orbit_cameras(centre, 60.0, [0.0], image_size=args.size)
    front = jax.tree.map(lambda x: x[0], front)
    settings = RasterSettings()
    target = rasterise(vertices, faces, front, settings=settings)

    forward = jax.jit(lambda v: rasterise(v, faces, front, settings=settings).silhouette)

    def loss(v, camera, target):
        return jnp.mean((rasterise(v, faces, camera, settings=settings).silhouette - target) ** 2)

    backward = jax.jit(jax.value_and_grad(lambda v: loss(v, front, target.silhouette)))
    targets = jax.vmap(lambda c: rasterise(vertices, faces, c, settings=settings).silhouette)(
        cameras
    )
    batched = jax.jit(
        jax.value_and_grad(
            lambda v: jnp.sum(jax.vmap(lambda c, t: loss(v, c, t))(cameras, targets))
        )
    )
    moved = vertices + 0.01
    rows = []
    t = median_seconds(lambda: forward(moved), args.repeats)
    rows.append(("forward, one view", t, 1.0 / t))
    t = median_seconds(lambda: backward(moved), args.repeats)
    rows.append(("forward + backward, one view", t, 1.0 / t))
    t = median_seconds(lambda: batched(moved), args.repeats)
    rows.append((f"forward + backward, {args.views} views (vmap)", t, args.views / t))
    if not args.no_dense:
        dense = RasterSettings(tile_size=None)
        dense_forward = jax.jit(lambda v: rasterise(v, faces, front, settings=dense).silhouette)
        t = median_seconds(lambda: dense_forward(moved), 1)
        rows.append(("forward, dense schedule (reference), one view", t, 1.0 / t))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        f"# Rasteriser speed, {args.size}^2, ICT head {len(d.vertices)} vertices / "
        f"{len(d.faces)} faces",
        "",
        f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load "
        f"average {load:.1f} at the end; jax {jax.__version__}; settings: sigma "
        f"{settings.sigma} px, gamma {settings.gamma}, tiles of {settings.tile_size} px, "
        f"{settings.faces_per_tile} faces per tile (largest tile count here: "
        f"{int(target.max_faces_in_tile)}); median of {args.repeats}.",
        "",
        "| what | latency (ms) | frames / s |",
        "|---|---|---|",
    ]
    lines += [f"| {name} | {1000 * t:.0f} | {fps:.2f} |" for name, t, fps in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        save_text(args.out, text)


if __name__ == "__main__":
    main()

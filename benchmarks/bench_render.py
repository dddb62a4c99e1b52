"""Speed of the differentiable rasterisers (issue 25: "256^2 at ~1,750 vertices fast enough to
train with on this CPU").

    python benchmarks/bench_render.py [--size 256] [--repeats 5] [--views 4] [--out FILE]

The generic ICT head (all 17 parts) decimated to ~1,750 vertices, a perspective camera 60 cm
in front. Both rasterisers, timed in the same process (median over ``--repeats``, warm jit),
on the same outputs: a silhouette, the depth and a 2-channel per-vertex attribute (a 2D
displacement field), and the same loss (squared silhouette error against a shifted target +
mean depth + mean square attribute):

- **soft**: ``rasterise`` (SoftRas-style, tiles of 8 px, 128 faces per tile);
- **fast**: ``rasterise_hard`` (z-buffer, no gradient) + ``interpolate`` (differentiable
  barycentrics, depth, attribute) + ``silhouette`` (analytic antialiasing of the silhouette
  edges, which carries the mask's gradient);

rows: forward, one view; forward + backward (value and gradient with respect to the
vertices), one view; forward + backward over ``--views`` views at once (``jax.vmap`` over
cameras; frames per second = views / latency); the fast path's visibility alone; optionally
(``--dense``) the soft rasteriser's dense schedule, for scale. The ratio column is soft /
fast latency of the matching row.

On the shared 2-core VM timings vary with the other jobs; the table prints the load average
before and after.
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from canrig_jax._io import save_text
from canrig_jax._timing import median_ms
from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate
from canrig_jax.render import (
    RasterSettings,
    interpolate,
    orbit_cameras,
    rasterise,
    rasterise_hard,
    screen_displacement,
    silhouette,
)


def median_seconds(function, repeats: int) -> float:
    """Median seconds after one warm-up call."""
    return median_ms(function, repeats) / 1e3


def load() -> float:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--vertices", type=int, default=1750)
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--soft-repeats", type=int, default=3, help="the soft rows are slow")
    parser.add_argument("--dense", action="store_true", help="add the dense-schedule row")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    load_before = load()
    ict = load_ict(None, parts=None)
    d = decimate(ict.neutral, ict.faces, args.vertices)
    vertices = jnp.asarray(d.vertices, jnp.float32)
    faces = jnp.asarray(d.faces, jnp.int32)
    centre = np.asarray(vertices.mean(0))
    yaws = np.linspace(-30.0, 30.0, args.views)
    cameras = orbit_cameras(centre, 60.0, yaws, image_size=args.size)
    front = jax.tree.map(lambda x: x[0], orbit_cameras(centre, 60.0, [0.0], image_size=args.size))
    settings = RasterSettings()
    # a 2-channel attribute: the screen displacement of a small rigid motion
    shifted = vertices + jnp.asarray([0.3, 0.2, 0.0])
    attributes = screen_displacement(front, vertices, shifted)

    def soft(v, camera):
        r = rasterise(v, faces, camera, attributes, settings=settings)
        return r.silhouette, r.depth * r.silhouette, r.attributes

    def fast(v, camera):
        fragments = rasterise_hard(v, faces, camera)
        values = interpolate(v, faces, camera, fragments, attributes)
        return silhouette(v, faces, camera, fragments), values.depth, values.attributes

    def make(render):
        def loss(v, camera, target):
            mask, depth, attr = render(v, camera)
            return jnp.mean((mask - target) ** 2) + 1e-3 * jnp.mean(depth) + jnp.mean(attr**2)

        targets = jax.vmap(lambda c: render(shifted, c)[0])(cameras)
        target = render(shifted, front)[0]
        forward = jax.jit(lambda v: render(v, front))
        backward = jax.jit(jax.value_and_grad(lambda v: loss(v, front, target)))
        batched = jax.jit(
            jax.value_and_grad(
                lambda v: jnp.sum(jax.vmap(lambda c, t: loss(v, c, t))(cameras, targets))
            )
        )
        return forward, backward, batched

    moved = vertices + 0.01
    rows = {}
    for name, render, repeats in (("fast", fast, args.repeats), ("soft", soft, args.soft_repeats)):
        forward, backward, batched = make(render)
        t = median_seconds(lambda f=forward: f(moved), repeats)
        rows[("forward, one view", name)] = (t, 1.0 / t)
        t = median_seconds(lambda f=backward: f(moved), repeats)
        rows[("forward + backward, one view", name)] = (t, 1.0 / t)
        t = median_seconds(lambda f=batched: f(moved), repeats)
        rows[(f"forward + backward, {args.views} views (vmap)", name)] = (t, args.views / t)
    visibility = jax.jit(lambda v: rasterise_hard(v, faces, front))
    t = median_seconds(lambda: visibility(moved), args.repeats)
    rows[("visibility only (rasterise_hard), one view", "fast")] = (t, 1.0 / t)
    if args.dense:
        dense = RasterSettings(tile_size=None)
        dense_forward = jax.jit(lambda v: rasterise(v, faces, front, settings=dense).silhouette)
        t = median_seconds(lambda: dense_forward(moved), 1)
        rows[("forward, dense schedule (reference), one view", "soft")] = (t, 1.0 / t)
    fragments = rasterise_hard(vertices, faces, front)
    tiles = rasterise(vertices, faces, front, settings=settings).max_faces_in_tile
    load_after = load()
    lines = [
        f"# Rasteriser speed, {args.size}^2, ICT head {len(d.vertices)} vertices / "
        f"{len(d.faces)} faces",
        "",
        f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load "
        f"average (1 min) {load_before:.1f} before, {load_after:.1f} after (other jobs share "
        f"the 2 cores: timings are inflated by them); jax {jax.__version__}; median of "
        f"{args.repeats} (fast) / {args.soft_repeats} (soft) warm calls, one process.",
        "",
        f"- fast: ``rasterise_hard`` (chunks of 4 px, budget 4 x the image; overflow here: "
        f"{int(fragments.overflow)}) + ``interpolate`` + ``silhouette`` (antialiased edges);",
        f"- soft: ``rasterise``, sigma {settings.sigma} px, gamma {settings.gamma}, tiles of "
        f"{settings.tile_size} px, {settings.faces_per_tile} faces per tile (largest tile "
        f"count here: {int(tiles)});",
        "- outputs: silhouette, depth, a 2-channel attribute; loss: squared silhouette error +"
        " mean depth + mean square attribute; gradient with respect to the vertices.",
        "",
        "| what | fast (ms) | fast frames / s | soft (ms) | soft frames / s | soft / fast |",
        "|---|---|---|---|---|---|",
    ]
    for what in dict.fromkeys(w for w, _ in rows):
        fast_row, soft_row = rows.get((what, "fast")), rows.get((what, "soft"))
        cells = []
        for row in (fast_row, soft_row):
            cells += ["-", "-"] if row is None else [f"{1000 * row[0]:.1f}", f"{row[1]:.2f}"]
        ratio = f"{soft_row[0] / fast_row[0]:.0f}" if fast_row and soft_row else "-"
        lines.append(f"| {what} | " + " | ".join(cells) + f" | {ratio} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        save_text(args.out, text)


if __name__ == "__main__":
    main()

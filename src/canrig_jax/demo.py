"""Main demo: build (or load from cache) the ict-quartic rig on the real ICT face, drive it
with the real Live Link Face capture, and compare linear and quartic rigs against the
nonlinear deformation-gradient blend; then invert the rig (Racković et al. 2023): recover the
capture's weights from noisy meshes with quartic coordinate descent, batched over the take.

    python -m canrig_jax.demo [--out DIR] [--data-dir DIR]

Progress lines (``[  12.3 s] ...``) and warnings go to stderr, results to stdout.
"""

import argparse
from collections.abc import Sequence
from pathlib import Path

from ._commands import _Progress
from ._warnings import print_warnings

BLEND_CHUNK = 60
"""Frames of the deformation-gradient blend between two progress lines."""


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="canrig_jax demo on the ICT face")
    parser.add_argument("--out", type=Path, default=Path("out/demo"))
    parser.add_argument("--data-dir", default=None)
    args = parser.parse_args(argv)
    with print_warnings("canrig_jax.demo"):
        _demo(args, _Progress(quiet=False))


def _demo(args, progress) -> None:
    progress("loading JAX and the library")
    import matplotlib.pyplot as plt
    import numpy as np

    from . import inverse
    from ._metrics import CM_TO_MM, per_vertex_distance
    from .data import load_livelinkface
    from .inverse import summarize
    from .mesh import DeformationGradientBlend
    from .render import plot_vertex_scalar, save_figure
    from .rig import evaluate_batch, ict_quartic_rig

    progress("the ict-quartic rig (built once, then read from the cache)")
    rig, report = ict_quartic_rig(args.data_dir)
    print(
        f"ict-quartic rig: {rig.n_vertices} vertices, {rig.n_blendshapes} blendshapes, "
        f"{rig.n_correctives(2)} pairs, {rig.n_correctives(3)} triplets, "
        f"{rig.n_correctives(4)} quads; max error at selected corners "
        f"{report.corner_max_error * CM_TO_MM:.1e} mm"
    )
    capture = load_livelinkface(args.data_dir).weights_for(rig.names, missing="zero")
    progress(f"the linear and quartic rigs at the capture's {len(capture)} frames")
    quartic = np.asarray(evaluate_batch(rig, capture))
    linear = np.asarray(evaluate_batch(rig.linear(), capture))
    progress("the nonlinear deformation-gradient blend: factorising its Poisson system")
    assert rig.faces is not None  # the ICT rig carries its triangles
    blend = DeformationGradientBlend(rig.neutral, rig.deltas, rig.faces)
    nonlinear = []
    for start in range(0, len(capture), BLEND_CHUNK):
        stop = min(start + BLEND_CHUNK, len(capture))
        progress(f"the nonlinear deformation-gradient blend, frames {start}-{stop - 1}")
        nonlinear.append(blend(capture[start:stop]))
    nonlinear = np.concatenate(nonlinear)
    for name, mesh in (("linear", linear), ("quartic", quartic)):
        err = per_vertex_distance(mesh, nonlinear) * CM_TO_MM
        print(
            f"{name:8s} rig vs nonlinear blend over {len(capture)} Live Link frames: "
            f"mean {err.mean():.3f} mm, p95 {np.percentile(err, 95):.3f} mm, max {err.max():.2f} mm"
        )
    frame = int(np.argmax(np.abs(quartic - linear).sum(axis=(1, 2))))
    fig, axes = plt.subplots(1, 2, figsize=(7, 4.2))
    for ax, mesh, label in zip(axes, (linear, quartic), ("linear", "quartic"), strict=True):
        err = per_vertex_distance(mesh[frame], nonlinear[frame]) * CM_TO_MM
        mapper = plot_vertex_scalar(
            ax, nonlinear[frame], rig.faces, err, vmax=5.0, title=f"{label}, frame {frame}"
        )
    fig.colorbar(mapper, ax=axes, shrink=0.7, label="distance to nonlinear blend (mm)")
    args.out.mkdir(parents=True, exist_ok=True)
    save_figure(fig, args.out / "demo_live_link.png")
    print(f"wrote {args.out / 'demo_live_link.png'}")

    noise = np.random.default_rng(0).normal(0.0, np.sqrt(0.03), quartic.shape)
    progress("preparing the inverse rig (the quartic objective's M and Q)")
    problem = inverse.prepare(rig)
    for method in (inverse.QuarticCD(alpha=5.0, passes=5), inverse.Cetinaslan(alpha=1.0)):
        progress(f"inverting {len(capture)} noisy frames with {method}")
        solution = inverse.solve_sequence(problem, (quartic + noise).astype(np.float32), method)
        scores = summarize(rig, np.asarray(solution.weights), quartic)
        print(
            f"inverse rig, {type(method).__name__} (alpha {method.alpha}) on the take + noise "
            f"(variance 0.03 cm^2): RMSE {scores['rmse_mean_mm']:.3f} mm, "
            f"{scores['cardinality']:.1f} active weights of {rig.n_blendshapes}"
        )


if __name__ == "__main__":
    main()

"""nox sessions: tests, lint, bench, demo, experiments."""

import os
from pathlib import Path

import nox

nox.options.sessions = ["tests", "lint"]
nox.options.default_venv_backend = "venv"


TEST_WORKERS = min(2, os.cpu_count() or 1)
"""Test processes (pytest-xdist). Most of the suite's time is XLA compilation, which runs on
one core per process, so two processes fill the 2-core CI machine (12:38 min serial, 8:45 with
two, 2026-12-02); more would each hold another copy of the session's rigs (2-5 GB)."""


@nox.session
def tests(session):
    """Default test run (fast; long experiments are marked slow), one file per worker
    (``--dist loadfile``: a module's fixtures are built once). ``-- -n 0`` runs serially."""
    session.install("-e", ".[dev]")
    workers = ("-n", str(TEST_WORKERS), "--dist", "loadfile")
    session.run("python", "-m", "pytest", *workers, *session.posargs)


@nox.session
def slow(session):
    """Long tests and full experiments (-m slow)."""
    session.install("-e", ".[dev]")
    session.run("python", "-m", "pytest", "-m", "slow", *session.posargs)


@nox.session
def stress(session):
    """The compiled fits that once deadlocked, 200 calls each, idle and beside a CPU hog, in
    subprocesses with timeouts (``tests/test_deadlock.py``'s slow tests)."""
    session.install("-e", ".[dev]")
    session.run("python", "-m", "pytest", "-m", "slow", "tests/test_deadlock.py", *session.posargs)


@nox.session
def distributed(session):
    """Two real local processes (jax.distributed): the slow tests that compare them with one
    process and kill one, then the throughput with one and two processes (under 5 minutes
    each on 2 cores)."""
    session.install("-e", ".[dev]")
    session.run("python", "-m", "pytest", "-m", "slow", "-p", "no:xdist", "tests/distributed")
    if "--no-experiment" not in session.posargs:
        session.run(
            "python", "experiments/distributed.py", "--out", "experiments/results/distributed"
        )


@nox.session
def lint(session):
    """ruff (lint and format) on the code, then pyright (basic mode, ``[tool.pyright]`` in
    pyproject.toml) on the package; the annotations pyright reads statically are the ones the
    test run checks at run time (jaxtyping's import hook with beartype, ``tests/conftest.py``)."""
    session.install("-e", ".[dev]")
    session.run("ruff", "check", "src", "tests", "experiments", "benchmarks", "noxfile.py")
    session.run("ruff", "format", "--check", "src", "tests", "experiments", "benchmarks")
    session.run("pyright", "--pythonpath", os.path.join(session.bin, "python"))


@nox.session
def bench(session):
    """Speed benchmarks against reference implementations, printed as tables."""
    session.install("-e", ".[jaxopt]")  # bench_lbfgsb times inverse.JaxoptLBFGSB
    for script in sorted(Path("benchmarks").glob("bench_*.py")):
        session.run("python", str(script))


@nox.session
def demo(session):
    """Main demo on the default data."""
    session.install("-e", ".")
    session.run("python", "-m", "canrig_jax.demo", *session.posargs)


SQUARED_RUNS = (
    ("autorig_squared", "squared_static", "7000", ()),
    ("autorig_balanced", "squared_static_balanced", "7000", ("autorig_squared",)),
    (
        "autorig_half_balanced",
        "squared_static_half_balanced",
        "7000",
        ("autorig_squared", "autorig_balanced"),
    ),
    ("autorig_balanced_03", "squared_static_balanced_0.3", "7000", ("autorig_half_balanced",)),
    (
        "autorig_half_balanced_long",
        "squared_static_half_balanced",
        "12000",
        ("autorig_half_balanced",),
    ),
)
"""The ``autorig_long`` recipe with the squared loss: (folder, --raf-loss, --steps, the runs
evaluated next to it besides ``autorig_long``). The last, ``autorig_half_balanced_long``, is the
default RigAnyFace (``canrig_jax.autorig.DEFAULT_CHECKPOINT``) since 2026-12-04."""
STANDARD_EXPERIMENTS = (
    ("build_quartic_rig.py", "--out", "experiments/results/build_quartic_rig"),
    ("inverse_rig.py", "--out", "experiments/results/inverse_rig"),
    ("inverse_rig_sparsity.py", "--out", "experiments/results/inverse_rig"),
    ("inverse_rig_exclusions.py", "--out", "experiments/results/inverse_rig"),  # its section
    ("inverse_rig_retarget.py", "--out", "experiments/results/inverse_rig"),  # its section
    ("inverse_rig_temporal.py", "--out", "experiments/results/inverse_rig"),  # its section
    ("inverse_rig_temporal.py", "--out", "experiments/results/inverse_rig", "--validation-split"),
    ("inverse_rig_streaming.py", "--out", "experiments/results/inverse_rig"),  # its section
    ("distributed.py", "--out", "experiments/results/distributed"),
    ("avatar.py", "--out", "experiments/results/avatar"),
    ("wpse.py", "--out", "experiments/results/wpse"),
    ("wpse_timing.py", "--out", "experiments/results/wpse"),  # Table 1's rows, into wpse's
    ("mesh_foundations.py", "--out", "experiments/results/mesh_foundations"),
    ("autorig.py", "--out", "experiments/results/autorig", "--no-progress"),
    # RigAnyFace width 64, 4,000 steps, and its step-matched ablation, then their evaluation
    *(
        (
            "autorig_train.py",
            name,
            *("--out", "experiments/results/autorig_wide", "--no-progress"),
            *("--raf-loss", "euclidean_static", "--raf-width", "64", "--steps", "4000"),
            *("--train-identities", "40"),
        )
        for name in ("raf", "raf_no_global_encoder")
    ),
    (
        "autorig_evaluate.py",
        *("--out", "experiments/results/autorig_wide", "--no-progress"),
        *(
            f"experiments/results/{checkpoint}.eqx"
            for checkpoint in (
                "autorig/checkpoint_raf",
                "autorig_retrain/checkpoint_raf",
                "autorig_retrain/checkpoint_raf_no_global_encoder",
                "autorig_wide/checkpoint_raf",
                "autorig_wide/checkpoint_raf_no_global_encoder",
            )
        ),
    ),
    # the loss ablation of pure RigAnyFace (width 32, 1,200 steps), then its evaluation
    *(
        (
            "autorig_train.py",
            "raf",
            *("--out", f"experiments/results/autorig_loss/{loss}", "--no-progress"),
            *("--steps", "1200", "--raf-loss", loss),
        )
        for loss in ("squared", "squared_static", "euclidean")
    ),
    (
        "autorig_evaluate.py",
        *("--out", "experiments/results/autorig_loss", "--no-progress"),
        *(
            f"experiments/results/{checkpoint}.eqx"
            for checkpoint in (
                "autorig_loss/squared/checkpoint_raf",
                "autorig_loss/squared_static/checkpoint_raf",
                "autorig_loss/euclidean/checkpoint_raf",
                "autorig_retrain/checkpoint_raf",
                "autorig/checkpoint_raf_dt_residual",
            )
        ),
    ),
    # the default RigAnyFace of 2026-12-03: the same recipe on 7,000 steps, then its evaluation
    (
        "autorig_train.py",
        "raf",
        *("--out", "experiments/results/autorig_long", "--no-progress"),
        *("--raf-loss", "euclidean_static", "--raf-width", "64", "--steps", "7000"),
        *("--train-identities", "40"),
    ),
    (
        "autorig_evaluate.py",
        *("--out", "experiments/results/autorig_long", "--no-progress"),
        "experiments/results/autorig_wide/checkpoint_raf.eqx",
        "experiments/results/autorig_long/checkpoint_raf.eqx",
    ),
    # that recipe with the squared loss, unbalanced, balanced per pose, part of the way and on a
    # longer schedule (the default since 2026-12-04); each evaluated next to autorig_long and the
    # runs it is compared with
    *(
        (
            "autorig_train.py",
            "raf",
            *("--out", f"experiments/results/{folder}", "--no-progress"),
            *("--raf-loss", loss, "--raf-width", "64", "--steps", steps),
            *("--train-identities", "40"),
        )
        for folder, loss, steps, _ in SQUARED_RUNS
    ),
    *(
        (
            "autorig_evaluate.py",
            *("--out", f"experiments/results/{folder}", "--no-progress"),
            *(
                f"experiments/results/{run}/checkpoint_raf.eqx"
                for run in ("autorig_long", *compared, folder)
            ),
        )
        for folder, _, _, compared in SQUARED_RUNS
    ),
    # a second seed of the default's recipe (reported, not a candidate), then its evaluation
    (
        "autorig_train.py",
        "raf",
        *("--out", "experiments/results/autorig_half_balanced_long_seed1", "--no-progress"),
        *("--raf-loss", "squared_static_half_balanced", "--raf-width", "64", "--steps", "12000"),
        *("--train-identities", "40", "--seed", "1"),
    ),
    (
        "autorig_evaluate.py",
        *("--out", "experiments/results/autorig_half_balanced_long_seed1", "--no-progress"),
        *(
            f"experiments/results/{run}/checkpoint_raf.eqx"
            for run in (
                "autorig_long",
                "autorig_half_balanced_long",
                "autorig_half_balanced_long_seed1",
            )
        ),
    ),
    # the residual models with face placement on MakeHuman
    (
        "autorig_evaluate.py",
        *("--out", "experiments/results/autorig_residual_face", "--no-progress"),
        "experiments/results/autorig/checkpoint_raf_anchored_dt_residual.eqx",
        "experiments/results/autorig/checkpoint_raf_dt_residual.eqx",
    ),
    (
        "canrig_train.py",
        *("--out", "experiments/results/canrig", "--minutes", "45", "--steps", "36000"),
        *("--decay-start", "16000", "--decay-steps", "20000", "--decay-floor", "0.02"),
        *("--no-progress", "--width", "96", "--fourier", "6", "--farthest-sets", "16"),
        *("--farthest-metric", "geodesic"),
        *("--p-farthest", "0.9", "--p-eval-radius", "0.9", "--p-neutral", "0.5"),
        "--interpolation-prior",
    ),
    (
        "canrig_eval.py",
        "--checkpoint",
        "experiments/results/canrig/checkpoint.eqx",
        "--out",
        "experiments/results/canrig",
    ),
    (
        "canrig_train.py",
        *("--out", "experiments/results/canrig_workflows/model", "--minutes", "80"),
        *("--steps", "28000", "--decay-start", "10000", "--decay-steps", "18000"),
        *("--decay-floor", "0.02", "--no-progress", "--width", "96", "--fourier", "6"),
        "--interpolation-prior",
    ),
    (
        "canrig_workflows.py",
        *("--checkpoint", "experiments/results/canrig_workflows/model/checkpoint.eqx"),
        *("--out", "experiments/results/canrig_workflows", "--pairs", "1000"),
        *("--fit-pairs", "100", "--fit-pairs-main", "1000", "--layer-pairs", "30"),
    ),
    (
        "canrig_workflows_dialogue.py",
        *("--checkpoint", "experiments/results/canrig_workflows/model/checkpoint.eqx"),
        *("--out", "experiments/results/canrig_workflows"),
    ),
    (
        "canrig_workflows_floor.py",
        *("--checkpoint", "experiments/results/canrig_workflows/model/checkpoint.eqx"),
        *("--out", "experiments/results/canrig_workflows", "--pairs", "1000"),
    ),
    (
        "canrig_workflows.py",
        *("--rig", "local-fit", "--out", "experiments/results/canrig_workflows_local_fit"),
        *("--pairs", "1000", "--fit-pairs", "100", "--fit-pairs-main", "1000"),
        *("--layer-pairs", "30"),
    ),
    (
        "canrig_workflows_dialogue.py",
        *("--rig", "local-fit", "--out", "experiments/results/canrig_workflows_local_fit"),
    ),
    (
        "canrig_pbs_train.py",
        *("--out", "experiments/results/canrig_pbs_attached_local_prior", "--model", "per_patch"),
        *("--local-prior", "--learning-rate", "1e-4", "--steps", "4000", "--decay-steps", "4000"),
        *("--minutes", "150", "--no-progress", "--graph", "attached"),
    ),
    (
        "canrig_pbs_train.py",
        *("--out", "experiments/results/canrig_pbs_attached_local_prior"),
        *("--model", "shape_transformer", "--steps", "4000", "--decay-steps", "4000"),
        *("--minutes", "150", "--no-progress", "--graph", "attached"),
    ),
    *(
        (
            "canrig_pbs_train.py",
            *("--out", "experiments/results/canrig_pbs_attached_local_prior", "--model", variant),
            *("--local-prior", "--learning-rate", "1e-4", "--steps", "1000"),
            *("--decay-steps", "2000", "--minutes", "60", "--tag", "_fig8"),
            *("--no-progress", "--graph", "attached"),
        )
        for variant in ("per_patch", "base_multiplied", "no_modulation")
    ),
    (
        "canrig_pbs.py",
        *("--out", "experiments/results/canrig_pbs_attached_local_prior"),
        *("--no-progress", "--graph", "attached"),
    ),
    (
        "canrig_pbs_table6_sweep.py",
        *("--out", "experiments/results/canrig_pbs_attached_local_prior"),
        *("--no-progress", "--graph", "attached", "--counts", "60", "120", "200", "400"),
    ),
    # any head: the auto_rig methods, few-shot style, templates, orientation (~15 minutes)
    ("any_head.py", "--out", "experiments/results/any_head"),
)
"""The standard configurations whose outputs are committed under experiments/results/ (the
same commands as each folder's COMMAND file)."""


@nox.session
def experiments(session):
    """Standard-configuration experiments (long: about eleven hours on 2 cores); pass script
    names to run a subset, e.g. ``nox -s experiments -- inverse_rig.py``."""
    session.install("-e", ".[jaxopt]")  # inverse_rig_sparsity times inverse.JaxoptLBFGSB
    for script, *arguments in STANDARD_EXPERIMENTS:
        if not session.posargs or script in session.posargs:
            session.run("python", f"experiments/{script}", *arguments)


@nox.session
def gltf(session):
    """The Khronos glTF validator and the three.js / three-vrm loaders (npm, into
    ./node_modules, git-ignored) and the glTF, avatar and command-line tests that use them
    (add -m slow for the end-to-end run)."""
    session.install("-e", ".[dev]")
    session.run(
        "npm",
        "install",
        "--no-save",
        "gltf-validator@2.0.0-dev.3.10",
        "three@0.187.0",
        "@pixiv/three-vrm@3.5.5",
        external=True,
    )
    session.run(
        "python",
        "-m",
        "pytest",
        "tests/rig/test_gltf_animation.py",
        "tests/test_commands.py",
        "tests/autorig/test_avatar.py",
        *session.posargs,
    )


@nox.session
def docs(session):
    """The documentation site (mkdocs-material; API reference from the docstrings, the CLI
    reference and the results pages generated at build time) built with ``--strict`` into
    ``build/site/`` (git-ignored); ``-- --site-dir DIR`` builds elsewhere."""
    session.install("-e", ".[docs]")
    session.run("mkdocs", "build", "--strict", *session.posargs)


@nox.session
def wheel(session):
    """The wheel as a user gets it: built, installed in a fresh virtualenv outside the
    repository (dependencies from the package index, no extras), then ``canrig autorig`` with
    the packaged default model and ``canrig animate`` run from a folder of their own
    (``tests/test_wheel.py``, a few minutes)."""
    session.install("-e", ".[dev]")
    session.run("python", "-m", "pytest", "-m", "slow", "-n", "0", "tests/test_wheel.py")

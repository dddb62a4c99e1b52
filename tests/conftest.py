"""Shared pytest fixtures, and the run-time type check of ``canrig_jax``.

Before anything imports ``canrig_jax``, jaxtyping's import hook decorates every function and
dataclass in it with ``jaxtyped(typechecker=beartype)``: each call checks its arguments and
return value against their annotations, array dtypes and shapes included, with the axis names
shared within the call. ``CANRIG_TYPECHECK=0`` runs the tests without it.

Tests marked ``bad_input`` (and every test under ``tests/bad_input/``) pass what the
annotations exclude on purpose, to test the library's own errors (the ones a user gets): the
check is off while they run.
"""

import os
import warnings

import jaxtyping

TYPECHECK = os.environ.get("CANRIG_TYPECHECK", "1") != "0"
"""Whether this run checks ``canrig_jax``'s annotations (``CANRIG_TYPECHECK=0``: no)."""

TYPECHECKER = "beartype.beartype(conf=beartype.BeartypeConf(is_pep484_tower=True))"
"""beartype, with an ``int`` accepted where ``float`` is annotated (PEP 484's numeric tower)."""

if TYPECHECK:
    jaxtyping.install_import_hook("canrig_jax", TYPECHECKER)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from canrig_jax.data import load_livelinkface  # noqa: E402
from canrig_jax.data._paths import resolve_data_dir  # noqa: E402

LONGEST_FILES = ("test_deadlock.py", "test_local_fit.py", "test_pbs_model.py")
"""Test files of a minute or more: collected first, so that pytest-xdist (``--dist loadfile``)
hands them out first and the two workers finish together instead of one waiting on a long file
handed out last."""


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "bad_input" in item.path.parts:
            item.add_marker(pytest.mark.bad_input)
    items.sort(key=lambda item: item.path.name not in LONGEST_FILES)  # stable: else unchanged


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """The run-time type check off while a ``bad_input`` test runs, its fixtures' set-up and
    tear-down included (a fixture may build the stand-ins the test passes); restored after."""
    if item.get_closest_marker("bad_input") is None:
        yield
        return
    before = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", before)


@pytest.fixture(scope="session")
def data_dir():
    """The real-data folder (argument, ``$CANRIG_DATA`` or ``../shared/data``)."""
    return resolve_data_dir()


@pytest.fixture(scope="session")
def _ict_quartic_build(data_dir):
    from canrig_jax.rig import ict_quartic_rig

    # Cached on disk (~/.cache/canrig_jax or $CANRIG_CACHE): ~45 s once per machine, then ~1 s.
    return ict_quartic_rig(data_dir, progress=False)


@pytest.fixture(scope="session")
def ict_quartic(_ict_quartic_build):
    """The standard ict-quartic rig (ICT face part, correctives up to order 4; cm)."""
    return _ict_quartic_build[0]


@pytest.fixture(scope="session")
def ict_quartic_report(_ict_quartic_build):
    """The ``SynthesisReport`` of the ict-quartic rig (from the cache when hit)."""
    return _ict_quartic_build[1]


@pytest.fixture(scope="session")
def ict_quartic_problem(ict_quartic):
    """``inverse.prepare(ict_quartic)``: Gram matrix, supports, LMMM bounds (~5 s)."""
    from canrig_jax import inverse

    return inverse.prepare(ict_quartic)


@pytest.fixture(scope="session")
def ict_face(data_dir):
    """The linear ICT rig on the face part (9,409 vertices, 53 expressions, faces; cm)."""
    from canrig_jax.rig import ict_linear_rig

    return ict_linear_rig(data_dir)


@pytest.fixture(scope="session")
def livelink_weights(data_dir, ict_face):
    """(180, 53) float32 Live Link Face frames retargeted onto the ICT channels."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TongueOut", category=UserWarning)
        return load_livelinkface(data_dir).weights_for(ict_face.names)


@pytest.fixture(scope="session")
def sparse_poses(ict_face):
    """(16, 53) float32 random sparse poses: 3..10 active channels, weights in (0, 1]."""
    rng = np.random.default_rng(20240601)
    k = ict_face.n_blendshapes
    poses = np.zeros((16, k), np.float32)
    for row in poses:
        active = rng.choice(k, size=rng.integers(3, 11), replace=False)
        row[active] = rng.uniform(0.05, 1.0, active.size)
    return poses


@pytest.fixture(scope="session")
def ict_face_blend(ict_face):
    """The deformation-gradient blend of all 53 ICT expressions on the face part (~7 s)."""
    from canrig_jax.mesh import DeformationGradientBlend

    return DeformationGradientBlend(
        np.asarray(ict_face.neutral), np.asarray(ict_face.deltas), np.asarray(ict_face.faces)
    )


# --------------------------------------------------------------------------- synthetic mesh
# A small face-sized mesh for contract tests that must run without the data folder (the
# data-folder tests stay the evidence of behaviour): a bumpy 10 x 10 cm sheet and smooth
# sinusoidal offsets of it as "expressions".


def synthetic_sheet(n: int = 20, size_cm: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n*n, 3) cm, faces (2(n-1)^2, 3)): a gently curved grid, two triangles per
    cell, every vertex on one connected piece."""
    u, v = np.meshgrid(np.linspace(0.0, size_cm, n), np.linspace(0.0, size_cm, n))
    z = 0.8 * np.sin(u / size_cm * np.pi) * np.cos(v / size_cm * np.pi / 2)
    vertices = np.stack([u, v, z], axis=-1).reshape(-1, 3).astype(np.float32)
    index = np.arange(n * n).reshape(n, n)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int32)
    return vertices, faces


def synthetic_expressions(vertices: np.ndarray, n_shapes: int = 12, seed: int = 0) -> np.ndarray:
    """(n_shapes, V, 3) shapes: the mesh plus smooth random sinusoidal offsets (<= ~0.5 cm)."""
    rng = np.random.default_rng(seed)
    span = np.ptp(vertices, axis=0).max()
    out = []
    for _ in range(n_shapes):
        frequency = rng.uniform(0.5, 2.0, size=(3, 3)) * 2 * np.pi / span
        phase = rng.uniform(0, 2 * np.pi, size=3)
        amplitude = rng.uniform(0.1, 0.5, size=3)
        offset = amplitude * np.sin(vertices @ frequency + phase)
        out.append(vertices + offset)
    return np.asarray(out, np.float32)


@pytest.fixture(scope="session")
def synthetic_face():
    """(vertices (400, 3) cm, faces, shapes (12, 400, 3) cm): ``synthetic_sheet`` and
    ``synthetic_expressions`` of it."""
    vertices, faces = synthetic_sheet()
    return vertices, faces, synthetic_expressions(vertices)


@pytest.fixture(scope="session")
def synthetic_rig(synthetic_face):
    """A small blendshape rig on ``synthetic_face`` (no data folder): 8 local sinusoidal
    blendshapes and pair, triplet and quad correctives on part of the sheet (cm). For
    contract tests; the ICT rigs stay the evidence of behaviour."""
    from canrig_jax.rig import BlendshapeRig, Corrective

    vertices, faces, _ = synthetic_face
    rng = np.random.default_rng(3)
    centres = vertices[rng.choice(len(vertices), 8, replace=False)]
    falloff = np.exp(-(((vertices[None] - centres[:, None]) ** 2).sum(-1)) / 8.0)  # (8, V)
    directions = rng.normal(size=(8, 1, 3))
    deltas = (0.6 * falloff[..., None] * directions).astype(np.float32)
    support = np.flatnonzero(vertices[:, 0] < 6.0).astype(np.int32)

    def corrective(indices):
        scale = 0.2 * rng.normal(size=(len(indices), len(support), 3))
        return Corrective(np.asarray(indices, np.int32), support, scale.astype(np.float32))

    correctives = (
        corrective([[0, 1], [2, 3], [1, 4]]),
        corrective([[0, 1, 2]]),
        corrective([[0, 1, 2, 3]]),
    )
    names = tuple(f"shape{i}" for i in range(8))
    return BlendshapeRig(vertices, deltas, correctives, names, faces, units="cm")

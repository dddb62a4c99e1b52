"""Damaged checkpoints: reported as corrupt, with their path; old ones (no hash) still load;
xz-compressed ones load the same, and damage to their compression is corruption too.

The trained models are the committed ones (``experiments/results/canrig/checkpoint.eqx``, kept
xz-compressed under 1 MB, and ``autorig/checkpoint_raf.eqx``) and the packaged default
RigAnyFace."""

from __future__ import annotations

import json
import types

import equinox as eqx
import jax
import numpy as np
import pytest

from canrig_jax import CorruptFileError, autorig, canrig
from canrig_jax._checkpoint import (
    load_checkpoint,
    read_checkpoint_state,
    save_checkpoint,
    seal_checkpoint,
)
from canrig_jax.data import FACE, load_ict

from .conftest import handled, raises, run_case

FORMAT = "test-checkpoint-1"
ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]
CANRIG_CHECKPOINT = ROOT / "experiments/results/canrig/checkpoint.eqx"
AUTORIG_CHECKPOINT = ROOT / "experiments/results/autorig/checkpoint_raf.eqx"


def _tree(seed=0):
    return eqx.nn.MLP(3, 3, 16, 2, key=jax.random.PRNGKey(seed))


def _flip(data: bytes, start: int, count: int = 200) -> bytes:
    array = bytearray(data)
    rng = np.random.default_rng(1)
    for i in rng.choice(np.arange(start, len(array)), count, replace=False):
        array[i] ^= 0xFF
    return bytes(array)


@pytest.fixture(scope="module")
def ctx(tmp_path_factory, data_dir):
    root = tmp_path_factory.mktemp("checkpoints")
    good = root / "good.eqx"
    save_checkpoint(good, _tree(), {"step": 3, "history": [1.5, 2.5]}, FORMAT)
    data = good.read_bytes()
    header_end = data.index(b"\n") + 1
    (root / "flipped.eqx").write_bytes(_flip(data, header_end))
    (root / "flipped_header.eqx").write_bytes(data.replace(b'"step": 3', b'"step": 4', 1))
    (root / "truncated.eqx").write_bytes(data[: header_end + (len(data) - header_end) // 2])
    (root / "header_only.eqx").write_bytes(data[: header_end - 20])
    (root / "empty.eqx").write_bytes(b"")
    (root / "other.eqx").write_bytes(json.dumps({"format": "other"}).encode() + b"\n")
    header = json.loads(data[:header_end])
    del header["sha256"]
    (root / "old.eqx").write_bytes(json.dumps(header).encode() + b"\n" + data[header_end:])
    save_checkpoint(root / "good.eqx.xz", _tree(), {"step": 3}, FORMAT, compress=True)
    packed = (root / "good.eqx.xz").read_bytes()
    (root / "xz_truncated.eqx").write_bytes(packed[: len(packed) // 2])
    (root / "xz_flipped.eqx").write_bytes(_flip(packed, 64, count=20))
    for name, source in (("canrig", CANRIG_CHECKPOINT), ("autorig", AUTORIG_CHECKPOINT)):
        raw = source.read_bytes()
        end = raw.index(b"\n") + 1
        (root / f"{name}_truncated.eqx").write_bytes(raw[: end + (len(raw) - end) // 2])
        (root / f"{name}_flipped.eqx").write_bytes(_flip(raw, end))
    return types.SimpleNamespace(root=root, neutral=load_ict(data_dir, parts=FACE).neutral)


def _load(c, name):
    return load_checkpoint(c.root / name, _tree(), FORMAT)


CHECKPOINT = [
    raises("missing", lambda c: _load(c, "missing.eqx"), ValueError, "missing.eqx"),
    raises("folder", lambda c: load_checkpoint(c.root, _tree(), FORMAT), ValueError, "folder"),
    raises("not-a-path", lambda c: load_checkpoint(7, _tree(), FORMAT), TypeError, "path"),
    raises("flipped-arrays", lambda c: _load(c, "flipped.eqx"), CorruptFileError, "flipped.eqx"),
    raises(
        "edited-header",
        lambda c: _load(c, "flipped_header.eqx"),
        CorruptFileError,
        "flipped_header.eqx",
    ),
    raises("truncated", lambda c: _load(c, "truncated.eqx"), CorruptFileError, "truncated.eqx"),
    raises(
        "header-cut", lambda c: _load(c, "header_only.eqx"), CorruptFileError, "header_only.eqx"
    ),
    raises("empty", lambda c: _load(c, "empty.eqx"), ValueError, "empty.eqx"),
    raises("other-format", lambda c: _load(c, "other.eqx"), ValueError, "not a test-checkpoint-1"),
    raises(
        "another-model",
        lambda c: load_checkpoint(
            c.root / "good.eqx", eqx.nn.MLP(3, 3, 8, 2, key=jax.random.PRNGKey(0)), FORMAT
        ),
        CorruptFileError,
        "good.eqx",
        compiles=True,
    ),
    handled(
        "xz-compressed",
        lambda c: _load(c, "good.eqx.xz"),
        lambda out, c: (
            (c.root / "good.eqx.xz").read_bytes().startswith(b"\xfd7zXZ\x00")
            or pytest.fail("not xz"),
            np.testing.assert_array_equal(out[0].layers[1].weight, _tree().layers[1].weight),
            out[1]["step"] == 3 or pytest.fail("state changed"),
        ),
    ),
    raises("xz-truncated", lambda c: _load(c, "xz_truncated.eqx"), CorruptFileError, "xz_trunc"),
    raises("xz-flipped", lambda c: _load(c, "xz_flipped.eqx"), CorruptFileError, "xz_flipped"),
    handled(
        "old-checkpoint-without-hash",
        lambda c: _load(c, "old.eqx"),
        lambda out, c: (
            np.testing.assert_array_equal(out[0].layers[0].weight, _tree().layers[0].weight),
            out[1]["history"] == [1.5, 2.5] or pytest.fail("state changed"),
        ),
    ),
    handled(
        "state-without-the-hash",
        lambda c: read_checkpoint_state(c.root / "good.eqx", FORMAT),
        lambda state, c: (
            state == {"format": FORMAT, "step": 3, "history": [1.5, 2.5]} or pytest.fail(str(state))
        ),
    ),
]


@pytest.mark.parametrize("case", CHECKPOINT)
def test_load_checkpoint(case, ctx):
    run_case(case, ctx)


TRAINED_MODELS = [
    raises(
        "canrig-truncated",
        lambda c: canrig.load_model(c.root / "canrig_truncated.eqx", c.neutral),
        CorruptFileError,
        "canrig_truncated.eqx",
        compiles=True,
    ),
    raises(
        "autorig-truncated",
        lambda c: autorig.load_riganyface(c.root / "autorig_truncated.eqx"),
        CorruptFileError,
        "autorig_truncated.eqx",
        compiles=True,
    ),
    raises(
        "canrig-missing",
        lambda c: canrig.load_model(c.root / "nothing.eqx", c.neutral),
        ValueError,
        "nothing.eqx",
    ),
]


@pytest.mark.slow  # builds the two trained models (~25 s)
@pytest.mark.parametrize("case", TRAINED_MODELS)
def test_trained_models(case, ctx):
    run_case(case, ctx)


def test_sealing_an_old_checkpoint_makes_damage_detectable(ctx, tmp_path):
    """An old checkpoint (no hash) loads as before once sealed, and flipped bytes anywhere in
    it are then reported as corruption (unsealed, only those that break the arrays' framing)."""
    old = tmp_path / "old.eqx"
    old.write_bytes((ctx.root / "old.eqx").read_bytes())
    seal_checkpoint(old, FORMAT)
    tree, state = load_checkpoint(old, _tree(), FORMAT)
    assert state["history"] == [1.5, 2.5]
    np.testing.assert_array_equal(tree.layers[1].weight, _tree().layers[1].weight)
    data = old.read_bytes()
    old.write_bytes(_flip(data, data.index(b"\n") + 1))
    with pytest.raises(CorruptFileError, match="old.eqx"):
        load_checkpoint(old, _tree(), FORMAT)

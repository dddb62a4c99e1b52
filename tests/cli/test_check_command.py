"""``canrig check``: the rigger's checks from the command line, on the Rocketbox male's own
rig (validation head) and on it broken: exit 0 when every hard check passes, 1 when one
fails (named in the summary), 2 with one error line for a rig that cannot be checked."""

from __future__ import annotations

import json

import numpy as np
import pytest

from canrig_jax import autorig, run_command
from canrig_jax.data import load_livelinkface, save_obj, write_livelink_csv


@pytest.fixture(scope="module")
def files(tmp_path_factory, data_dir):
    root = tmp_path_factory.mktemp("check")
    h = autorig.load_rocketbox_head("Male_Adult_08", data_dir)
    arrays = dict(neutral=h.vertices, deltas=h.deltas, names=np.asarray(h.names), units="cm")
    np.savez(root / "artist.npz", faces=h.faces, **arrays)
    broken = h.deltas.copy()
    broken[h.names.index("jawOpen")] *= -1  # the jaw opens upwards
    np.savez(root / "broken.npz", faces=h.faces, **{**arrays, "deltas": broken})
    np.savez(root / "nofaces.npz", **arrays)
    save_obj(root / "neutral.obj", h.vertices, h.faces)
    save_obj(root / "other.obj", h.vertices[:-1], h.faces[:10])
    capture = load_livelinkface(data_dir)
    write_livelink_csv(root / "take.csv", capture)
    return root


def _run(capsys, *argv):
    status = run_command([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


@pytest.mark.slow
def test_an_artists_rig_passes_under_the_take(files, capsys):
    status, out, err = _run(
        capsys, "check", files / "artist.npz", "--take", files / "take.csv",
        "--sheet", files / "sheet.png", "--json", files / "checks.json",
    )  # fmt: skip
    assert status == 0, out + err
    assert "| blink_closes | hard |" in out and "FAILED" not in out
    written = json.loads((files / "checks.json").read_text())
    assert written["ok"] is True and set(written["checks"]) == set(autorig.CHECK_LIMITS)
    assert (files / "sheet.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_failed_hard_check_is_named_and_exits_1(files, capsys):
    status, out, _ = _run(capsys, "check", files / "broken.npz", "--n-random", "8")
    assert status == 1
    assert "FAILED (hard):" in out and "chin_moves_down" in out.splitlines()[-1]


def test_faces_from_the_head_file(files, capsys):
    status, _, err = _run(capsys, "check", files / "nofaces.npz", "--n-random", "8")
    assert status == 2 and "faces" in err.splitlines()[-1], err
    status, out, err = _run(
        capsys, "check", files / "nofaces.npz", "--head", files / "neutral.obj", "--n-random", "8"
    )
    assert status == 0, out + err
    status, _, err = _run(capsys, "check", files / "nofaces.npz", "--head", files / "other.obj")
    assert status == 2 and err.splitlines()[-1].startswith("canrig: error: --head"), err


@pytest.mark.slow
def test_autorig_warns_about_a_failed_hard_check_and_strict_refuses(files, capsys, data_dir):
    """The RigAnyFace network's rig of the Rocketbox female folds her lids and lips (it fails
    hard checks): written with a warning naming them, not written with --strict."""
    h = autorig.load_rocketbox_head("Female_Adult_01", data_dir)
    save_obj(files / "female.obj", h.vertices, h.faces)
    argv = ("autorig", files / "female.obj", "--units", "cm", "--method", "raf")
    status, _, err = _run(capsys, *argv, "-o", files / "raf.glb")
    assert status == 0 and (files / "raf.glb").is_file()
    warning = [line for line in err.splitlines() if line.startswith("canrig: warning: the rig")]
    assert warning and "flipped_triangles" in warning[0], err
    status, _, err = _run(capsys, *argv, "--strict", "-o", files / "strict.glb")
    assert status == 2 and not (files / "strict.glb").exists()
    assert "fails hard checks" in err.splitlines()[-1] and "not written" in err, err

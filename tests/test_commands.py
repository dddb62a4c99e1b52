"""The ``canrig`` command line: help, the four subcommands on real data, clear errors.

The fast tests drive a real linear ICT face rig (saved as .npz) with the real Live Link Face
capture; the end-to-end example of issue 20 (MakeHuman head, decimetres -> autorig ->
animate -> validate -> invert) is ``-m slow``.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest

from canrig_jax import run_command
from canrig_jax.data import (
    ARKIT_NAMES,
    data_file,
    load_livelinkface,
    read_arrays,
    read_livelink_csv,
    save_obj,
    to_arkit,
    write_livelink_csv,
)
from canrig_jax.rig import (
    BlendshapeRig,
    evaluate_batch,
    find_gltf_validator,
    ict_linear_rig,
    load_gltf_rig,
    save_rig,
    validate_gltf,
)

SUBCOMMANDS = ("autorig", "animate", "invert", "correct")


@pytest.fixture(scope="module")
def workspace(tmp_path_factory, data_dir):
    """A linear ICT face rig (.npz) and the real capture written as a Live Link Face CSV."""
    root = tmp_path_factory.mktemp("commands")
    rig = ict_linear_rig(data_dir)
    save_rig(root / "rig.npz", rig)
    write_livelink_csv(root / "take.csv", load_livelinkface(data_dir))
    return root, rig


def _run(capsys, *argv):
    status = run_command([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


PROGRESS = re.compile(r"^\[ *\d+\.\d s\] ")
"""A progress line: ``[  12.3 s] message``."""


def _timecodes(path):
    return [line.split(",", 1)[0] for line in path.read_text().splitlines()[1:]]


def _assert_one_voice(err: str, quiet: bool = False) -> list[str]:
    """Every stderr line is a progress line (none with ``quiet``), a ``canrig: warning:`` or a
    ``canrig: error:`` line: no traceback, no source line, no warning class. Returns the
    warning lines, each message once."""
    lines = [line for line in err.splitlines() if line.strip()]
    warns = [line for line in lines if line.startswith("canrig: warning: ")]
    for line in lines:
        voiced = line.startswith(("canrig: warning: ", "canrig: error: "))
        assert voiced or (not quiet and PROGRESS.match(line)), line
    assert "Traceback" not in err and "CanrigWarning" not in err and ".py:" not in err, err
    assert len(warns) == len(set(warns)), warns
    return warns


@pytest.mark.parametrize("command", SUBCOMMANDS)
def test_help(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        run_command([command, "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    assert f"usage: canrig {command}" in text and "-o OUTPUT" in text
    if command == "invert":
        assert "--method {quartic,linear,seol" in text and "--alpha" in text
    if command == "autorig":
        assert "--method {transfer,raf,transfer-residual}" in text and "--examples" in text
        from canrig_jax.autorig import DEFAULT_METHOD

        assert f"(default: {DEFAULT_METHOD.name})" in " ".join(text.split())
        assert "--names {arkit,ict}" in text and "--up" in text and "--forward" in text


def _options(parser):
    """Each subcommand's (option strings, default, choices), from a parser."""
    sub = next(a for a in parser._actions if a.dest == "command")
    return {
        name: sorted(
            (tuple(a.option_strings), a.dest, str(a.default), str(a.choices)) for a in p._actions
        )
        for name, p in sub.choices.items()
    }


def test_one_subcommands_parser_is_the_whole_parsers_and_imports_only_its_own():
    from canrig_jax._commands import build_parser

    whole = _options(build_parser())
    assert set(SUBCOMMANDS) <= set(whole)
    for command in whole:
        assert _options(build_parser(command)) == {command: whole[command]}
    # canrig autorig in a fresh process reads its arguments without the inverse rig's modules
    code = (
        "import sys; from canrig_jax._commands import build_parser; "
        "build_parser('autorig').parse_args(['autorig', 'head.obj', '-o', 'rig.glb']); "
        "print(sorted(m for m in sys.modules if m.startswith('canrig_jax.inverse')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_console_script_runs_in_a_fresh_process():
    result = subprocess.run(
        [sys.executable, "-c", "import sys, canrig_jax; sys.exit(canrig_jax.run_command())", "-h"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0 and all(c in result.stdout for c in SUBCOMMANDS)


@pytest.mark.slow
def test_animate_then_invert_recovers_the_take(workspace, capsys):
    """animate writes a glTF whose keys are the take's weights; invert of the animated meshes
    gives back those weights (linear rig, exact solver up to convergence)."""
    root, rig = workspace
    status, out, err = _run(
        capsys,
        *("animate", root / "rig.npz", root / "take.csv", "-o", root / "anim.glb"),
        *("--meshes", root / "meshes.npz"),
    )
    assert status == 0, err
    assert "180 frames at 60 fps (from the timecodes)" in err
    assert "7 frames dropped" in err and "TongueOut" in err  # reported, never silent
    meshes = read_arrays(root / "meshes.npz", ("meshes", "weights"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        expected = read_livelink_csv(root / "take.csv").weights_for(rig.names)
    np.testing.assert_array_equal(meshes["weights"], expected)
    np.testing.assert_allclose(
        meshes["meshes"][::45], evaluate_batch(rig, expected[::45]), atol=1e-5
    )
    assert load_gltf_rig(root / "anim.glb").n_blendshapes == 53

    _assert_one_voice(err)
    status, out, err = _run(
        capsys,
        *("invert", root / "rig.npz", root / "meshes.npz", "-o", root / "back.csv"),
        *("--method", "linear", "--reference", root / "take.csv", "--quiet"),
        *("--timecodes", root / "take.csv"),
    )
    assert status == 0, err
    assert _timecodes(root / "back.csv") == _timecodes(root / "take.csv")  # the gap kept
    match = re.search(r"mean ([\d.]+), RMS ([\d.]+), max ([\d.]+)", out)
    mean, rms, worst = (float(x) for x in match.groups())
    assert mean < 2e-3 and worst < 0.1, out
    # the mesh error of the solved weights, against the meshes the weights came from
    mesh_mean, mesh_max = (
        float(x) for x in re.search(r"mean ([\d.]+) mm, max ([\d.]+) mm", out).groups()
    )
    assert mesh_mean <= mesh_max < 0.5 and mesh_mean < 0.01, out
    with pytest.warns(UserWarning, match="7 frames dropped"):  # the gap, from --timecodes
        back = read_livelink_csv(root / "back.csv", fps=60)
    assert back.n_frames == 180 and len(back.names) == 51  # ICT has no TongueOut
    assert back.names[:2] == ("EyeBlinkLeft", "EyeLookDownLeft")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        take = read_livelink_csv(root / "take.csv")
    jaw = back.names.index("JawOpen")
    assert np.abs(back.weights[:, jaw] - take.weights[:, take.names.index("JawOpen")]).max() < 0.05

    # the take with 20 more rows dropped, and the meshes of the rows kept: the written CSV has
    # the dropped-row take's timecodes, both gaps included
    lines = (root / "take.csv").read_text().splitlines()
    (root / "gap.csv").write_text("\n".join(lines[:101] + lines[121:]) + "\n")
    kept = np.r_[0:100, 120:180]
    np.savez(root / "gap_meshes.npz", meshes=meshes["meshes"][kept])
    status, out, err = _run(
        capsys,
        *("invert", root / "rig.npz", root / "gap_meshes.npz", "-o", root / "gap_back.csv"),
        *("--method", "linear", "--timecodes", root / "gap.csv"),
    )
    assert status == 0, err
    assert "160 frames at 60 fps, 27 frames dropped in 2 gaps (kept)" in err
    assert _timecodes(root / "gap_back.csv") == _timecodes(root / "gap.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gap_back = read_livelink_csv(root / "gap_back.csv")
    np.testing.assert_array_equal(gap_back.frame_number, take.frame_number[kept])
    np.testing.assert_allclose(gap_back.weights, back.weights[kept], atol=1e-3)


def test_invert_refuses_timecodes_of_another_length(workspace, capsys, tmp_path):
    root, rig = workspace
    np.savez(tmp_path / "m.npz", meshes=np.repeat(np.asarray(rig.neutral)[None], 5, axis=0))
    status, _, err = _run(
        capsys,
        *("invert", root / "rig.npz", tmp_path / "m.npz", "-o", tmp_path / "t.csv"),
        *("--timecodes", root / "take.csv"),
    )
    assert status == 2 and "--timecodes" in err and "180 frames" in err and "m.npz 5" in err
    assert not (tmp_path / "t.csv").exists()
    _assert_one_voice(err)


def test_invert_a_folder_of_obj(workspace, capsys, tmp_path):
    root, rig = workspace
    weights = np.zeros((3, rig.n_blendshapes), np.float32)
    jaw = [to_arkit(n) for n in rig.names].index("jawOpen")
    weights[:, jaw] = (0.2, 0.5, 0.9)
    for i, mesh in enumerate(np.asarray(evaluate_batch(rig, weights))):
        save_obj(tmp_path / f"frame_{i:03d}.obj", mesh, np.asarray(rig.faces))
    status, _, err = _run(
        capsys, "invert", root / "rig.npz", tmp_path, "-o", tmp_path / "t.csv", "--quiet"
    )
    assert status == 0, err
    back = read_livelink_csv(tmp_path / "t.csv", fps=60)
    np.testing.assert_allclose(
        back.weights[:, back.names.index("JawOpen")], (0.2, 0.5, 0.9), atol=1e-3
    )
    assert np.abs(np.delete(back.weights, back.names.index("JawOpen"), axis=1)).max() < 1e-3


@pytest.mark.slow
def test_correct_bakes_the_sculpts(workspace, capsys, tmp_path):
    """WPSE from 3 sculpted frames: the baked targets reproduce each sculpt at its pose."""
    root, rig = workspace
    rng = np.random.default_rng(0)
    poses = np.zeros((3, rig.n_blendshapes), np.float32)
    poses[np.arange(3), rng.choice(rig.n_blendshapes, 3, replace=False)] = 1.0
    posed = np.asarray(evaluate_batch(rig, poses))
    bump = np.zeros_like(posed)
    bump[:, :200, 1] = 0.05 * (1 + np.arange(3))[:, None]  # 0.5-1.5 mm sculpted offsets
    np.savez(tmp_path / "edits.npz", poses=poses, meshes=posed + bump)
    status, out, err = _run(
        capsys, "correct", root / "rig.npz", tmp_path / "edits.npz", "-o", tmp_path / "fixed.glb"
    )
    assert status == 0, err
    assert "correction: BAKED" in out
    fixed = load_gltf_rig(tmp_path / "fixed.glb")
    assert fixed.names[-3:] == ("wpse_frame_0000", "wpse_frame_0001", "wpse_frame_0002")
    on = np.concatenate([poses, np.eye(3, dtype=np.float32)], axis=1)
    np.testing.assert_allclose(np.asarray(evaluate_batch(fixed, on)), posed + bump, atol=2e-3)


@pytest.mark.slow
def test_correct_over_a_take(workspace, capsys, tmp_path):
    """--take: one baked WPSE target per frame, animated one-hot at its own key."""
    root, rig = workspace
    poses = np.zeros((2, rig.n_blendshapes), np.float32)
    poses[0, 3] = poses[1, 17] = 1.0
    posed = np.array(evaluate_batch(rig, poses))
    posed[:, :100, 2] += 0.1
    np.savez(tmp_path / "edits.npz", poses=poses, meshes=posed)
    lines = (root / "take.csv").read_text().splitlines()
    (tmp_path / "short.csv").write_text("\n".join(lines[:13]) + "\n")  # 12 frames
    status, out, err = _run(
        capsys,
        *("correct", root / "rig.npz", tmp_path / "edits.npz", "-o", tmp_path / "take.glb"),
        *("--take", tmp_path / "short.csv", "--sigma", "0.5"),
    )
    assert status == 0, err
    assert "BAKED" in out and "animated over the 12 frames" in out
    animated = load_gltf_rig(tmp_path / "take.glb")
    assert animated.n_blendshapes == 53 + 12
    if find_gltf_validator() is not None:
        assert validate_gltf(tmp_path / "take.glb")["issues"]["numErrors"] == 0


def test_errors_name_the_file_and_write_nothing(workspace, capsys, tmp_path):
    root, _ = workspace
    cases = [
        (("autorig", tmp_path / "nohead.obj", "-o", tmp_path / "r.glb"), "nohead.obj"),
        (("autorig", tmp_path / "h.obj", "-o", tmp_path / "missing" / "r.glb"), "does not exist"),
        (("autorig", tmp_path / "h.obj", "-o", tmp_path / "r.glb", "--model", "m.eqx"), "--model"),
        (
            ("autorig", tmp_path / "h.obj", "-o", tmp_path / "r.glb", "--method", "raf")
            + ("--template", tmp_path / "h.obj"),
            "--template: only --method transfer",
        ),
        (
            ("autorig", tmp_path / "h.obj", "-o", tmp_path / "r.glb", "--method", "raf")
            + ("--model", tmp_path / "none.eqx"),
            "checkpoint not found",
        ),
        (("animate", root / "rig.npz", tmp_path / "bad.csv", "-o", tmp_path / "a.glb"), "line 2"),
        (("animate", root / "rig.npz", root / "take.csv", "-o", tmp_path / "a.txt"), ".glb"),
        (("invert", root / "rig.npz", tmp_path / "nothing", "-o", tmp_path / "t.csv"), "nothing"),
        (("animate", tmp_path / "none.glb", root / "take.csv", "-o", tmp_path / "a.glb"), "none"),
    ]
    (tmp_path / "h.obj").write_text("")
    (tmp_path / "bad.csv").write_text("Timecode,EyeBlinkLeft\n00:00:00:01.000,x\n")
    before = sorted(os.listdir(tmp_path))
    for argv, message in cases:
        status, _, err = _run(capsys, *argv)
        assert status == 2 and message in err and "Traceback" not in err, (argv, err)
        assert err.splitlines()[-1].startswith("canrig: error: "), err
        _assert_one_voice(err)
    assert sorted(os.listdir(tmp_path)) == before
    with pytest.raises(SystemExit) as exit_info:  # argparse's errors read the same
        run_command(["invert", str(root / "rig.npz"), str(tmp_path), "-o", "t.csv", "--fps", "x"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.splitlines()[-1].startswith("canrig: error: ")
    assert "--fps" in err
    status, _, err = _run(capsys, "autorig", tmp_path / "h.obj", "-o", tmp_path / "r.glb")
    assert status == 2 and "h.obj is empty" in err


@pytest.mark.slow
def test_autorig_orientation(tmp_path, capsys, data_dir):
    """A real ICT identity stored z up (turned 90 degrees about x): canrig autorig finds the
    orientation from the face and writes the upright head's rig turned into the file's frame;
    stating it (--up=+z --forward=-y) gives the same rig; a wrong statement gives another."""
    from canrig_jax.autorig import auto_rig
    from canrig_jax.data import ict_identity, load_ict
    from canrig_jax.mesh import decimate

    ict = load_ict(data_dir, parts=None)
    identity = ict_identity(np.random.default_rng(11).standard_normal(100), data_dir, model=ict)
    mesh = decimate(identity, ict.faces, 1300)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # y up -> z up
    turned = (mesh.vertices @ turn.T).astype(np.float32)
    save_obj(tmp_path / "zup.obj", turned, mesh.faces)
    argv = ("autorig", tmp_path / "zup.obj", "--units", "cm")
    status, _, err = _run(capsys, *argv, "-o", tmp_path / "found.glb")
    assert status == 0 and "up +z, facing -y (fitted)" in err, err
    found = load_gltf_rig(tmp_path / "found.glb")
    np.testing.assert_allclose(found.neutral, turned, atol=1e-4)
    upright = auto_rig(mesh.vertices.astype(np.float32), mesh.faces).rig
    assert found.names == upright.names
    np.testing.assert_allclose(found.deltas, np.asarray(upright.deltas) @ turn.T, atol=1e-4)

    stated = (*argv, "--up=+z", "--forward=-y", "-o", tmp_path / "stated.glb")
    status, _, err = _run(capsys, *stated)
    assert status == 0 and "(stated)" in err, err
    stated_rig = load_gltf_rig(tmp_path / "stated.glb")
    np.testing.assert_allclose(stated_rig.deltas, found.deltas, atol=1e-4)
    wrong = (*argv, "--up=+y", "--forward=+z", "-o", tmp_path / "w.glb")
    status, _, err = _run(capsys, *wrong)
    if status == 0:  # the head as stored, taken as upright: another (wrong) rig
        assert np.abs(load_gltf_rig(tmp_path / "w.glb").deltas - found.deltas).max() > 1e-2


@pytest.mark.slow
def test_end_to_end_makehuman(tmp_path, capsys, data_dir):
    """Issue 20's example: the MakeHuman head (decimetres, evaluation only) -> autorig ->
    animate with the Live Link capture as CSV -> validated glTF -> invert back to a CSV."""
    head = read_arrays(data_file("makehuman/hm08_face.npz", data_dir), ("neutral", "faces"))
    save_obj(tmp_path / "head.obj", head["neutral"], head["faces"])
    write_livelink_csv(tmp_path / "take.csv", load_livelinkface(data_dir))
    status, _, err = _run(
        capsys, "autorig", tmp_path / "head.obj", "--units", "dm", "-o", tmp_path / "rig.glb"
    )
    assert status == 0, err
    rig = load_gltf_rig(tmp_path / "rig.glb")
    assert rig.n_blendshapes == 51 and rig.n_vertices == 4920 and rig.units == "cm"
    assert set(rig.names) <= set(ARKIT_NAMES)
    np.testing.assert_allclose(rig.neutral, head["neutral"] * 10, rtol=1e-5, atol=1e-4)
    status, _, err = _run(
        capsys,
        *("animate", tmp_path / "rig.glb", tmp_path / "take.csv", "-o", tmp_path / "anim.glb"),
        *("--meshes", tmp_path / "meshes.npz"),
    )
    assert status == 0, err
    if find_gltf_validator() is not None:
        report = validate_gltf(tmp_path / "anim.glb")
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    else:
        warnings.warn("gltf-validator not installed: anim.glb not validated", stacklevel=1)
    status, out, err = _run(
        capsys,
        *("invert", tmp_path / "rig.glb", tmp_path / "meshes.npz", "-o", tmp_path / "back.csv"),
        *("--reference", tmp_path / "take.csv"),
    )
    assert status == 0, err
    print(out)  # the mesh and weight errors, for the record (-s)
    # the meshes are reproduced: the well-posed half of inversion
    mean_mm, max_mm = (
        float(x) for x in re.search(r"mean ([\d.]+) mm, max ([\d.]+) mm", out).groups()
    )
    assert mean_mm < 5e-3 and max_mm < 0.2, out
    # the weights are recovered where the rig can tell its blendshapes apart: channels whose
    # delta has no other within |cos| 0.8 (on MakeHuman some generated eye and brow shapes are
    # nearly parallel, |cos| up to 0.97, so their weights trade without changing the mesh)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the capture's known frame gap
        back = read_livelink_csv(tmp_path / "back.csv", fps=60)
        take = read_livelink_csv(tmp_path / "take.csv", fps=60)
    assert back.n_frames == 180
    deltas = np.asarray(rig.deltas).reshape(rig.n_blendshapes, -1)
    unit = deltas / np.linalg.norm(deltas, axis=1, keepdims=True)
    cosine = np.abs(unit @ unit.T) - np.eye(rig.n_blendshapes)
    separate = cosine.max(axis=1) < 0.8
    error = np.abs(
        back.weights_for(rig.names, missing="zero") - take.weights_for(rig.names, missing="zero")
    )
    assert separate.sum() >= 10 and error[:, separate].max() < 0.01, (
        f"{separate.sum()} separate channels, error {error[:, separate].max():.4f}"
    )


def _last_key_seconds(path) -> float:
    """The time of an animated glb's last key (its first sampler input's ``max``)."""
    data = path.read_bytes()
    length = int.from_bytes(data[12:16], "little")
    gltf = json.loads(data[20 : 20 + length])
    sampler = gltf["animations"][0]["samplers"][0]
    return float(gltf["accessors"][sampler["input"]]["max"][0])


def _tiny_rig() -> BlendshapeRig:
    """Three ARKit-named shapes on a 4 x 4 vertex grid (cm)."""
    x, y = np.meshgrid(np.arange(4.0), np.arange(4.0), indexing="ij")
    neutral = np.stack([x.ravel(), y.ravel(), np.zeros(16)], axis=1).astype(np.float32)
    faces = []
    for i in range(3):
        for j in range(3):
            a, b, c, d = 4 * i + j, 4 * i + j + 4, 4 * i + j + 5, 4 * i + j + 1
            faces += [(a, b, c), (a, c, d)]
    deltas = np.random.default_rng(0).normal(0, 0.1, (3, 16, 3)).astype(np.float32)
    names = ("jawOpen", "eyeBlink_L", "mouthSmile_L")
    return BlendshapeRig(neutral, deltas, (), names, np.array(faces, np.int32))


@pytest.mark.parametrize("quiet", [False, True])
def test_warnings_are_one_line_each(workspace, capsys, tmp_path, quiet):
    """``canrig correct --take`` on a take with dropped rows and channels the rig lacks: each
    warning is one ``canrig: warning:`` line, never a warning class and a source line, and
    ``--quiet`` keeps them (it silences progress only)."""
    root, _ = workspace
    rig = _tiny_rig()
    save_rig(tmp_path / "tiny.npz", rig)
    poses = np.eye(3, dtype=np.float32)[:2]
    sculpted = np.asarray(evaluate_batch(rig, poses)) + 0.05
    np.savez(tmp_path / "edits.npz", poses=poses, meshes=sculpted)
    lines = (root / "take.csv").read_text().splitlines()
    (tmp_path / "gap.csv").write_text("\n".join(lines[:13] + lines[15:70]) + "\n")
    status, out, err = _run(
        capsys,
        *("correct", tmp_path / "tiny.npz", tmp_path / "edits.npz", "-o", tmp_path / "c.glb"),
        *("--take", tmp_path / "gap.csv", "--sigma", "0.5", *(["--quiet"] if quiet else [])),
    )
    assert status == 0, err
    warns = _assert_one_voice(err, quiet)
    assert sum("9 frames dropped at 60 fps in 2 gaps" in w for w in warns) == 1, warns
    assert sum("not used by the target" in w and "TongueOut" in w for w in warns) == 1, warns
    assert any(PROGRESS.match(line) for line in err.splitlines()) != quiet
    # the corrected take keeps its timecodes: keys at the frames' own times, gaps included
    animated = load_gltf_rig(tmp_path / "c.glb")
    assert animated.n_blendshapes == 3 + 67
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        take = read_livelink_csv(tmp_path / "gap.csv")
    seconds = (take.frame_number[-1] - take.frame_number[0]) / 60  # 75 frames for 67 rows
    assert _last_key_seconds(tmp_path / "c.glb") == pytest.approx(seconds, abs=1e-4)


def test_autorig_unit_mistake_is_one_error_line(capsys, tmp_path, data_dir):
    """A head in decimetres given as centimetres (3.76 cm tall): one error line naming the
    file, the unit and the likely one, before any model is read (the --model is damaged)."""
    head = read_arrays(data_file("makehuman/hm08_face.npz", data_dir), ("neutral", "faces"))
    save_obj(tmp_path / "head.obj", head["neutral"], head["faces"])
    (tmp_path / "bad.eqx").write_bytes(b"not a checkpoint")
    status, _, err = _run(
        capsys,
        *("autorig", tmp_path / "head.obj", "--units", "cm", "--method", "raf"),
        *("--model", tmp_path / "bad.eqx", "-o", tmp_path / "r.glb"),
    )
    assert status == 2 and not (tmp_path / "r.glb").exists()
    assert not _assert_one_voice(err)  # no warning: the unit mistake is an error
    last = err.splitlines()[-1]
    assert last.startswith("canrig: error: ") and "head.obj" in last and "units" in last, err
    assert "bad.eqx" not in err


def test_animate_an_fbx_rig_by_arkit_names(workspace, capsys, data_dir):
    """An artist's FBX rig (Rocketbox, whole body) is driven by the capture through its ARKit
    names: every keyed morph target is an ARKit shape of the file, and its weight at each
    frame is the capture's value of that channel."""
    from canrig_jax.data import read_livelink_csv
    from canrig_jax.rig import load_fbx_rig

    fbx = data_file("rocketbox/Female_Adult_01_facial.fbx", data_dir)
    root, _ = workspace
    out = root / "rocketbox.glb"
    meshes = root / "rocketbox_meshes.npz"
    status, _, err = _run(capsys, "animate", fbx, root / "take.csv", "-o", out, "--meshes", meshes)
    assert status == 0, err
    _assert_one_voice(err)
    rig = load_fbx_rig(fbx)
    animated = load_gltf_rig(out)
    assert animated.names == rig.names and set(rig.names) <= set(ARKIT_NAMES)
    np.testing.assert_allclose(animated.deltas, rig.deltas, atol=1e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        expected = read_livelink_csv(root / "take.csv").weights_for(rig.names)
    np.testing.assert_array_equal(read_arrays(meshes, ("weights",))["weights"], expected)


def test_a_missing_optional_dependency_is_one_error_line(workspace, capsys, monkeypatch):
    """Without jaxopt (an extra), ``canrig invert --method lbfgsb`` says which extra to
    install in one error line, no traceback."""
    root, rig = workspace
    frames = np.repeat(np.asarray(rig.neutral)[None], 2, axis=0)
    np.savez(root / "still.npz", meshes=frames)
    monkeypatch.setitem(sys.modules, "jaxopt", None)  # import jaxopt raises ImportError
    status, _, err = _run(
        capsys,
        *("invert", root / "rig.npz", root / "still.npz", "-o", root / "w.csv"),
        *("--method", "lbfgsb", "--quiet"),
    )
    assert status == 2 and "canrig_jax[jaxopt]" in err, err
    _assert_one_voice(err, quiet=True)
    assert not (root / "w.csv").exists()

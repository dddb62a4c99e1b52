"""The built wheel, installed in a fresh virtualenv outside the repository (its dependencies
from the package index, no extras), runs the command line from a folder of its own: ``canrig
autorig`` with the packaged default model on the MakeHuman head (as an OBJ in decimetres),
then ``canrig animate`` with the Live Link capture (as a CSV). Slow (``nox -s wheel``): it
builds the wheel, installs JAX and the rest into the new environment and compiles the model.
"""

from __future__ import annotations

import os
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import numpy as np
import pytest

from canrig_jax.data import (
    data_file,
    load_livelinkface,
    read_arrays,
    save_obj,
    write_livelink_csv,
)
from canrig_jax.rig import load_gltf_rig
from canrig_jax.viewer import inspect_glb

ROOT = Path(__file__).resolve().parents[1]
MODEL = "canrig_jax/autorig/models/riganyface.eqx.xz"


def _run(argv, cwd, env, timeout=1800) -> subprocess.CompletedProcess:
    result = subprocess.run(
        [str(a) for a in argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    assert result.returncode == 0, f"{argv}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


@pytest.mark.slow  # ~2 min: builds the wheel, installs its dependencies, runs the model
def test_wheel_runs_autorig_and_animate_outside_the_repository(tmp_path, data_dir):
    assert ROOT not in tmp_path.parents
    # a clean environment: nothing from the repository or this test run's own packages
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "CANRIG_DATA")}
    env["CANRIG_CACHE"] = str(tmp_path / "cache")
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", dist, ROOT], tmp_path, env)
    (wheel,) = dist.glob("canrig_jax-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
    assert MODEL in names and any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    assert not [n for n in names if n.startswith(("experiments/", "tests/"))]

    venv.create(tmp_path / "venv", with_pip=True)
    bin_dir = tmp_path / "venv" / "bin"
    _run([bin_dir / "python", "-m", "pip", "install", "-q", wheel], tmp_path, env)

    work = tmp_path / "work"
    work.mkdir()
    head = read_arrays(data_file("makehuman/hm08_face.npz", data_dir), ("neutral", "faces"))
    save_obj(work / "head.obj", head["neutral"], head["faces"])
    capture = load_livelinkface(data_dir)
    write_livelink_csv(work / "take.csv", capture)

    autorig = _run(
        [bin_dir / "canrig", "autorig", "head.obj", "--units", "dm", "-o", "rig.glb"], work, env
    )
    installed = tmp_path / "venv" / "lib"
    assert f"loading the network {installed}" in autorig.stderr + autorig.stdout
    rig = load_gltf_rig(work / "rig.glb")
    assert rig.n_blendshapes == 51 and rig.n_vertices == 4920 and rig.units == "cm"
    np.testing.assert_allclose(rig.neutral, head["neutral"] * 10, rtol=1e-5, atol=1e-4)
    assert np.abs(np.asarray(rig.deltas)[rig.names.index("jawOpen")]).max() > 0.1  # cm

    _run([bin_dir / "canrig", "animate", "rig.glb", "take.csv", "-o", "anim.glb"], work, env)
    animated = load_gltf_rig(work / "anim.glb")
    assert animated.n_blendshapes == 51 and animated.n_vertices == 4920
    summary = inspect_glb(work / "anim.glb")
    assert summary.n_vertices == 4920 and summary.animations and len(summary.morph_names) >= 51

    # the core install has no jaxopt; the solver that needs it says which extra to install
    probe = subprocess.run(
        [bin_dir / "python", "-c", "from canrig_jax import inverse; inverse.JaxoptLBFGSB()"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert probe.returncode != 0 and "pip install canrig_jax[jaxopt]" in probe.stderr

"""The compiled solves users run cannot deadlock XLA's CPU thread pool: a stress run of the
fits that hung (in a subprocess with a timeout, beside a CPU hog), and a scan of every program
the workload compiles for a LAPACK call holding a batch of matrices (the condition of the
deadlock; see ``canrig_jax._linalg``). ``nox -s stress`` runs 200 calls idle and under load.
A hang fails the test on its timeout (the workload's watchdog dumps the stacks first), never
the suite."""

import os
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

import pytest

from canrig_jax._linalg import lapack_calls

WORKLOAD = Path(__file__).with_name("stress_workload.py")
CALLS = 3
"""Fitted A-to-B calls per rig in the default run (the hang came on the second; nox -s
stress runs 200)."""


@contextmanager
def cpu_hog(processes: int = 1):
    """Busy processes beside the block: with the other test worker, the CI machine's two
    cores stay oversubscribed (``nox -s stress`` runs two)."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(processes)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def run_workload(*args: str, timeout: float, env: dict | None = None) -> str:
    """The workload's output; fails (never hangs) on a timeout or a non-zero exit."""
    command = [sys.executable, str(WORKLOAD), *args]
    try:
        run = subprocess.run(
            command, capture_output=True, text=True, timeout=timeout, env=env or dict(os.environ)
        )
    except subprocess.TimeoutExpired as expired:
        pytest.fail(f"the stress workload hung (> {timeout:g} s):\n{expired.stderr}")
    assert run.returncode == 0, f"exit {run.returncode}\n{run.stdout}\n{run.stderr[-5000:]}"
    assert run.stdout.rstrip().endswith("ok")
    return run.stdout


@pytest.mark.slow
def test_fits_complete_under_load(data_dir):
    with cpu_hog():
        out = run_workload(
            *("--calls", str(CALLS), "--data-dir", str(data_dir), "--watchdog", "300"),
            # the fitted A-to-B calls that hung (LocalFitRig's); the dump scan covers every
            # other phase, nox -s stress the network's calls too
            *("--phases", "local"),
            timeout=900,
        )
    assert f"LocalFitRig: {CALLS} fitted A-to-B calls" in out


@pytest.mark.slow
def test_no_compiled_program_holds_a_batched_lapack_call(data_dir, tmp_path):
    env = dict(os.environ, XLA_FLAGS=f"--xla_dump_to={tmp_path} --xla_dump_hlo_as_text")
    run_workload(
        "--calls", "1", "--data-dir", str(data_dir), "--watchdog", "600", timeout=900, env=env
    )
    programs = sorted(tmp_path.glob("*after_optimizations.txt"))
    assert len(programs) > 50  # every phase compiled something
    calls = {path.name: lapack_calls(path.read_text()) for path in programs}
    kernels = {name for found in calls.values() for name, _ in found}
    # Cholesky, triangular solves, LU (L-BFGS-B, WPSE's LOO) and eigh (LMMM) all ran
    assert {"lapack_spotrf_ffi", "lapack_strsm_ffi", "lapack_sgetrf_ffi"} <= kernels
    assert "lapack_ssyevd_ffi" in kernels
    batched = {
        name: [c for c in found if len(c[1]) > 2]
        for name, found in calls.items()
        if any(len(c[1]) > 2 for c in found)
    }
    assert not batched, batched


@pytest.mark.slow
@pytest.mark.parametrize("load", [False, True], ids=["idle", "cpu-hog"])
def test_two_hundred_fits(data_dir, load):
    hog = cpu_hog(2) if load else cpu_hog(0)
    with hog:
        out = run_workload("--calls", "200", "--data-dir", str(data_dir), timeout=2400)
    assert "LocalFitRig: 200 fitted A-to-B calls" in out

"""Real processes on this machine (-m slow; ``nox -s distributed``): the worker run as one
process and as two under ``canrig launch`` gives the same trained parameters, inverse weights
and auto-rigs; a killed process ends the others with JAX's message within a minute; a SLURM
environment (simulated: the variables ``srun`` sets, coordinator on localhost) starts the same
run."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow

WORKER = Path(__file__).resolve().parents[1] / "distributed_worker.py"
ENV = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONUNBUFFERED": "1"}
for name in ("CANRIG_COORDINATOR", "CANRIG_PROCESSES", "CANRIG_PROCESS_ID", "XLA_FLAGS"):
    ENV.pop(name, None)


def _relative(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a, np.float64) - b) / np.linalg.norm(b))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The worker's results as one process and as two (``canrig launch -n 2``)."""
    folder = tmp_path_factory.mktemp("distributed")
    one = subprocess.run(
        [sys.executable, WORKER, "run", "--out", folder / "one"],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert one.returncode == 0, one.stderr[-3000:]
    launch = [sys.executable, "-m", "canrig_jax._commands", "launch", "-n", "2", "--"]
    two = subprocess.run(
        [*launch, sys.executable, WORKER, "run", "--out", folder / "two"],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert two.returncode == 0, two.stderr[-3000:]
    timing = json.loads((folder / "two" / "timing.json").read_text())
    assert timing["processes"] == 2 and timing["devices"] == 2
    return np.load(folder / "one" / "result.npz"), np.load(folder / "two" / "result.npz")


@pytest.mark.parametrize("trainer", ["canrig", "pbs", "riganyface"])
def test_trained_parameters_equal_one_process(runs, trainer):
    one, two = runs
    assert _relative(two[f"{trainer}_params"], one[f"{trainer}_params"]) < 1e-5
    np.testing.assert_allclose(two[f"{trainer}_losses"], one[f"{trainer}_losses"], rtol=1e-5)
    # and they trained: the parameters moved from their start
    assert _relative(one[f"{trainer}_params"], one[f"{trainer}_start"]) > 1e-4


def test_inverse_weights_and_auto_rigs_equal_one_process(runs):
    one, two = runs
    assert two["inverse_weights"].shape == (45, 53)
    np.testing.assert_allclose(two["inverse_weights"], one["inverse_weights"], rtol=0, atol=1e-6)
    assert np.all(two["inverse_converged"])
    # the capture's own weights are recovered (mean |w - w_true| in weight units)
    assert np.mean(np.abs(one["inverse_weights"] - one["inverse_truth"])) < 0.05
    for i in (0, 1):
        d1, d2 = one[f"autorig_{i}_deltas"], two[f"autorig_{i}_deltas"]
        assert _relative(d2, d1) < 1e-5
    assert not np.allclose(one["autorig_0_deltas"], one["autorig_1_deltas"])  # two heads
    assert list(two["autorig_names"]) == list(one["autorig_names"])


def _start_waiting(env_of) -> list[subprocess.Popen]:
    return [
        subprocess.Popen(
            [sys.executable, WORKER, "wait"],
            env={**ENV, **env_of(i)},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in (0, 1)
    ]


def _wait_until_alive(process: subprocess.Popen, timeout: float = 120) -> list[str]:
    """The lines ``process`` printed up to its fourth all-gather with the other."""
    deadline = time.monotonic() + timeout
    assert process.stdout is not None
    lines = []
    for line in process.stdout:
        lines.append(line)
        if line.startswith("alive 3 6.0"):  # both processes' 3s gathered: 3 + 3
            return lines
        assert time.monotonic() < deadline, "the run did not start"
    pytest.fail(f"the worker ended before it was alive: {process.stderr.read()[-2000:]}")


@pytest.mark.parametrize("killed", [1, 0], ids=["worker", "coordinator"])
def test_a_killed_process_ends_the_others_with_a_clear_error(killed):
    from canrig_jax.distributed._launch import free_port

    port = free_port()
    procs = _start_waiting(
        lambda i: {
            "CANRIG_COORDINATOR": f"127.0.0.1:{port}",
            "CANRIG_PROCESSES": "2",
            "CANRIG_PROCESS_ID": str(i),
        }
    )
    try:
        _wait_until_alive(procs[1 - killed])
        procs[killed].send_signal(signal.SIGKILL)
        start = time.monotonic()
        survivor = procs[1 - killed]
        _, err = survivor.communicate(timeout=90)
        elapsed = time.monotonic() - start
    finally:
        for p in procs:
            p.kill()
    assert survivor.returncode != 0
    assert elapsed < 60, f"the survivor took {elapsed:.0f} s to end"
    assert "another task died" in err


def test_a_slurm_environment_starts_the_run():
    job = str(4000 + os.getpid() % 1000)  # JAX derives the coordinator's port from the job id
    procs = _start_waiting(
        lambda i: {
            "SLURM_JOB_ID": job,
            "SLURM_STEP_NODELIST": "localhost",
            "SLURM_NTASKS": "2",
            "SLURM_PROCID": str(i),
            "SLURM_LOCALID": str(i),
        }
    )
    try:
        for i, p in enumerate(procs):
            assert f"process {i} of 2, from SLURM" in _wait_until_alive(p)[0]
    finally:
        for p in procs:
            p.kill()
            p.wait()

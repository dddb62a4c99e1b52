"""``canrig_jax.watchdog``: a step with no progress ends the process with a clear message, every
thread's stack and exit status 70 (in a subprocess); progress keeps it alive; the limit from
``CANRIG_WATCHDOG`` is checked."""

import subprocess
import sys
import time

import pytest

from canrig_jax.watchdog import EXIT_STATUS, limit_from_environment, watchdog


def _run(body: str) -> tuple[subprocess.CompletedProcess, float]:
    script = "import time\nfrom canrig_jax.watchdog import watchdog, progress\n" + body
    start = time.monotonic()
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    return run, time.monotonic() - start


def test_a_stuck_step_ends_with_a_message_and_the_stacks():
    run, _ = _run(
        "def stuck_solve():\n    time.sleep(50)\n"
        "with watchdog(1.0, 'the fit'):\n    progress('first frame')\n    stuck_solve()\n"
    )
    assert run.returncode == EXIT_STATUS
    assert "no progress for 1 s in the fit (last step: first frame)" in run.stderr
    assert "stuck_solve" in run.stderr  # the stack of the blocked thread


@pytest.mark.slow
def test_progress_keeps_it_alive_and_leaving_disarms_it():
    run, _ = _run(
        "with watchdog(1.0, 'the take'):\n"
        "    for i in range(12):\n        time.sleep(0.25)\n        progress(f'frame {i}')\n"
        "time.sleep(2.0)\nprint('done')\n"
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "done"


def test_limit_from_environment(monkeypatch):
    monkeypatch.delenv("CANRIG_WATCHDOG", raising=False)
    assert limit_from_environment(600.0) == 600.0
    monkeypatch.setenv("CANRIG_WATCHDOG", "0")
    assert limit_from_environment(600.0) is None
    with watchdog(limit_from_environment(600.0)) as dog:
        assert dog is None
    for bad in ("soon", "-3", "inf"):
        monkeypatch.setenv("CANRIG_WATCHDOG", bad)
        with pytest.raises(ValueError, match="CANRIG_WATCHDOG"):
            limit_from_environment(600.0)
    with pytest.raises(ValueError, match="seconds"):
        watchdog(float("nan"))


def test_runs_where_standard_error_has_no_file_descriptor(capsys, monkeypatch):
    """Under a capturing runner (no ``fileno``) the watchdog still arms and disarms."""
    import io

    monkeypatch.setattr(sys, "stderr", io.StringIO())
    monkeypatch.setattr(sys, "__stderr__", io.StringIO())
    with watchdog(5.0, "captured") as dog:
        dog.progress("a step")
    assert dog.last == "a step"

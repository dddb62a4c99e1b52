"""Start N local processes of one command, as ``srun`` does on a cluster (``canrig launch``).

For one machine only (tests, a workstation with several accelerators): each copy gets
``CANRIG_COORDINATOR=127.0.0.1:PORT``, ``CANRIG_PROCESSES=N`` and ``CANRIG_PROCESS_ID=i`` and
its output lines prefixed ``[i]``. The run ends when every process has ended; when one fails,
the others are given ``grace_s`` seconds to end by themselves (JAX's coordination service ends
them after its heartbeat timeout), then stopped. On a cluster use its launcher (``srun``, a
Kubernetes indexed Job): ``initialize`` reads what they set.
"""

import contextlib
import dataclasses
import io
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence

from .. import watchdog
from ._process_group import ENV_COORDINATOR, ENV_PROCESS_ID, ENV_PROCESSES


def free_port() -> int:
    """A TCP port on localhost that was free a moment ago."""
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclasses.dataclass(frozen=True)
class LaunchResult:
    """How a launched run ended (``launch`` lists the fields)."""

    returncodes: tuple[int, ...]
    first_failure: int | None
    seconds: float
    stopped: tuple[int, ...]

    @property
    def returncode(self) -> int:
        """0 when every process succeeded, else the first failure's status (1 for a signal)."""
        if self.first_failure is None:
            return 0
        code = self.returncodes[self.first_failure]
        return code if code > 0 else 1

    def describe(self) -> str:
        if self.first_failure is None:
            return f"{len(self.returncodes)} processes succeeded in {self.seconds:.1f} s"
        first = self.first_failure
        parts = [f"process {first} failed first ({_status(self.returncodes[first])})"]
        for i, code in enumerate(self.returncodes):
            if i != self.first_failure:
                how = "stopped by launch" if i in self.stopped else _status(code)
                parts.append(f"process {i}: {how}")
        return "; ".join(parts) + f"; {self.seconds:.1f} s in all"


def _status(code: int) -> str:
    if code == 0:
        return "exit 0"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    if code == 134:
        return "exit 134: aborted (JAX's 'another task died')"
    return f"exit {code}"


def _relay(stream, out: io.TextIOBase, prefix: str) -> None:
    for line in iter(stream.readline, b""):
        out.write(prefix + line.decode(errors="replace"))
        out.flush()
    stream.close()


def launch(
    command: Sequence[str],
    processes: int,
    *,
    port: int | None = None,
    grace_s: float = 60.0,
    env: Mapping[str, str] | None = None,
    stdout: io.TextIOBase | None = None,
    stderr: io.TextIOBase | None = None,
) -> LaunchResult:
    """Run ``processes`` copies of ``command`` (argv) on this machine as one multi-process run
    (module docstring) and wait for them. ``port``: the coordinator's (default: a free one);
    ``env``: the environment (default: this one's) to which the ``CANRIG_*`` variables are
    added; ``stdout``/``stderr``: where the prefixed lines go (default: this process's).
    Never raises for a failed process.

    Returns:
        How the run ended, a ``LaunchResult``: ``returncodes``, each process's exit status
        (negative: killed by that signal); ``first_failure``, the process that failed first,
        or None when all succeeded; ``seconds``, the wall-clock time from the start to the
        last process's end; ``stopped``, the processes ``launch`` had to stop after the grace
        period; ``returncode``, 0 when every process succeeded, else the first failure's
        status (1 for a signal); ``describe()``, what happened in words.
    """
    command = [str(c) for c in command]
    if not command:
        raise ValueError("command: expected a command to launch, got nothing")
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes: expected a positive number of processes, got {processes!r}")
    if grace_s < 0:
        raise ValueError(f"grace_s: expected a non-negative number of seconds, got {grace_s}")
    port = free_port() if port is None else port
    base = dict(os.environ if env is None else env)
    base[ENV_COORDINATOR] = f"127.0.0.1:{port}"
    base[ENV_PROCESSES] = str(processes)
    out, err = stdout or sys.stdout, stderr or sys.stderr
    start = time.monotonic()
    children, relays = [], []
    for i in range(processes):
        child = subprocess.Popen(
            command,
            env={**base, ENV_PROCESS_ID: str(i), "PYTHONUNBUFFERED": "1"},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        children.append(child)
        for stream, sink in ((child.stdout, out), (child.stderr, err)):
            relay = threading.Thread(target=_relay, args=(stream, sink, f"[{i}] "), daemon=True)
            relay.start()
            relays.append(relay)
    first_failure, failed_at, stopped = None, 0.0, []
    try:
        while any([c.poll() is None for c in children]):  # a list: poll every child
            if first_failure is None:
                for i, c in enumerate(children):
                    if c.returncode not in (None, 0):
                        first_failure, failed_at = i, time.monotonic()
                        break
            elif time.monotonic() - failed_at > grace_s:
                stopped = [i for i, c in enumerate(children) if c.poll() is None]
                _stop([children[i] for i in stopped])
                break
            watchdog.progress(f"launch: {processes} processes running")  # they watch themselves
            time.sleep(0.1)
    finally:
        _stop([c for c in children if c.poll() is None])
        for relay in relays:
            relay.join(timeout=5)
    codes = tuple(int(c.wait()) for c in children)
    if first_failure is None:
        first_failure = next((i for i, c in enumerate(codes) if c != 0), None)
    return LaunchResult(codes, first_failure, time.monotonic() - start, tuple(stopped))


def _stop(children: Sequence[subprocess.Popen]) -> None:
    """SIGTERM, then SIGKILL after 5 s."""
    for c in children:
        c.terminate()
    deadline = time.monotonic() + 5
    for c in children:
        try:
            c.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            c.kill()
            c.wait()

"""Which process of how many (arguments, CANRIG_* variables, SLURM, a Kubernetes indexed Job),
shares of a batch, work gathered in one process, and the local launcher's verdicts. The runs
with real processes are in ``test_two_processes.py`` (-m slow, ``nox -s distributed``)."""

import io
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax import distributed
from canrig_jax.distributed._process_group import ProcessGroup, process_group
from canrig_jax.distributed._share import process_share

SLURM = {
    "SLURM_JOB_ID": "4242",
    "SLURM_STEP_NODELIST": "node[001-004]",
    "SLURM_NTASKS": "4",
    "SLURM_PROCID": "2",
    "SLURM_LOCALID": "0",
}


def test_resolution_order():
    env = {"CANRIG_COORDINATOR": "h:1234", "CANRIG_PROCESSES": "3", "CANRIG_PROCESS_ID": "1"}
    assert process_group(environ={}) == ProcessGroup(1, 0, None, "one process")
    group = process_group(environ=env)
    assert (group.processes, group.process_id, group.coordinator) == (3, 1, "h:1234")
    assert group.source == "CANRIG_* environment" and not group.is_main
    # an argument wins over its variable; the others still come from the environment
    group = process_group(process_id=0, environ=env)
    assert (group.processes, group.process_id, group.source) == (3, 0, "arguments")
    # the CANRIG_* variables win over SLURM's; SLURM alone leaves the coordinator to JAX
    assert process_group(environ={**SLURM, **env}).processes == 3
    slurm = process_group(environ=SLURM)
    assert (slurm.processes, slurm.process_id, slurm.coordinator, slurm.source) == (
        4,
        2,
        None,
        "SLURM",
    )
    # a Kubernetes indexed Job: the id from JOB_COMPLETION_INDEX
    job = {"CANRIG_COORDINATOR": "job-0.svc:1234", "CANRIG_PROCESSES": "2"}
    group = process_group(environ={**job, "JOB_COMPLETION_INDEX": "1"})
    assert group.process_id == 1 and "Kubernetes" in group.source


@pytest.mark.parametrize(
    "kwargs, env, match",
    [
        ({"processes": 2, "process_id": 0}, {}, "coordinator: a run of 2 processes"),
        ({"processes": 2, "coordinator": "h:1"}, {}, "process_id: a run of 2"),
        ({"processes": 2, "process_id": 2, "coordinator": "h:1"}, {}, "process_id: expected"),
        ({"processes": 2, "process_id": 0, "coordinator": "h"}, {}, "coordinator: expected HOST"),
        ({}, {"CANRIG_PROCESSES": "two"}, "CANRIG_PROCESSES: expected an integer"),
        ({}, {"CANRIG_PROCESSES": "0"}, "CANRIG_PROCESSES: expected at least 1"),
        ({}, {**SLURM, "SLURM_PROCID": "7"}, "SLURM_PROCID: expected a process id from 0 to 3"),
    ],
)
def test_bad_values_are_named(kwargs, env, match):
    with pytest.raises(ValueError, match=match):
        process_group(**kwargs, environ=env)


def test_initialize_one_process_starts_nothing():
    assert distributed.initialize(processes=1).processes == 1
    assert not jax.distributed.is_initialized()
    with pytest.raises(ValueError, match="heartbeat_s"):
        distributed.initialize(heartbeat_s=0)


@pytest.mark.parametrize("n, processes", [(45, 2), (7, 3), (1, 2), (0, 4), (64, 8)])
def test_shares_cover_every_item_once(n, processes):
    shares = [process_share(n, processes, i) for i in range(processes)]
    covered = np.concatenate([np.arange(n)[s] for s in shares])
    np.testing.assert_array_equal(covered, np.arange(n))  # in order, no gaps, no repeats
    sizes = [s.stop - s.start for s in shares]
    assert max(sizes) - min(sizes) <= -(-n // processes)  # contiguous shares, equal but the tail


def test_gather_frames_in_one_process_is_frame_wise():
    calls = []

    def fn(batch):
        calls.append(batch["x"].shape[0])
        return {"y": jnp.sin(batch["x"]) * batch["scale"][:, None]}

    batch = {"x": np.arange(21.0).reshape(7, 3), "scale": np.arange(7.0)}
    whole = fn(batch)
    chunked = distributed.gather_frames(fn, batch, chunk=3)
    assert calls == [7, 3, 3, 3]  # one compiled shape: the last chunk is padded
    np.testing.assert_array_equal(chunked["y"], whole["y"])
    keys = jax.random.split(jax.random.key(0), 5)  # typed keys are gathered too
    data = jax.vmap(jax.random.key_data)
    got = distributed.gather_frames(lambda k: data(k), keys, chunk=2)
    np.testing.assert_array_equal(got, data(keys))
    with pytest.raises(ValueError, match="batch: expected array leaves sharing one"):
        distributed.gather_frames(fn, {"x": np.zeros((2, 1)), "scale": np.zeros(3)})
    with pytest.raises(ValueError, match="chunk: expected a positive"):
        distributed.gather_frames(fn, batch, chunk=0)


def test_map_items_in_one_process():
    assert distributed.map_items(lambda x: x * 2, [1, 2, 3]) == [2, 4, 6]


def _python(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def test_launch_sets_the_environment_and_reports_the_first_failure():
    out, err = io.StringIO(), io.StringIO()
    code = "import os; print(os.environ['CANRIG_PROCESS_ID'], os.environ['CANRIG_PROCESSES'])"
    result = distributed.launch(_python(code), 3, stdout=out, stderr=err)
    assert result.returncode == 0 and result.first_failure is None
    assert sorted(out.getvalue().splitlines()) == ["[0] 0 3", "[1] 1 3", "[2] 2 3"]
    # process 1 fails at once; process 0 would run 30 s: stopped after the grace period
    code = (
        "import os, sys, time; i = int(os.environ['CANRIG_PROCESS_ID']); "
        "sys.exit(5) if i == 1 else time.sleep(30)"
    )
    result = distributed.launch(_python(code), 2, grace_s=0.5, stdout=out, stderr=err)
    assert result.first_failure == 1 and result.returncode == 5
    assert result.stopped == (0,) and result.seconds < 20
    assert "process 1 failed first (exit 5); process 0: stopped by launch" in result.describe()
    with pytest.raises(ValueError, match="processes: expected a positive"):
        distributed.launch(_python("pass"), 0)


def test_launch_command_line(capsys):
    from canrig_jax import run_command

    assert run_command(["launch", "-n", "2"]) == 2
    assert "COMMAND: give the command to run after --" in capsys.readouterr().err
    code = "import os, sys; sys.exit(3 * int(os.environ['CANRIG_PROCESS_ID']))"
    assert run_command(["launch", "-n", "2", "--quiet", "--", sys.executable, "-c", code]) == 3
    assert "process 1 failed first (exit 3)" in capsys.readouterr().err


def test_only_independent_frames_are_shared_across_processes():
    from canrig_jax import inverse
    from canrig_jax.rig import BlendshapeRig

    rng = np.random.default_rng(1)  # a toy rig: the check comes before any solve
    rig = BlendshapeRig(
        rng.normal(size=(6, 3)).astype(np.float32),
        rng.normal(size=(4, 6, 3)).astype(np.float32),
        (),
        ("a", "b", "c", "d"),
        np.array([[0, 1, 2], [3, 4, 5]]),
    )
    targets = np.repeat(np.asarray(rig.neutral)[None], 3, axis=0)
    for method, warm in ((inverse.TemporalNewton(alpha=0.1, smoothness=1.0), False),
                         (inverse.QuarticNewton(alpha=0.1), True)):  # fmt: skip
        with pytest.raises(ValueError, match="across_processes: frames are shared"):
            inverse.solve_sequence(rig, targets, method, warm_start=warm, across_processes=True)

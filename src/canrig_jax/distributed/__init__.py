"""Runs beyond one process: JAX's multi-controller runtime (``jax.distributed``), started from
the arguments or the environment a launcher sets, and work shared across its processes.

- ``initialize()`` first in every process (it returns this process's place in the run;
  ``add_process_options``/``initialize_from_args`` for scripts). Afterwards the trainers
  (``canrig.train``, ``pbs.train_pbs``, ``autorig.train_riganyface``) run data-parallel over
  every process's devices, process 0 writing the checkpoint.
- ``gather_frames(fn, batch)``: frame-independent work (``inverse.solve_sequence(...,
  across_processes=True)``) in shares, gathered in frame order; ``map_items(fn, items)``: one
  item per call, results of any shape (``autorig.auto_rig_heads(..., across_processes=True)``).
- ``launch(command, processes)``: N local copies of a command (``canrig launch``), for one
  machine; clusters use their own launcher (SLURM's ``srun``, a Kubernetes indexed Job).

The guide ``docs/guides/distributed.md`` shows each with the environment it needs.
"""

from ._launch import launch
from ._process_group import add_process_options, initialize, initialize_from_args
from ._share import gather_frames, map_items

__all__ = [
    "add_process_options",
    "gather_frames",
    "initialize",
    "initialize_from_args",
    "launch",
    "map_items",
]

"""Several processes, one sweep: JAX's multi-controller runtime (``jax.distributed``).

A multi-process sweep starts the same program once per process (one per host, or one per
GPU); each process joins the others through a coordinator (``host:port`` of process 0),
after which ``jax.devices()`` lists every device of every process.  The sweep shards its
runs over all of them; every process builds the same batches from the seed, and the
per-run metrics are gathered on every process after each batch
(:func:`uimm_jax.studies.sweep.run_sweep`).  Process 0 writes the outputs.

:func:`initialize` takes the coordinator, the process count and the process id from its
arguments, or -- when they are not given -- from the environment of a multi-task launch:
a Slurm job step started by ``srun`` with more than one task, or an Open MPI ``mpirun``
with more than one rank (:func:`cluster_launch`).  A plain process with none of these
stays single-process.  It must run before anything starts a JAX backend.

:func:`share` hands process 0's host values to every process (resume records, refusals).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

__all__ = ["cluster_launch", "initialize", "is_main", "share"]


def _int_env(env: Mapping[str, str], name: str) -> int:
    try:
        return int(env.get(name, "1"))
    except ValueError:
        return 1


def cluster_launch(env: Mapping[str, str] | None = None) -> str | None:
    """The multi-process launcher this process was started by, if any.

    Args:
        env: the environment (default ``os.environ``).

    Returns:
        ``"slurm"`` for a Slurm job step of more than one task (``srun``: the variables
        ``SLURM_STEP_ID``, ``SLURM_STEP_NODELIST``, ``SLURM_PROCID``, ``SLURM_LOCALID`` and
        ``SLURM_STEP_NUM_TASKS`` > 1), ``"ompi"`` for an Open MPI launch of more than one
        rank (``OMPI_COMM_WORLD_SIZE`` > 1 under ``mpirun``), else ``None`` (a batch
        script's own shell or an ``salloc`` shell is not a multi-process launch).
    """
    env = os.environ if env is None else env
    slurm = ("SLURM_JOB_ID", "SLURM_STEP_ID", "SLURM_STEP_NODELIST", "SLURM_PROCID",
             "SLURM_LOCALID", "SLURM_NTASKS")  # fmt: skip
    if all(v in env for v in slurm) and _int_env(env, "SLURM_STEP_NUM_TASKS") > 1:
        return "slurm"
    if "OMPI_MCA_orte_hnp_uri" in env and _int_env(env, "OMPI_COMM_WORLD_SIZE") > 1:
        return "ompi"
    return None


def _check_address(coordinator: str) -> None:
    host, sep, port = coordinator.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(
            f"--coordinator: {coordinator!r} is not HOST:PORT; give the address of process 0 "
            "and a free port, e.g. --coordinator node001:12345"
        )


def initialize(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    *,
    env: Mapping[str, str] | None = None,
) -> bool:
    """Join a multi-process run (``jax.distributed.initialize``) when one is asked for.

    With ``coordinator``, ``num_processes`` and ``process_id`` all given, those are used;
    with none given, a multi-task launch found by :func:`cluster_launch` lets JAX read its
    environment (Slurm: process 0's host from ``SLURM_STEP_NODELIST``, a port derived from
    the job id unless ``JAX_COORDINATOR_PORT`` sets one, one local GPU per task by
    ``SLURM_LOCALID``).  Call it before anything starts a JAX backend.

    Args:
        coordinator: ``HOST:PORT`` of process 0 (process 0 listens on it).
        num_processes: the number of processes (>= 1).
        process_id: this process's index, ``0 .. num_processes - 1``.
        env: the environment (default ``os.environ``).

    Returns:
        True if this process joined a multi-process run (or JAX had already been
        initialized for one), False for a single process.

    Raises:
        ValueError: only some of the three arguments given, or invalid ones.
    """
    import jax

    given = [v is not None for v in (coordinator, num_processes, process_id)]
    if any(given) and not all(given):
        raise ValueError(
            "--coordinator, --num-processes and --process-id go together: give all three "
            "(or none, under srun or mpirun, to read them from the cluster's environment)"
        )
    if jax.distributed.is_initialized():
        return jax.process_count() > 1
    if all(given):
        _check_address(coordinator)
        if not isinstance(num_processes, int) or num_processes < 1:
            raise ValueError(f"--num-processes: expected an integer >= 1, got {num_processes!r}")
        if not isinstance(process_id, int) or not 0 <= process_id < num_processes:
            raise ValueError(
                f"--process-id: expected an integer in 0..{num_processes - 1} "
                f"(--num-processes {num_processes}), got {process_id!r}"
            )
        if num_processes == 1:
            return False
        jax.distributed.initialize(coordinator, num_processes, process_id)
        return True
    if cluster_launch(env) is None:
        return False
    jax.distributed.initialize()
    return jax.process_count() > 1


def is_main() -> bool:
    """True on process 0 (the one that prints and writes), and in a single process."""
    import jax

    return jax.process_index() == 0


def share(tree):
    """Process 0's value of a pytree of host arrays, on every process.

    Every process must call it with arrays of the same shapes and dtypes (the values of
    the other processes are ignored); it returns writable NumPy copies.  A single process
    gets its own values back.
    """
    import jax

    if jax.process_count() == 1:
        return tree
    from jax.experimental import multihost_utils

    out = multihost_utils.broadcast_one_to_all(jax.tree.map(np.asarray, tree))
    return jax.tree.map(np.array, out)  # writable host copies

"""Multi-process runs: is this process one of several an MPI launcher started, and if so the
communicator. mpi4py is imported only then, so a single process never pays for it. A model kind
that trains across processes (its Kind.distributed) uses the communicator."""
from __future__ import annotations

import os

# The world size MPI launchers put in the environment of every process they start (Open MPI's
# mpirun; PMI launchers: MPICH and Intel MPI's Hydra, srun --mpi=pmi2). Without one, the
# process is alone and mpi4py is not imported.
LAUNCHER_SIZE_VARS = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE")


def launched_size() -> int:
    """Number of processes the MPI launcher says it started (1 when none did)."""
    for v in LAUNCHER_SIZE_VARS:
        try:
            n = int(os.environ.get(v, ""))
        except ValueError:
            continue
        if n > 0:
            return n
    return 1


def world():
    """The mpi4py COMM_WORLD of a multi-process MPI run, or None (single process, or mpi4py not
    installed: then the launcher's processes would each train alone, which is refused)."""
    if launched_size() <= 1:
        return None
    pin_threads()
    try:
        from mpi4py import MPI
    except ImportError:
        raise RuntimeError(f"started by an MPI launcher with {launched_size()} processes but "
                           f"mpi4py is not installed: pip install 'clrf[mpi]' (needs an MPI "
                           f"library, e.g. Debian's openmpi-bin libopenmpi-dev)") from None
    comm = MPI.COMM_WORLD
    return comm if comm.Get_size() > 1 else None


def pin_threads():
    """PoCL starts a thread per online CPU whatever the process's CPU affinity, so ranks bound
    to a core each (`mpirun --bind-to core`) would run several threads on it: where the
    launcher bound this process to fewer CPUs than are online, PoCL is told that many
    (POCL_MAX_PTHREAD_COUNT, unless the environment already says). Called before the first
    OpenCL call: PoCL reads it when its devices start (on bonsai_800 at downscale 4, 60 s
    of splats at 2 ranks: 1,009 steps against 923 without)."""
    try:
        mine = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return
    if 0 < mine < (os.cpu_count() or mine):
        os.environ.setdefault("POCL_MAX_PTHREAD_COUNT", str(mine))

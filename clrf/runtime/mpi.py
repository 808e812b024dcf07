"""Multi-process runs: is this process one of several an MPI launcher started, and if so the
communicator. mpi4py is imported only then, so a single process never pays for it. A model kind
that trains across processes (its Kind.distributed) uses the communicator."""
from __future__ import annotations

import os
import sys

# The world size MPI launchers put in the environment of every process they start (Open MPI's
# mpirun; PMI launchers: MPICH and Intel MPI's Hydra, srun --mpi=pmi2). Without one, the
# process is alone and mpi4py is not imported.
LAUNCHER_SIZE_VARS = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE")
LAUNCHER_RANK_VARS = ("OMPI_COMM_WORLD_RANK", "PMI_RANK")   # this process's rank, likewise


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
    own_kernel_cache()
    try:
        from mpi4py import MPI
    except ImportError:
        raise RuntimeError(f"started by an MPI launcher with {launched_size()} processes but "
                           f"mpi4py is not installed: pip install 'clrf[mpi]' (needs an MPI "
                           f"library, e.g. Debian's openmpi-bin libopenmpi-dev)") from None
    comm = MPI.COMM_WORLD
    if comm.Get_size() <= 1:
        return None
    _end_job_on_failure(comm)
    return comm


# the communicator whose job a failing process ends (world() sets it)
_JOB = None
# the exit status of an interrupted run: every rank was interrupted (the launcher forwards
# the signal) and each finishes its part of the checkpoint, so none ends the others
EXIT_INTERRUPTED = 130


def _end_job_on_failure(comm):
    """A rank that fails alone leaves the others waiting for it in a collective, and its own
    exit waits in MPI_Finalize on them: the job would hang until killed. From here on, an
    uncaught exception in this process ends the whole job (MPI_Abort) once its traceback is
    printed; a failing exit status does through ``end_job_if_failed``."""
    global _JOB
    if _JOB is not None:
        return
    _JOB = comm
    shown = sys.excepthook

    def hook(kind, value, tb):
        shown(kind, value, tb)
        end_job_if_failed(EXIT_INTERRUPTED if issubclass(kind, KeyboardInterrupt) else 1)

    sys.excepthook = hook


def end_job_if_failed(status) -> None:
    """Under an MPI launcher (once world() has run): a non-zero exit ``status`` other than an
    interrupt's ends every rank of the job with that status (MPI_Abort), so that one rank's
    error does not leave the others hanging. Otherwise returns."""
    if _JOB is None or not status or status == EXIT_INTERRUPTED:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    _JOB.Abort(int(status) if isinstance(status, int) else 1)


def own_kernel_cache():
    """PoCL's kernel cache is not safe for processes that build the same program at once
    (pocl issues 430 and 1480: failed builds and crashes), which is what the ranks of a job
    do on their first run: each rank gets a cache folder of its own, named by its rank so
    that later runs still hit it (POCL_CACHE_DIR, unless the environment already says).
    Called before the first OpenCL call."""
    if "POCL_CACHE_DIR" in os.environ:
        return
    rank = next((os.environ[v] for v in LAUNCHER_RANK_VARS if os.environ.get(v, "").isdigit()),
                None)
    if rank is None:
        return
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    os.environ["POCL_CACHE_DIR"] = os.path.join(base, "pocl", f"kcache-rank{rank}")


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

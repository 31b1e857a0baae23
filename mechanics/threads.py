"""Thread counts of the solver: the setting, the environment variable
``BREASTMODEL_THREADS`` or the cores of the process (never the load), and OpenBLAS held to
one thread inside a solve (the parallel work is PARDISO's, on its explicit count)."""

from __future__ import annotations

import os

#: Environment variable that sets the default thread count (see :func:`resolve_threads`).
THREADS_ENV = "BREASTMODEL_THREADS"


def machine_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover (no affinity on this platform)
        return max(1, os.cpu_count() or 1)


def resolve_threads(threads: int | None = None) -> int:
    """The thread count to use: ``threads`` when given (>= 1), else the environment variable
    ``BREASTMODEL_THREADS``, else :func:`machine_cores`. Never derived from the load: the
    same command runs on the same number of threads every time."""
    if threads is None:
        env = os.environ.get(THREADS_ENV, "").strip()
        if not env:
            return machine_cores()
        try:
            threads = int(env)
        except ValueError:
            raise ValueError(f"mechanics: {THREADS_ENV} must be a positive integer, "
                             f"got {env!r}") from None
        where = THREADS_ENV
    else:
        where = "threads"
    if int(threads) != threads or threads < 1:
        raise ValueError(f"mechanics: {where} must be a positive integer, got {threads!r}")
    return int(threads)


class single_thread_blas:
    """Context: OpenBLAS (numpy's and scipy's BLAS) on one thread inside the block.

    The Newton loop's BLAS calls are vector norms and dots of 10^4-10^5 entries, which
    threading only slows down (OpenBLAS's threads wake up on the cores that PARDISO's MKL
    threads use). The parallel work is PARDISO's, on its explicit thread count. A no-op
    without ``threadpoolctl``.
    """

    def __enter__(self):
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # pragma: no cover
            self._ctx = None
            return self
        self._ctx = threadpool_limits(limits={"libscipy_openblas": 1, "libopenblas": 1})
        return self

    def __exit__(self, *exc):
        if self._ctx is not None:
            self._ctx.restore_original_limits()
        return False

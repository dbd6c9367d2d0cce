"""Thread counts for a block of work, restored afterwards (no setting outlives its block).

Two thread pools share the CPUs: BLAS's (numpy, scipy: OpenBLAS pthreads, which spin for a
while after each call) and torch's (OpenMP). A tiny torch operation right after numpy work,
run with several torch threads, waits for cores that BLAS's spinning threads still hold, so it
is slower than with one thread. The classical path therefore runs its small torch work
single-threaded (:func:`torch_threads`), and :func:`thread_limit` sets both pools for a whole
computation. ``python -m bench speed --case threads`` checks that no workload is slower with all
threads than with one.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from threadpoolctl import ThreadpoolController, threadpool_limits

from .lazy import torch


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """torch's intra-op threads set to ``n`` inside the block and restored after it, also when
    it raises (``None``: unchanged). The setting is process-wide while the block runs."""
    if n is None:
        yield
        return
    previous = torch.get_num_threads()
    if previous == n:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def blas_limiter(n: int) -> Callable[[], contextlib.AbstractContextManager]:
    """A factory of contexts setting BLAS threads to ``n``, for a limit entered many times (each
    Krylov step): the loaded libraries are looked up once here, not at every entry."""
    controller = ThreadpoolController()
    return lambda: controller.limit(limits=n, user_api="blas")


@contextlib.contextmanager
def blas_threads(n: int | None) -> Iterator[None]:
    """BLAS threads (threadpoolctl) set to ``n`` inside the block, restored after it (``None``:
    unchanged)."""
    with contextlib.nullcontext() if n is None else threadpool_limits(limits=n, user_api="blas"):
        yield


@contextlib.contextmanager
def thread_limit(threads: int | None) -> Iterator[None]:
    """BLAS / OpenMP threads (threadpoolctl) and torch's threads set to ``threads`` inside the
    block, restored after it (``None``: all unchanged)."""
    with contextlib.nullcontext() if threads is None else threadpool_limits(limits=threads):
        with torch_threads(threads):
            yield

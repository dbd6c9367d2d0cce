"""Thread counts (BLAS via threadpoolctl, torch) for a block of work, restored afterwards. Small torch
work right after numpy runs single-threaded: OpenBLAS's spinning threads still hold the cores."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from threadpoolctl import ThreadpoolController, threadpool_limits

from .lazy import torch


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """torch's intra-op threads (process-wide) set to ``n`` inside the block (``None``: unchanged)."""
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
    """A factory of contexts setting BLAS threads to ``n`` (libraries looked up once, for many entries)."""
    controller = ThreadpoolController()
    return lambda: controller.limit(limits=n, user_api="blas")


@contextlib.contextmanager
def blas_threads(n: int | None) -> Iterator[None]:
    """BLAS threads set to ``n`` inside the block (``None``: unchanged)."""
    with contextlib.nullcontext() if n is None else threadpool_limits(limits=n, user_api="blas"):
        yield


@contextlib.contextmanager
def thread_limit(threads: int | None) -> Iterator[None]:
    """BLAS / OpenMP and torch threads set to ``threads`` inside the block (``None``: unchanged)."""
    with contextlib.nullcontext() if threads is None else threadpool_limits(limits=threads):
        with torch_threads(threads):
            yield

"""CPU threading of the batched solver: single-threaded kernels on worker threads (why:
:func:`workers_for`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import torch

__all__ = ["cpu_threads", "workers_for", "for_chunks"]


@contextmanager
def cpu_threads(device: torch.device | str, num_threads: int | None) -> Iterator[None]:
    """Temporarily lower torch's intra-op thread count for CPU work (no-op elsewhere).

    ``num_threads=None`` keeps torch's setting. The setting is process-wide while the block runs.
    """
    dev = torch.device(device)
    _check_threads(num_threads)
    old = torch.get_num_threads()
    if dev.type != "cpu" or num_threads is None or int(num_threads) >= old:
        yield
        return
    torch.set_num_threads(int(num_threads))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def workers_for(device: torch.device, num_threads: int | None) -> int:
    """Worker threads of the CPU solver: ``num_threads`` or torch's intra-op thread count.

    The solver runs thousands of small batched kernels. On a small machine shared with other
    processes every multi-threaded kernel waits at its barrier for a thread the OS has not
    scheduled: measured on the 2-core development machine under load, one frame took 3.6–9 s
    with torch's 2 intra-op threads and 0.6–1.1 s with one. So the solver runs single-threaded
    kernels and instead splits the pixels between ``num_threads`` Python threads (torch releases
    the GIL inside kernels), which never wait for each other within a kernel.
    """
    _check_threads(num_threads)
    if device.type != "cpu":
        return 1
    return int(num_threads) if num_threads is not None else torch.get_num_threads()


def _check_threads(num_threads: int | None) -> None:
    if num_threads is not None and int(num_threads) < 1:
        raise ValueError(f"num_threads must be >= 1 or None, got {num_threads}")


_POOLS: dict[int, ThreadPoolExecutor] = {}


def for_chunks(fn: Callable[[slice], None], num: int, n: int, workers: int) -> None:
    """Call ``fn(slice)`` for consecutive chunks of ``n`` of ``range(num)``.

    With ``workers > 1`` the chunks are split into ``workers`` contiguous blocks run by that many
    threads (``fn`` must write disjoint outputs).
    """
    chunks = [slice(s, min(num, s + n)) for s in range(0, num, max(1, n))]
    if workers <= 1 or len(chunks) <= 1:
        for sl in chunks:
            fn(sl)
        return
    workers = min(workers, len(chunks))
    per = -(-len(chunks) // workers)
    blocks = [chunks[i:i + per] for i in range(0, len(chunks), per)]
    pool = _POOLS.get(workers)
    if pool is None:
        pool = _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix="hsi_nnls")

    def run(block: list[slice]) -> None:
        for sl in block:
            fn(sl)

    for f in [pool.submit(run, blk) for blk in blocks]:
        f.result()



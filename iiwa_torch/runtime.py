"""The machine a run happens on: its facts, recorded next to every wall time, and its threads for
compiled work that releases the GIL (:func:`in_parts`)."""

from __future__ import annotations

import concurrent.futures
import functools
import os
import platform
import time
from pathlib import Path
from typing import Any

__all__ = ["cpu_model", "in_parts", "machine_info", "thread_pool"]


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (``platform.processor()`` elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine_info() -> dict[str, Any]:
    """Threads, OpenMP wait policy, load, CPU and versions: what decides how to read a time."""
    import torch

    return {
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "loadavg": list(os.getloadavg()),  # 1, 5 and 15 minutes
        "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }


def in_parts(n: int, work, threshold: int) -> None:
    """``work(start, stop)`` over ``range(n)``: in one call below ``threshold`` items or with one torch
    thread, else one part per torch thread, the parts run at once on :func:`thread_pool`'s threads
    (``work`` must release the GIL, as the compiled kernels marked ``jit_nogil`` do, and each part
    must write only its own items)."""
    if n < threshold:
        work(0, n)
        return
    import torch

    threads = torch.get_num_threads()
    if threads == 1:
        work(0, n)
        return
    size = -(-n // threads)
    starts = range(0, n, size)
    list(thread_pool(len(starts), os.getpid()).map(lambda start: work(start, min(start + size, n)), starts))


@functools.cache
def thread_pool(threads: int, pid: int) -> concurrent.futures.ThreadPoolExecutor:
    """A pool of ``threads`` threads for :func:`in_parts`, kept for the process ``pid``: a process forked
    from this one has none of its threads, so it builds its own."""
    return concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="iiwa_torch-parts")

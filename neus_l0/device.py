"""The torch device a command runs on, how many CPU threads it uses, waiting for it, and the
host memory available now."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch


def pick_device(name: str | None) -> str:
    """`name`, or cuda when available; cuda without a GPU is a user error.

    Args:
        name: "cpu", "cuda" or None (the `--device` flag of the commands).

    Returns:
        The device name.

    Raises:
        NeusL0Error: `name` is "cuda" and no CUDA device is available.
    """
    import torch

    from neus_l0.errors import NeusL0Error

    if name is None:
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise NeusL0Error("--device cuda: no CUDA device is available")
    return name


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA); nothing on the CPU."""
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def free_cpu_threads(requested: int | None = None) -> int:
    """Torch CPU threads for a command: `requested` when given (>= 1; at most the cores this
    process may use, with one line on stderr when more were asked), else those cores less
    the machine's recent load (rounded), at least 1.

    Torch's default of one thread per core is wrong on a shared machine: while another job
    holds a core, the threads wait on each other and training slows down several-fold
    (docs/BENCHMARKS.md, "How many CPU threads should training use?").
    """
    import os
    import sys

    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    if requested and int(requested) > cores:
        print(f"neus-l0: --threads {requested}: more than the {cores} cores this process may "
              f"use; using {cores}", file=sys.stderr, flush=True)
        return cores
    if requested:
        return max(1, int(requested))
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover
        load = 0.0
    return max(1, min(cores, int(cores - load + 0.5)))


def use_cpu_threads(requested: int | None, device: str) -> int | None:
    """Set torch's CPU threads from `free_cpu_threads` when the command runs on the CPU and
    return them (None on CUDA, where torch's default stays)."""
    if device != "cpu":
        return None
    import torch

    threads = free_cpu_threads(requested)
    torch.set_num_threads(threads)
    return threads


def _cgroup_available() -> int | None:
    """Memory left under a cgroup v2 or v1 limit (containers), or None without a limit."""
    pairs = [("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
             ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
              "/sys/fs/cgroup/memory/memory.usage_in_bytes")]
    for limit_file, usage_file in pairs:
        try:
            limit = Path(limit_file).read_text().strip()
            usage = int(Path(usage_file).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 2**60:
            return max(int(limit) - usage, 0)
    return None


def available_memory() -> int | None:
    """Bytes of host memory available now, or None where it cannot be told.

    Linux: ``MemAvailable`` of /proc/meminfo, capped by a cgroup limit; elsewhere
    ``os.sysconf`` (free physical pages), where the platform has it.
    """
    found = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found = int(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        found = None
    if found is None:
        try:
            found = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (AttributeError, ValueError, OSError):
            found = None
    cgroup = _cgroup_available()
    if cgroup is not None:
        found = cgroup if found is None else min(found, cgroup)
    return found

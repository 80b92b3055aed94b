"""The ``--threads`` flag of the commands that run torch on the CPU (`neus_l0.device`)."""

from __future__ import annotations

import argparse


def add_threads_flag(p: argparse.ArgumentParser) -> None:
    """``--threads N``: torch CPU threads (default: the cores free when the command starts)."""
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (default: the cores free when it starts, from the "
                        "load average; ignored on CUDA)")


def check_threads(threads: int | None) -> None:
    """Refuse ``--threads`` below 1, before any work.

    Raises:
        NeusL0Error: naming the flag.
    """
    from neus_l0.errors import NeusL0Error

    if threads is not None and threads < 1:
        raise NeusL0Error(f"--threads {threads}: must be at least 1 (leave it out for the "
                          "free cores)")


def use_threads(threads: int | None, device: str) -> int | None:
    """Check ``--threads`` and set torch's CPU threads (`neus_l0.device.use_cpu_threads`):
    `threads`, or the free cores; None on CUDA."""
    from neus_l0.device import use_cpu_threads

    check_threads(threads)
    return use_cpu_threads(threads, device)

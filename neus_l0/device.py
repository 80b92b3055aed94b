"""The torch device a command runs on, and waiting for it."""

from __future__ import annotations

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

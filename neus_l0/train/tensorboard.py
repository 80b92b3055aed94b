"""TensorBoard events in a run folder: scalars and images, for ``tensorboard --logdir RUN``.

A thin layer over `torch.utils.tensorboard.SummaryWriter`, which is imported on the first
write (importing it loads TensorBoard, about a second), so a run that logs nothing does not
pay for it. The event files (``events.out.tfevents.*``) go straight into the run folder, so
``tensorboard --logdir RUNS`` over a folder of runs names each run by its folder.
`metrics.jsonl` stays the run's record; these events are for watching.

On a resumed run, pass the resumed iteration as `purge_step`: TensorBoard then hides the
events at or after it that the interrupted run had written, so the curves do not overlap.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np


class TensorBoardLogger:
    """Writes scalars and images of a run as TensorBoard events.

    Args:
        run_dir: the run folder (created if missing); the events go into it.
        purge_step: on a resume, the iteration it resumes from (see the module docstring);
            None for a fresh run.
        flush_secs: how often the writer flushes to disk.
    """

    def __init__(self, run_dir: str | Path, purge_step: int | None = None,
                 flush_secs: int = 30):
        self.run_dir = Path(run_dir)
        self.purge_step = purge_step
        self.flush_secs = flush_secs
        self._writer = None

    @property
    def writer(self):
        """The `SummaryWriter`, made on first use."""
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter

            self.run_dir.mkdir(parents=True, exist_ok=True)
            self._writer = SummaryWriter(log_dir=str(self.run_dir), purge_step=self.purge_step,
                                         flush_secs=self.flush_secs)
        return self._writer

    def scalars(self, step: int, values: Mapping[str, float], prefix: str = "train/") -> None:
        """One point per value at `step`, tagged ``prefix + name``.

        Values may be Python or NumPy numbers or one-element tensors/arrays; others (None,
        strings, lists, booleans) are skipped. NaN and infinities are written as they are
        (TensorBoard shows them), so a diverging run is visible.
        """
        for name, value in values.items():
            number = _as_float(value)
            if number is not None:
                self.writer.add_scalar(f"{prefix}{name}", number, global_step=int(step))

    def image(self, step: int, tag: str, rgb_uint8_hwc: np.ndarray) -> None:
        """An RGB image at `step`.

        Args:
            rgb_uint8_hwc: (H, W, 3) uint8, e.g. `neus_l0.train.validation.validation_image`'s.

        Raises:
            ValueError: another shape or dtype.
        """
        img = np.asarray(rgb_uint8_hwc)
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"image {tag}: expected (H, W, 3) uint8, got {img.shape} "
                             f"{img.dtype}")
        self.writer.add_image(tag, img, global_step=int(step), dataformats="HWC")

    def flush(self) -> None:
        """Write what is buffered to disk now."""
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        """Flush and close the event file (idempotent; a later write opens a new one)."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> TensorBoardLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _as_float(value) -> float | None:
    """A real number as float, or None for anything else."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float, np.number)):
        return float(value)
    if hasattr(value, "numel") and hasattr(value, "item"):  # a torch tensor
        return float(value.item()) if value.numel() == 1 and not value.is_complex() else None
    if isinstance(value, np.ndarray) and value.size == 1 and np.isrealobj(value):
        return float(value.item()) if value.dtype.kind in "iuf" else None
    return None

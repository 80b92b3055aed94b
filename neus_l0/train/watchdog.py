"""Divergence: what the logged metrics say about a run that has gone wrong.

A run diverges when a logged number is not finite, when the loss explodes (NeuS's loss is
colour L1 + weighted Eikonal + weighted mask BCE: of order 1 in a healthy run, whatever the
scene), or when the PSNR falls well below the best it reached and stays there. The loop
asks `Watchdog.check` at every log line and stops the run at the first verdict; the
checkpoints of the suspect stretch are set aside, so that a resume starts from the last
good one.
"""

from __future__ import annotations

import dataclasses
import math

#: A logged loss above this is an explosion (healthy NeuS losses are of order 1).
LOSS_LIMIT = 1e3
#: A PSNR this many dB below the best so far is suspect...
PSNR_DROP = 3.0
#: ...and this many suspect log lines in a row are a divergence.
PATIENCE = 3


@dataclasses.dataclass
class Watchdog:
    """The verdict of a run's log lines so far.

    Attributes:
        best_psnr: the best PSNR logged.
        suspect: suspect log lines in a row (PSNR more than `PSNR_DROP` below the best).
        last_good_iter: the iteration of the newest log line that was not suspect (None
            before the first).
    """

    best_psnr: float = -math.inf
    suspect: int = 0
    last_good_iter: int | None = None

    def check(self, metrics: dict) -> str | None:
        """Read one log line (``iter``, ``loss``, ``psnr``, ...); return why the run
        diverged, or None while it has not."""
        numbers = {k: v for k, v in metrics.items()
                   if isinstance(v, (int, float)) and not isinstance(v, bool)}
        bad = sorted(k for k, v in numbers.items() if not math.isfinite(v))
        if bad:
            return f"{', '.join(bad)} not finite"
        loss, psnr = metrics["loss"], metrics["psnr"]
        if loss > LOSS_LIMIT:
            return f"the loss exploded to {loss:.3g}"
        if psnr < self.best_psnr - PSNR_DROP:
            self.suspect += 1
            if self.suspect >= PATIENCE:
                return (f"the PSNR fell from {self.best_psnr:.2f} to {psnr:.2f} dB and stayed "
                        f"below {self.best_psnr - PSNR_DROP:.2f} for {self.suspect} log lines")
            return None
        self.suspect = 0
        self.best_psnr = max(self.best_psnr, psnr)
        self.last_good_iter = int(metrics["iter"])
        return None

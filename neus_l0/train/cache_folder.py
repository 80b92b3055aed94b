"""neus-l0's cache folder (``$XDG_CACHE_HOME/neus-l0``, else ``~/.cache/neus-l0``): inductor's
compiled kernels and the record of compile times that `train.compile: auto` reads
(`neus_l0.train.compile_auto`). Imports nothing heavy: the CLI calls `use_persistent_cache`
before torch loads.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path:
    """neus-l0's cache folder: ``$XDG_CACHE_HOME/neus-l0``, else ``~/.cache/neus-l0``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "neus-l0"


def compile_record_path() -> Path:
    """The record of measured compile times, one entry per step key."""
    return cache_root() / "compile_times.json"


def use_persistent_cache() -> Path:
    """Point torch's inductor cache at ``cache_root()/inductor`` unless one is chosen
    (``TORCHINDUCTOR_CACHE_DIR``); returns the folder in use.

    Call it before torch imports ``torch._dynamo`` (creating an optimiser does): that import
    sets ``TORCHINDUCTOR_CACHE_DIR`` to torch's default under /tmp, which then counts as
    chosen. The CLI calls it first thing.
    """
    chosen = os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    if chosen:
        return Path(chosen)
    folder = cache_root() / "inductor"
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(folder)
    return folder

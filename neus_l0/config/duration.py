"""Durations in configs and on the command line: ``240``, ``90s``, ``10m``, ``1h``, ``1.5h``."""

from __future__ import annotations

import math
import re

from neus_l0.errors import ConfigError

#: Seconds per unit suffix.
UNITS = {"": 1.0, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}
#: The longest budget accepted (one week): longer is surely a typo (``1e9``).
MAX_SECONDS = 7 * 24 * 3600.0
_FORM = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-z]*)\s*$")


def parse_seconds(value: object, key: str, allow_zero: bool = True) -> float:
    """A duration in seconds from a number or a string with a unit (s, m, min, h).

    Args:
        value: ``240``, ``240.0``, ``"90s"``, ``"10m"``, ``"1h"``.
        key: the key or flag named in errors (``train.budget``, ``--budget``).
        allow_zero: whether 0 (off) is accepted.

    Raises:
        ConfigError: one line naming `key`: not a duration, negative, zero when not
            allowed, not finite or over a week.
    """
    hint = "seconds, or a number with s, m or h, e.g. 90s, 10m, 1h"
    if isinstance(value, bool):
        raise ConfigError(f"{key}: {value!r} is not a duration ({hint})")
    if isinstance(value, (int, float)):
        seconds = float(value)
    else:
        text = str(value).strip().lower()
        match = _FORM.match(text)
        if match is None or match.group(2) not in UNITS:
            if text.startswith("-"):
                raise ConfigError(f"{key}: {value}: must not be negative ({hint})")
            raise ConfigError(f"{key}: {value!r} is not a duration ({hint})")
        seconds = float(match.group(1)) * UNITS[match.group(2)]
    if not math.isfinite(seconds) or seconds > MAX_SECONDS:
        raise ConfigError(f"{key}: {value}: more than a week; give e.g. 10m or 2h")
    if seconds < 0:
        raise ConfigError(f"{key}: {value}: must not be negative ({hint})")
    if seconds == 0 and not allow_zero:
        raise ConfigError(f"{key}: {value}: must be more than 0 ({hint})")
    return seconds

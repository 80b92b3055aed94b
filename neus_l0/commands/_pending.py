"""Shared helper for subcommands whose implementation has not landed yet."""

from __future__ import annotations

from neus_l0.errors import NeusL0Error


def not_yet(command: str, issue: str) -> int:
    """Raise a clear error saying which piece of work provides `command`."""
    raise NeusL0Error(f"'{command}' is not implemented yet: it arrives with {issue}.")

"""`neus-l0 figures`: figures of pits and thin structures compared between samplers.

Not implemented yet: the benchmark issue brings it.
"""

from __future__ import annotations

import argparse

from neus_l0.commands._pending import not_yet


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="figures of pits and thin structures compared between samplers "
                                  "[pending: the benchmark issue]")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return p


def run(args: argparse.Namespace) -> int:
    return not_yet("figures", "the benchmark issue")

"""`neus-l0 bench`: sweep scenes x samplers x budgets and record time against error.

Not implemented yet: the benchmark issue brings it.
"""

from __future__ import annotations

import argparse

from neus_l0.commands._pending import not_yet


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="sweep scenes x samplers x budgets and record time against error "
                                  "[pending: the benchmark issue]")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return p


def run(args: argparse.Namespace) -> int:
    return not_yet("bench", "the benchmark issue")

"""`neus-l0 eval`: score a mesh by Chamfer distance (not implemented yet: the evaluation issue)."""

from __future__ import annotations

import argparse

from neus_l0.commands._pending import not_yet


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="score a mesh by Chamfer distance [pending: the evaluation issue]")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return p


def run(args: argparse.Namespace) -> int:
    return not_yet("eval", "the evaluation issue")

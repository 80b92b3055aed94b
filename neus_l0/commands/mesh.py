"""`neus-l0 mesh`: extract a mesh from a trained run (not implemented yet: the reconstruction issue)."""

from __future__ import annotations

import argparse

from neus_l0.commands._pending import not_yet


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="extract a mesh from a trained run [pending: the reconstruction issue]")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return p


def run(args: argparse.Namespace) -> int:
    return not_yet("mesh", "the reconstruction issue")

"""`neus-l0 inspect`: validate a NeuS-format scene and print a summary (not implemented yet: the scenes issue)."""

from __future__ import annotations

import argparse

from neus_l0.commands._pending import not_yet


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="validate a NeuS-format scene and print a summary [pending: the scenes issue]")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return p


def run(args: argparse.Namespace) -> int:
    return not_yet("inspect", "the scenes issue")

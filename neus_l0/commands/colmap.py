"""`neus-l0 colmap`: turn a folder of photos into a NeuS-format scene with pycolmap (not implemented yet: the own-photos issue)."""

from __future__ import annotations

import argparse

from neus_l0.commands._pending import not_yet


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="turn a folder of photos into a NeuS-format scene with pycolmap [pending: the own-photos issue]")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return p


def run(args: argparse.Namespace) -> int:
    return not_yet("colmap", "the own-photos issue")

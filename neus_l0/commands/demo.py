"""`neus-l0 demo`: make a small built-in scene, reconstruct it and score the mesh (not implemented yet: the reconstruction issue)."""

from __future__ import annotations

import argparse

from neus_l0.commands._pending import not_yet


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="make a small built-in scene, reconstruct it and score the mesh [pending: the reconstruction issue]")
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return p


def run(args: argparse.Namespace) -> int:
    return not_yet("demo", "the reconstruction issue")

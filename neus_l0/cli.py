"""The `neus-l0` command line.

Each subcommand lives in its own module under `neus_l0.commands` and exposes
`add_parser(subparsers)` (argument definitions, cheap imports only) and `run(args) -> int`
(the work, importing heavy modules lazily). User errors (`NeusL0Error`) are printed as one
line on stderr with exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from neus_l0 import __version__
from neus_l0.errors import NeusL0Error

#: Subcommands in the order `--help` lists them: (name, module under neus_l0.commands).
COMMANDS: list[tuple[str, str]] = [
    ("demo", "demo"),
    ("synth", "synth"),
    ("inspect", "inspect_scene"),
    ("colmap", "colmap"),
    ("train", "train"),
    ("mesh", "mesh"),
    ("render", "render"),
    ("eval", "evaluate"),
    ("bench", "bench"),
    ("figures", "figures"),
    ("study", "study"),
    ("config", "config"),
]


def build_parser() -> argparse.ArgumentParser:
    """Return the top-level parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="neus-l0",
        description="NeuS surface reconstruction with the L0-Sampler.",
    )
    parser.add_argument("--version", action="version", version=f"neus-l0 {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in COMMANDS:
        mod = importlib.import_module(f"neus_l0.commands.{module}")
        p = mod.add_parser(sub, name)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `neus-l0` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help()
        return 1
    try:
        return int(args._run(args) or 0)
    except NeusL0Error as exc:
        print(f"neus-l0 {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"neus-l0 {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

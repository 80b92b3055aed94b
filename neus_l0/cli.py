"""The `neus-l0` command line.

Each subcommand lives in its own module under `neus_l0.commands` and exposes
`add_parser(subparsers)` (argument definitions, cheap imports only) and `run(args) -> int`
(the work, importing heavy modules lazily). User errors (`NeusL0Error`) are printed as one
line on stderr with exit status 2.

Signals: Ctrl-C (SIGINT) and SIGTERM end a command with the shell's codes 130 and 143 and
one line on stderr. Where a command handles them itself (training finishes its step and
writes a checkpoint; the bench passes them on to its running run) it returns those codes;
elsewhere SIGINT is Python's `KeyboardInterrupt` and SIGTERM is raised the same way here,
so that ``finally`` blocks (locks, temporary files) run instead of the process dying.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import signal
import sys
import threading

from neus_l0 import __version__
from neus_l0.errors import NeusL0Error
from neus_l0.train.cache_folder import use_persistent_cache

#: Subcommands in the order `--help` lists them: (name, module under neus_l0.commands).
COMMANDS: list[tuple[str, str]] = [
    ("demo", "demo"),
    ("synth", "synth"),
    ("inspect", "inspect_scene"),
    ("colmap", "colmap"),
    ("train", "train"),
    ("mesh", "mesh"),
    ("render", "render"),
    ("view", "view"),
    ("eval", "evaluate"),
    ("bench", "bench"),
    ("figures", "figures"),
    ("checkpoint", "checkpoint"),
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


class _Terminated(BaseException):  # noqa: N818 - like KeyboardInterrupt, not an error
    """SIGTERM where no handler of the command's own catches it."""


def _raise_terminated(signum: int, frame) -> None:
    raise _Terminated


@contextlib.contextmanager
def _sigterm_raises():
    """SIGTERM raises `_Terminated` inside (main thread only; the old handler comes back)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `neus-l0` console script."""
    use_persistent_cache()  # before torch imports torch._dynamo, which fixes inductor's cache
    for stream in (sys.stdout, sys.stderr):  # a path that is not UTF-8 is shown, not fatal
        with contextlib.suppress(AttributeError, ValueError):
            stream.reconfigure(errors="backslashreplace")
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help()
        return 1
    try:
        with _sigterm_raises():
            return int(args._run(args) or 0)
    except NeusL0Error as exc:
        print(f"neus-l0 {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"neus-l0 {args.command}: interrupted", file=sys.stderr)
        return 130
    except _Terminated:
        print(f"neus-l0 {args.command}: terminated (SIGTERM)", file=sys.stderr)
        return 128 + int(signal.SIGTERM)


if __name__ == "__main__":
    sys.exit(main())

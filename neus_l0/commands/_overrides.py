"""Let a subcommand take `key=value` config overrides anywhere among its options.

argparse cannot split positionals around options (``train DATA --conf x a=1`` fails with
"unrecognized arguments"), so the subparser collects leftover ``key=value`` words itself.
"""

from __future__ import annotations

import argparse


def accept_overrides(parser: argparse.ArgumentParser, dest: str = "overrides") -> None:
    """Add a positional `dest` list and move stray ``key=value`` words into it."""
    parser.add_argument(dest, nargs="*", metavar="KEY=VALUE",
                        help="config overrides with dotted keys, e.g. train.iters=2000 "
                             "model.sdf.hidden=64 sampler=hvs")
    original = parser.parse_known_args

    def parse_known_args(args=None, namespace=None):
        ns, rest = original(args, namespace)
        extra = [a for a in rest if "=" in a and not a.startswith("-")]
        setattr(ns, dest, list(getattr(ns, dest, None) or []) + extra)
        return ns, [a for a in rest if a not in extra]

    parser.parse_known_args = parse_known_args  # type: ignore[method-assign]

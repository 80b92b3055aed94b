"""`neus-l0 config show`: the resolved config, every key with its one-line meaning."""

from __future__ import annotations

import argparse

from neus_l0.commands._overrides import accept_overrides
from neus_l0.config.load import conf_names


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="show the resolved config, each key with its meaning",
                       description="Print the config that `neus-l0 train --conf CONF "
                                   "[key=value ...]` would run with: every key, its value and "
                                   "its one-line meaning (from the schema's documentation).")
    p.add_argument("action", choices=["show"], help="show: print the resolved config")
    p.add_argument("--conf", default="wmask",
                   help="config: a YAML path, confs/NAME.yaml or a built-in NAME "
                        f"({', '.join(conf_names())}); default wmask")
    p.add_argument("--full", action="store_true",
                   help="each key's whole description, wrapped under it (default: its first "
                        "sentence on one line, cut at 110 characters)")
    accept_overrides(p)
    return p


def run(args: argparse.Namespace) -> int:
    from neus_l0.config.describe import format_listing
    from neus_l0.config.load import load_config, resolve_conf_path

    cfg = load_config(args.conf, args.overrides)
    print(f"# {resolve_conf_path(args.conf)}" +
          (f" with {' '.join(args.overrides)}" if args.overrides else ""))
    print(format_listing(cfg, full=args.full))
    return 0

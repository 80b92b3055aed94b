"""`neus-l0 checkpoint upgrade FILE --trust-pickle`: convert an old checkpoint to plain data.

Checkpoints load with ``torch.load(weights_only=True)``, which builds tensors and plain
values only, so that a checkpoint someone shared cannot run code. A checkpoint that names
Python objects (an older neus-l0's, or a planted one) is refused with a line naming this
command. Converting it unpickles it in full, which runs any code it carries: the command
does so only with ``--trust-pickle``, and then writes the checkpoint back as plain data
(`neus_l0.run.checkpoints.upgrade_checkpoint`).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="convert an old checkpoint to the safe format",
                       description="Rewrite a checkpoint that needs Python's pickle to load as "
                                   "plain tensors and values, which neus-l0 loads without "
                                   "running code. Unpickling the old file runs any code it "
                                   "carries: only for files you trust (--trust-pickle).")
    p.add_argument("action", choices=["upgrade"], help="upgrade: convert FILE")
    p.add_argument("file", type=Path, metavar="FILE", help="the checkpoint (ckpt_NNNNNNN.pt)")
    p.add_argument("--trust-pickle", action="store_true",
                   help="unpickle FILE in full, which runs any code it carries (only for a "
                        "file whose source you trust)")
    p.add_argument("--out", type=Path, default=None, metavar="FILE",
                   help="write the converted checkpoint here (default: over FILE)")
    return p


def run(args: argparse.Namespace) -> int:
    from neus_l0.commands._paths import check_output_file
    from neus_l0.run.checkpoints import upgrade_checkpoint

    if args.out is not None:
        check_output_file(args.out, "--out")
    path, converted = upgrade_checkpoint(args.file, args.out, trust_pickle=args.trust_pickle)
    if converted:
        print(f"neus-l0 checkpoint: wrote {path} as plain data (loads without pickle)")
    else:
        print(f"neus-l0 checkpoint: {path} is already plain data; nothing to do")
    return 0

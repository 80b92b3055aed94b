"""`neus-l0 study sampling --out DIR`: the oracle sampling study on analytic SDFs."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(
        name, help="studies of one part of the method outside training (oracle sampling)",
        description="`sampling`: NeuS's up-sampling run exactly on analytic SDFs (sphere, "
                    "grazing planes, pits, rods, fins, the synthetic scenes) with every "
                    "sampler, three budgets and two sharpness regimes; writes sampling.csv, "
                    "summary.md and heat maps into DIR (docs/BENCHMARKS.md reads them).")
    p.add_argument("study", choices=["sampling"], help="which study (sampling)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for CSV, summary, plots")
    p.add_argument("--rays", type=int, default=128, help="rays per shape (default 128)")
    p.add_argument("--quick", action="store_true",
                   help="4 shapes, 16 rays, the 16+16 budget, sharp regime only (seconds)")
    return p


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from neus_l0.atomic import atomic_write_text
    from neus_l0.errors import NeusL0Error
    from neus_l0.study import report
    from neus_l0.study.sampling import BUDGETS, REGIMES, run_study

    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise NeusL0Error(f"{out}: cannot create the output folder ({exc.strerror})") from None
    if args.rays < 1:
        raise NeusL0Error(f"--rays {args.rays}: must be >= 1")
    t0 = time.perf_counter()
    if args.quick:
        rows = run_study(min(args.rays, 16),
                         cases=["sphere", "plane 80deg", "pit r0.05 d0.2", "rod r0.02"],
                         budgets=BUDGETS[:1], regimes={"sharp": REGIMES["sharp"]})
    else:
        rows = run_study(args.rays)
    report.write_csv(out / "sampling.csv", rows)
    text = "\n".join(report.summary(rows, m) for m in (report.HEADLINE, "within_0.003"))
    atomic_write_text(out / "summary.md", text)
    report.plot(out / "within_0.01.png", rows)
    report.plot(out / "depth_err.png", rows, "depth_err")
    print(text)
    print(f"wrote {out}/sampling.csv, summary.md, within_0.01.png, depth_err.png "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0

"""Issue #35's before and after, side by side: the setting #35 found against today's, per
feature of the pits-and-rods scenes, paired run by run.

Usage:
    python tools/pits_before_after.py --out DIR [--scenes cup,well] [--seeds 0,1,2]
        [--seconds 300] [--device cpu|cuda] [--parallel 2] [--dry-run | --table-only]

The two arms (the same scene, seed and budget, started together so that they share the
machine alike):

- ``ISSUE``: as #35 found it: no photometric term, NeuS's colour composite over black
  (``train.photo.weight=0 train.hit_color_floor=0``), the raw marching-cubes mesh;
- ``NOW``: the photometric term and the hit colour at `demo`'s values, and the demo's mesh
  steps (``--close-underside --drop-outside-masks --fill-missed``).

Each arm is a ``neus-l0 bench --plan`` sweep of one run (sampler l0, meshes at 256, one
thread a run on a CPU) in ``DIR/ISSUE_SCENE_SEED`` and ``DIR/NOW_SCENE_SEED``; re-running
resumes, as `bench` skips a run its status records as done. The bench's config is `demo` on
a CPU (so NOW is the demo as it ships) and `fast` on CUDA (which has neither term: NOW adds
them). A scene that is not a folder is synthesised first: ``neus-l0 synth NAME
DIR/scenes/NAME-49 --views 49 --width 400 --height 300``. Then ``DIR/table.md``:
`pair_features.py`'s tables of the overall error and of the completeness (a floor that one
arm lost has no accuracy); ``--table-only`` writes it from the runs already there (a
campaign stopped part-way).

On a GPU, one command a seed (a pair of 120 s runs started together, with compiling, meshing
and scoring about 5 minutes, not yet measured; the second call resumes the first's folder):
    python tools/pits_before_after.py --device cuda --scenes cup --seeds 0 --seconds 120
        --out /tmp/pba
    (then --seeds 1, and --seeds 0,1 --table-only for the paired table)
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from pair_features import markdown_table, paired_rows

from neus_l0.atomic import atomic_write_text
from neus_l0.config.load import load_config

#: The bench flags both arms share (the per-feature errors need meshes at 256).
COMMON = ("--plan", "--samplers", "l0", "--resolution", "256", "--eval-density", "0.5")
#: The mesh steps of `demo` (NOW only).
MESH_STEPS = ("--close-underside", "--drop-outside-masks", "--fill-missed")


def arm_overrides(arm: str) -> list[str]:
    """The config overrides of `arm` (``ISSUE`` or ``NOW``); NOW's are `demo`'s values."""
    if arm == "ISSUE":
        return ["train.photo.weight=0", "train.hit_color_floor=0"]
    train = load_config("demo").train
    p = train.photo
    return [f"train.photo.weight={p.weight}", f"train.photo.patch={p.patch}",
            f"train.photo.sources={p.sources}", f"train.photo.best={p.best}",
            f"train.hit_color_floor={train.hit_color_floor}"]


def bench_command(arm: str, scene: Path, seed: int, seconds: float, device: str,
                  out: Path) -> list[str]:
    """The ``neus-l0 bench`` command line of one arm's run."""
    cmd = [sys.executable, "-m", "neus_l0", "bench", *COMMON, "--scenes", str(scene),
           "--seeds", str(seed), "--seconds", f"{seconds:g}", "--device", device,
           "--out", str(out)]
    if device == "cpu":
        cmd += ["--threads", "1"]
    if arm == "NOW":
        cmd += list(MESH_STEPS)
    return cmd + arm_overrides(arm)


def scene_folder(name: str, root: Path) -> tuple[Path, list[str] | None]:
    """(the scene's folder, the command that synthesises it, or None if it exists)."""
    if Path(name).is_dir():
        return Path(name), None
    folder = root / "scenes" / f"{name}-49"
    if folder.is_dir():
        return folder, None
    return folder, [sys.executable, "-m", "neus_l0", "synth", name, str(folder), "--views",
                    "49", "--width", "400", "--height", "300"]


def plan(args: argparse.Namespace) -> tuple[list[list[str]], list[list[list[str]]]]:
    """(synthesis commands, the pairs of bench commands: ISSUE then NOW per scene and seed)."""
    synths, pairs = [], []
    for name in args.scenes:
        folder, synth = scene_folder(name, args.out)
        if synth:
            synths.append(synth)
        pairs += [[bench_command(arm, folder, seed, args.seconds, args.device,
                                 args.out / f"{arm}_{Path(name).name}_{seed}")
                   for arm in ("ISSUE", "NOW")] for seed in args.seeds]
    return synths, pairs


def run_together(commands: list[list[str]], log_dir: Path) -> None:
    """Start `commands` at once and wait for them all; each appends to its log
    (``DIR/log_ARM_SCENE_SEED.txt``: an earlier attempt's stays), a failure names it."""
    procs = []
    for cmd in commands:
        log = log_dir / f"log_{Path(cmd[cmd.index('--out') + 1]).name}.txt"
        with log.open("a") as f:  # the child holds its own descriptor
            procs.append((subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT), log))
    failed = [str(log) for p, log in procs if p.wait() != 0]
    if failed:
        raise SystemExit(f"pits_before_after: a bench run failed; see {', '.join(failed)}")


def table(out: Path, scenes: list[str], seeds: list[int]) -> str:
    """The paired tables (overall, then completeness) of the finished arms."""
    names = [f"{Path(s).name}_{k}" for s in scenes for k in seeds]
    off = [out / f"ISSUE_{n}" for n in names]
    on = [out / f"NOW_{n}" for n in names]
    lines = []
    for metric in ("overall", "completeness"):
        rows = paired_rows(off, on, metric, "eval.json")
        lines += [f"## {metric}", "", *markdown_table(rows, "ISSUE", "NOW"), ""]
    return "\n".join(lines)


def _seeds(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: seeds are integers, comma-separated") from None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="the campaign's folder")
    ap.add_argument("--scenes", type=lambda s: s.split(","), default=["cup", "well"],
                    help="synthetic scene names or scene folders, comma-separated")
    ap.add_argument("--seeds", type=_seeds, default=[0, 1, 2], help="e.g. 0,1,2")
    ap.add_argument("--seconds", type=float, default=300.0, help="each run's budget")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--parallel", type=int, default=2,
                    help="runs at a time (a pair starts together; default 2)")
    what = ap.add_mutually_exclusive_group()
    what.add_argument("--dry-run", action="store_true", help="print the commands, run none")
    what.add_argument("--table-only", action="store_true",
                      help="only write DIR/table.md, from the runs already finished")
    args = ap.parse_args()
    if args.out.exists() and not args.out.is_dir():
        raise SystemExit(f"pits_before_after: --out {args.out}: is a file, not a folder")
    synths, pairs = plan(args)
    if args.table_only:
        pairs, synths = [], []
    elif args.dry_run:
        for cmd in synths + [c for pair in pairs for c in pair]:
            print(" ".join(cmd))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    for cmd in synths:
        if subprocess.run(cmd).returncode != 0:
            raise SystemExit(f"pits_before_after: could not synthesise {cmd[4]!r} into "
                             f"{cmd[5]} (a built-in scene name or a scene folder)")
    per_batch = max(1, args.parallel // 2)  # pairs started together
    for i in range(0, len(pairs), per_batch):
        run_together([c for pair in pairs[i:i + per_batch] for c in pair], args.out)
    text = table(args.out, args.scenes, args.seeds)
    atomic_write_text(args.out / "table.md", text)
    print(text)


if __name__ == "__main__":
    main()

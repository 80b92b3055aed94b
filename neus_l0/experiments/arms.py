"""Arms of a side-by-side benchmark: Chamfer against training time, verdict, table, figure.

An *arm* is one setting (config + sampler + budget) trained on a scene by
`neus_l0.experiments.runner` with snapshots (`RunSpec.snapshots`); its ``eval.json`` holds
``curve``: ``{seconds, iteration, accuracy, completeness, overall, mesh_s}`` per snapshot,
the final model last. `tools/bench_fast_vs_neus.py` runs two arms per scene (``fast`` and
``neus``) and uses this module for everything after the runs:

* `read_arm`: an arm's results row, curve and timings from its run folder;
* `verdict`: does the fast arm reach the NeuS arm's final Chamfer, when, and is it still
  improving at its end;
* `summary_table`: the Markdown table and verdict lines;
* `plot_curves`: Chamfer overall against training seconds, a panel per scene;
* `machine_info`: where the benchmark ran.
"""

from __future__ import annotations

import datetime
import json
import math
import platform
from pathlib import Path

from neus_l0.atomic import atomic_path

#: Line colours of the arms (others cycle through matplotlib's defaults).
COLORS = {"neus": "tab:blue", "fast": "tab:red"}


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def scored(curve: list[dict]) -> list[dict]:
    """The points of `curve` that have a finite ``overall`` Chamfer, by training time."""
    pts = [p for p in curve if _finite(p.get("overall")) and _finite(p.get("seconds"))]
    return sorted(pts, key=lambda p: (p["seconds"], p.get("iteration", 0)))


def read_arm(run_dir: str | Path) -> dict:
    """An arm's outcome from its run folder.

    Returns:
        ``{"status", "row", "curve", "timings", "label"}``: status ``done`` / ``failed`` /
        ``missing``; ``row`` the results row of status.json (None when missing); ``curve``
        and ``timings`` from eval.json (empty when it is missing).
    """
    run_dir = Path(run_dir)
    out = {"status": "missing", "row": None, "curve": [], "timings": {}, "label": None}
    try:
        status = json.loads((run_dir / "status.json").read_text(encoding="utf-8"))
        out["status"], out["row"] = status["status"], status["row"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError):
        return out
    try:
        ev = json.loads((run_dir / "eval.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return out
    out["curve"] = list(ev.get("curve") or [])
    out["timings"] = dict(ev.get("timings") or {})
    out["label"] = ev.get("label")
    return out


def verdict(neus_curve: list[dict], fast_curve: list[dict]) -> dict:
    """Compare the fast arm's Chamfer curve with the NeuS arm's final Chamfer.

    Args:
        neus_curve, fast_curve: curve points (``seconds``, ``iteration``, ``overall``, ...);
            points without a finite ``overall`` are ignored.

    Returns:
        ``neus_final`` / ``neus_seconds``: the NeuS arm's last Chamfer and its training time;
        ``fast_final`` / ``fast_seconds``: the same for the fast arm (at its budget);
        ``reached_s`` / ``reached_iteration``: the earliest fast point with Chamfer <=
        ``neus_final`` (None: never); ``fast_matches``: ``fast_final <= neus_final``;
        ``still_improving``: the fast arm's last point is below the one before (None with
        fewer than two points); ``last_two``: those two Chamfers; ``target_met``:
        ``fast_matches and still_improving``. Everything None when an arm has no scored
        point.
    """
    n, f = scored(neus_curve), scored(fast_curve)
    out = dict.fromkeys(("neus_final", "neus_seconds", "fast_final", "fast_seconds",
                         "reached_s", "reached_iteration", "fast_matches", "still_improving",
                         "last_two", "target_met"))
    if not n or not f:
        return out
    neus_final = n[-1]["overall"]
    out.update(neus_final=neus_final, neus_seconds=n[-1]["seconds"],
               fast_final=f[-1]["overall"], fast_seconds=f[-1]["seconds"])
    reached = next((p for p in f if p["overall"] <= neus_final), None)
    if reached is not None:
        out.update(reached_s=reached["seconds"], reached_iteration=reached.get("iteration"))
    out["fast_matches"] = f[-1]["overall"] <= neus_final
    if len(f) >= 2:
        out["last_two"] = [f[-2]["overall"], f[-1]["overall"]]
        out["still_improving"] = f[-1]["overall"] < f[-2]["overall"]
        out["target_met"] = out["fast_matches"] and out["still_improving"]
    return out


def _num(x, digits: int = 3) -> str:
    if not _finite(x):
        return "–"
    return f"{x:.{digits}g}" if abs(x) < 10 ** digits else f"{x:.0f}"


def verdict_line(scene: str, v: dict, budgets: dict[str, float]) -> str:
    """One sentence per scene: the numbers of `verdict` in words."""
    if v.get("neus_final") is None:
        return f"- **{scene}**: no verdict (an arm failed or has no Chamfer score)."
    fb, nb = budgets.get("fast"), budgets.get("neus")
    reach = (f"first <= it at {_num(v['reached_s'])} s (iteration {v['reached_iteration']})"
             if v["reached_s"] is not None else "never <= it within its budget")
    if v["still_improving"] is None:
        trend = "too few points to tell whether it is still improving"
    else:
        a, b = v["last_two"]
        trend = (f"still improving ({_num(a)} -> {_num(b)})" if v["still_improving"]
                 else f"not improving at the end ({_num(a)} -> {_num(b)})")
    met = {True: "yes", False: "NO", None: "undecided"}
    return (f"- **{scene}**: NeuS arm ({_num(nb)} s budget) final Chamfer "
            f"{_num(v['neus_final'])} at {_num(v['neus_seconds'])} s; fast arm "
            f"({_num(fb)} s budget) {_num(v['fast_final'])} at {_num(v['fast_seconds'])} s, "
            f"{reach}; {trend}. Fast arm at or below NeuS's final Chamfer and still "
            f"improving: {met[v['target_met']]}.")


#: Columns of the summary table: (key in an arm's summary, header, significant digits).
TABLE_COLUMNS = (("conf", "conf", 0), ("sampler", "sampler", 0), ("budget_s", "budget (s)", 4),
                 ("train_seconds", "trained (s)", 4), ("iterations", "iterations", 6),
                 ("its_per_s", "it/s", 3), ("peak_mem_mb", "peak mem (MB)", 4),
                 ("extract_s", "mesh extraction (s)", 3), ("accuracy", "accuracy", 3),
                 ("completeness", "completeness", 3), ("overall", "Chamfer overall", 3),
                 ("status", "status", 0))


def arm_summary(arm: dict, conf: str, sampler: str, budget_s: float) -> dict:
    """The table's numbers for one arm (`read_arm`'s dict) and its curve."""
    row = arm["row"] or {}
    timings = arm["timings"]
    return {
        "conf": conf, "sampler": sampler, "budget_s": budget_s, "status": arm["status"],
        "error": row.get("error"), "train_seconds": row.get("train_seconds"),
        "iterations": row.get("iterations"), "its_per_s": row.get("its_per_s"),
        "peak_mem_mb": row.get("peak_mem_mb"),
        "extract_s": timings.get("extract_s", row.get("mesh_seconds")),
        "accuracy": row.get("accuracy"), "completeness": row.get("completeness"),
        "overall": row.get("overall"), "psnr_heldout": row.get("psnr_heldout"),
        "curve": arm["curve"],
    }


def summary_table(scenes: dict[str, dict]) -> str:
    """Markdown: a row per (scene, arm), each arm's curve, then the verdict per scene.

    Args:
        scenes: ``{scene: {"arms": {arm: arm_summary(...)}, "verdict": verdict(...)}}``.
    """
    heads = [h for _, h, _ in TABLE_COLUMNS]
    lines = ["| scene | arm | " + " | ".join(heads) + " |",
             "|---|---|" + "---|" * len(heads)]
    for scene, s in scenes.items():
        for name, a in s["arms"].items():
            cells = [str(a.get(k) or "–") if d == 0 else _num(a.get(k), d)
                     for k, _, d in TABLE_COLUMNS]
            lines.append(f"| {scene} | {name} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    text += ("\nTimes are training-loop seconds (setup, snapshot writing and probes excluded); "
             "peak memory is the GPU's max allocated on CUDA, the process's peak RSS on the "
             "CPU; mesh extraction is the final mesh's marching cubes; Chamfer distances in "
             "world units.\n\nChamfer overall over time (seconds: value):\n\n")
    for scene, s in scenes.items():
        for name, a in s["arms"].items():
            pts = ", ".join(f"{_num(p.get('seconds'))}: {_num(p.get('overall'))}"
                            for p in a["curve"]) or "–"
            text += f"- {scene}, {name}: {pts}\n"
    text += "\nVerdict (the fast arm against the NeuS arm's final Chamfer):\n\n"
    budgets = {}
    for scene, s in scenes.items():
        budgets = {name: a.get("budget_s") for name, a in s["arms"].items()}
        text += verdict_line(scene, s.get("verdict") or {}, budgets) + "\n"
    failed = [(scene, name, a) for scene, s in scenes.items() for name, a in s["arms"].items()
              if a["status"] != "done"]
    if failed:
        text += "\nFailed runs:\n\n"
        text += "".join(f"- {scene}, {name}: {a['status']}: {a.get('error') or ''}\n"
                        for scene, name, a in failed)
    return text


def plot_curves(scenes: dict[str, dict], path: str | Path) -> Path:
    """Chamfer overall against training seconds, a panel per scene and a line per arm.

    Args:
        scenes: as for `summary_table`.
        path: the PNG to write (atomically).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(scenes) or ["(no scenes)"]
    fig, axes = plt.subplots(1, len(names), figsize=(5.0 * len(names), 3.8), squeeze=False)
    for ax, scene in zip(axes[0], names):
        arms = scenes.get(scene, {}).get("arms", {})
        for i, (name, a) in enumerate(arms.items()):
            pts = scored(a["curve"])
            if not pts:
                continue
            color = COLORS.get(name, f"C{i % 10}")
            ax.plot([p["seconds"] for p in pts], [p["overall"] for p in pts], "o-",
                    color=color, label=f"{name}: {a['conf']}, {a['sampler']}")
            if name == "neus":
                ax.axhline(pts[-1]["overall"], color=color, ls="--", lw=0.8, alpha=0.7)
        ax.set_title(scene)
        ax.set_xlabel("training seconds")
        ax.set_ylabel("Chamfer overall (world units)")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info(device: str) -> dict:
    """Platform, CPU, GPU (when `device` is cuda), torch version, core count and the date."""
    import os

    import torch

    gpu = None
    if device == "cuda" and torch.cuda.is_available():
        gpu = torch.cuda.get_device_name(0)
    return {
        "platform": platform.platform(), "python": platform.python_version(),
        "cpu": _cpu_name(), "cpu_count": os.cpu_count(), "gpu": gpu,
        "torch": torch.__version__, "cuda": torch.version.cuda if gpu else None,
        "device": device,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def machine_line(m: dict) -> str:
    """`machine_info` in one line."""
    where = m["gpu"] or f"{m['cpu']} ({m['cpu_count']} cores)"
    return (f"machine: {where}; {m['platform']}; torch {m['torch']}"
            + (f" (CUDA {m['cuda']})" if m.get("cuda") else "") + f"; {m['date']}")

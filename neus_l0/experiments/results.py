"""The results table of a sweep: its columns, rows, and the files that hold them.

One row per run (see docs/benchmarks/sweeps.md): ``DIR/results.csv`` (header row,
then one line per run; empty cells for missing numbers) and ``DIR/results.json`` (a JSON list
of the same rows, missing numbers as null). Paths (``run_dir``, ``mesh``) are relative to DIR.
Both files are rewritten atomically after every finished run, from the ``status.json`` files
of every run folder under ``DIR/runs/``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from neus_l0.atomic import atomic_write_json, atomic_write_text

#: Columns of results.csv, in order (``mesh_seconds``: the final mesh's marching cubes
#: alone, without loading the model; ``pits`` and ``thin``: the Chamfer distance over the
#: scene's pit and thin features, ``features.json``, None on a scene without them; each
#: missing in sweeps made before it existed).
COLUMNS = ("scene", "sampler", "budget_s", "seed", "status", "error", "train_seconds",
           "iterations", "its_per_s", "accuracy", "completeness", "overall", "psnr_heldout",
           "peak_mem_mb", "sample_dist_final", "run_dir", "mesh", "mesh_seconds", "pits",
           "thin")
#: Columns holding numbers (None when missing).
NUMERIC = ("budget_s", "seed", "train_seconds", "iterations", "its_per_s", "accuracy",
           "completeness", "overall", "psnr_heldout", "peak_mem_mb", "sample_dist_final",
           "mesh_seconds", "pits", "thin")
#: Columns that do not depend on timing: equal between two sweeps that reach `train.iters`.
DETERMINISTIC = ("scene", "sampler", "budget_s", "seed", "status", "iterations", "accuracy",
                 "completeness", "overall", "psnr_heldout", "sample_dist_final", "pits",
                 "thin")


def run_name(scene: str, sampler: str, budget_s: float, seed: int) -> str:
    """The run folder name ``<scene>__<sampler>__<budget>s__seed<seed>``."""
    return f"{scene}__{sampler}__{budget_s:g}s__seed{seed}"


def clean_number(x) -> float | int | None:
    """`x` as a JSON-safe number: None for missing, NaN or infinite values."""
    if x is None or isinstance(x, bool):
        return None
    if isinstance(x, int):
        return x
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def make_row(**values) -> dict:
    """A row with every column (missing ones None, numbers cleaned, the error one line)."""
    row = {c: values.get(c) for c in COLUMNS}
    for c in NUMERIC:
        row[c] = clean_number(row[c])
    if row["error"]:
        row["error"] = " ".join(str(row["error"]).split())[:500]
    return row


def sort_key(row: dict) -> tuple:
    return (str(row["scene"]), str(row["sampler"]), row["budget_s"] or 0.0, row["seed"] or 0)


def collect_rows(out_dir: str | Path) -> list[dict]:
    """Rows of every run folder under ``out_dir/runs`` that has a status.json, sorted."""
    rows = []
    for status in sorted(Path(out_dir, "runs").glob("*/status.json")):
        try:
            data = json.loads(status.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(data, dict) and isinstance(data.get("row"), dict):
            rows.append(make_row(**data["row"]))
    return sorted(rows, key=sort_key)


def to_csv(rows: list[dict]) -> str:
    """The CSV text of `rows` (header first; None as an empty cell)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: ("" if r.get(c) is None else r[c]) for c in COLUMNS})
    return buf.getvalue()


def write_results(out_dir: str | Path, rows: list[dict]) -> None:
    """Write results.csv and results.json atomically."""
    out_dir = Path(out_dir)
    atomic_write_text(out_dir / "results.csv", to_csv(rows))
    atomic_write_json(out_dir / "results.json", rows)


def read_results(out_dir: str | Path) -> list[dict]:
    """The rows of ``out_dir/results.json`` (or of results.csv when the JSON is missing)."""
    out_dir = Path(out_dir)
    js = out_dir / "results.json"
    if js.is_file():
        return [make_row(**r) for r in json.loads(js.read_text(encoding="utf-8"))]
    rows = []
    with open(out_dir / "results.csv", newline="", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            rows.append(make_row(**{k: (v if v != "" else None) for k, v in r.items()}))
    for r in rows:
        for c in ("iterations", "seed"):
            if r[c] is not None:
                r[c] = int(r[c])
    return rows

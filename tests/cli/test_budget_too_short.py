"""A budget too short to train is refused in one line naming the budget as typed, and the
run folder the command would have made is not left behind."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_a_budget_that_start_up_already_spent(refused, tiny_scene, tmp_path):
    """In-process, the interpreter has run for longer than 1 s: nothing is left to train."""
    line = refused(["train", str(tiny_scene), "--out", str(tmp_path / "r"), "--budget", "1s",
                    "--quiet", "--threads", "1"], "--budget 1s", "too short")
    assert "start-up alone took" in line
    assert not (tmp_path / "r").exists()


def test_a_budget_too_short_after_the_measured_steps(tiny_scene, tmp_path, error_line):
    """A fresh process: the plan, made after the first steps, finds no room for the fewest
    iterations; the line names the typed budget and the least that would train."""
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-m", "neus_l0", "train", str(tiny_scene), "--out",
                          str(run), "--budget", "0.12m", "--threads", "1", "--quiet",
                          "train.compile=false", "train.save_every=1"],
                         capture_output=True, text=True, env=env, cwd=ROOT)
    assert out.returncode == 2, out.stderr
    line = error_line(out.stderr, "train", "--budget 0.12m", "too short", "give at least")
    assert "train.budget=" not in line
    assert not run.exists()

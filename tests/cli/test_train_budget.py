"""`neus-l0 train --budget`: bad budgets get one line; a budget run on the tiny scene ends
within its budget, end to end, with its schedule finished."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from neus_l0.cli import main
from neus_l0.config.load import load_config
from neus_l0.train.schedule import lr_factor

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("bad", ["0", "-5", "abc", "1e9"])
def test_bad_budgets_get_one_clear_line(bad, tiny_scene, tmp_path, capsys):
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "r"), f"--budget={bad}",
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--budget" in err[0], err
    assert not (tmp_path / "r" / "checkpoints").exists()


def test_a_budget_with_resume_is_refused(tiny_scene, tmp_path, capsys):
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "r"), "--budget", "1m",
                 "--resume", "--quiet"]) == 2
    assert "resume without --budget" in capsys.readouterr().err


def test_a_budget_run_ends_within_its_budget(tiny_scene, tmp_path):
    # 40 s: start-up (~5-8 s) plus a plan of a few hundred steps of the default config; the
    # test times the whole process, so what is left after start-up is what the plan fills
    budget = 40.0
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "neus_l0", "train", str(tiny_scene),
                          "--out", str(run), "--budget", f"{budget:g}s", "--threads", "1",
                          "--quiet"], capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.monotonic() - t0
    assert out.returncode == 0, out.stderr
    assert wall <= budget, (wall, out.stderr)
    assert "buys" in out.stderr and "end to end" in out.stdout
    recorded = load_config(run / "config.yaml")
    plan = json.loads((run / "budget.json").read_text())
    assert recorded.train.budget == 0 and recorded.train.iters == plan["planned_iters"]
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    # the training lines (validation and snapshot lines share the file and may come last)
    last = [m for m in lines if "lr" in m][-1]
    # the schedule reached its (possibly compressed) end: the final learning rate of the
    # config's curve when the plan is at least the config's length, else the curve's value
    # where the shorter plan stops (`planned_config`)
    assert last["iter"] == plan["done_iters"]
    t = recorded.train
    want = t.lr * lr_factor(t.iters, t.warm_up, t.lr_decay_iters or t.iters, t.lr_alpha)
    assert last["lr"] == pytest.approx(want, rel=0.05)
    if t.lr_decay_iters <= t.iters:
        assert want == pytest.approx(t.lr * t.lr_alpha)

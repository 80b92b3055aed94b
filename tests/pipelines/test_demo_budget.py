"""`neus-l0 demo --budget`: the training stage is a planned budget run, recorded so that a
re-run reuses it instead of planning again."""

import json

import pytest

from neus_l0.cli import main
from neus_l0.config.load import load_config


def test_the_demo_trains_a_planned_budget_and_a_rerun_reuses_it(small, tiny_demo, tmp_path,
                                                                 capsys):

    out = tmp_path / "demo"
    argv = ["demo", "--out", str(out), "--quiet", "--resolution", "40", "--budget", "20s",
            "--threads", "1",
            *[o for o in small[:-3] if not o.startswith("model.sdf.encoding")],
            "train.val_every=0", "train.compile=false"]
    assert main(argv) == 0
    plan = json.loads((out / "run" / "budget.json").read_text())
    recorded = load_config(out / "run" / "config.yaml")
    metrics = json.loads((out / "metrics.json").read_text())
    assert recorded.train.budget == 0 and recorded.train.iters == plan["planned_iters"]
    assert metrics["iterations"] == plan["done_iters"] > 20
    assert plan["steps_end_s"] <= 20.0
    assert "planned for a 20 s budget" in capsys.readouterr().out
    assert main(argv) == 0  # the finished plan is reused, not re-planned
    again = json.loads((out / "metrics.json").read_text())
    assert again["iterations"] == metrics["iterations"]
    # the demo closes the unseen underside by default; --no-close-underside meshes as is
    assert metrics["mesh"]["close_underside"] is True
    assert "underside_plane" in metrics["mesh"]
    assert isinstance(metrics["mesh"]["dropped_outside_masks"], list)
    assert metrics["mesh"]["filled_missed"]["grid"] == metrics["mesh"]["resolution"]
    assert main([*argv, "--no-close-underside", "--no-drop-outside-masks",
                 "--no-fill-missed"]) == 0
    plain = json.loads((out / "metrics.json").read_text())["mesh"]
    assert plain["close_underside"] is False and plain["underside_plane"] is None
    assert plain["dropped_outside_masks"] is None and plain["filled_missed"] is None
    capsys.readouterr()
    # the recorded plan does not let another sampler through under the run's label
    assert main([*argv, "sampler=hvs"]) == 2
    assert "sampler" in capsys.readouterr().err


@pytest.mark.parametrize("bad", ["0", "-5", "abc", "1e9"])
def test_bad_demo_budgets_get_one_line(bad, refused, tmp_path):
    refused(["demo", "--out", str(tmp_path / "d"), f"--budget={bad}"], "--budget", alone=True)
    assert not (tmp_path / "d").exists()


def test_the_default_demo_fits_its_time_compressing_a_schedule_that_does_not(
        small, tiny_demo, tmp_path, monkeypatch, capsys):
    """Without --budget the demo plans at most the config's iterations within what is left
    of `DEMO_BUDGET_S` since the process started, less `DEMO_RESERVE_S`: 100000 iterations
    do not fit a 14 s training stage and are compressed to it, schedule finished."""
    from neus_l0.pipelines import demo

    monkeypatch.setattr("neus_l0.train.run_config.process_seconds", lambda: 0.0)
    monkeypatch.setattr(demo, "DEMO_BUDGET_S", demo.DEMO_RESERVE_S + 14.0)
    monkeypatch.setattr(demo, "DEMO_MIN_TRAIN_S", 1.0)
    out = tmp_path / "demo"
    argv = ["demo", "--out", str(out), "--quiet", "--resolution", "40", "--threads", "1",
            *[o for o in small[:-3] if not o.startswith("model.sdf.encoding")],
            "train.iters=100000", "train.val_every=0", "train.compile=false"]
    assert main(argv) == 0
    plan = json.loads((out / "run" / "budget.json").read_text())
    recorded = load_config(out / "run" / "config.yaml")
    metrics = json.loads((out / "metrics.json").read_text())
    assert plan["budget_s"] == 14.0 and 20 <= plan["planned_iters"] < 100000
    assert plan["most_iters"] == 100000
    assert recorded.train.iters == plan["planned_iters"] and not recorded.train.budget_up_to_iters
    assert metrics["iterations"] == plan["done_iters"] and plan["steps_end_s"] <= 14.0
    assert "at most 100000 iterations, fitted to 14 s" in capsys.readouterr().out
    assert metrics["timings"]["process_s"] >= 0


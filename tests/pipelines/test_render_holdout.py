"""`render --views test` renders the views the run held out, and never calls a trained view
held-out: a run trained on every view refuses, or (views asked for by flag) labels them
train views."""

from __future__ import annotations

import json

import pytest

from neus_l0.cli import main
from neus_l0.config.load import load_config
from neus_l0.errors import NeusL0Error
from neus_l0.pipelines.render_run import RenderOptions, render_run
from neus_l0.train.loop import train


def _train(scene_dir, overrides, out):
    from neus_l0.formats.open import open_scene

    cfg = load_config("demo", [*overrides, "train.iters=4"])
    train(open_scene(scene_dir, preview=False, log=lambda _line: None), cfg, out,
          progress=False)
    return out


@pytest.fixture(scope="module")
def runs(tiny_scene, small_overrides, tmp_path_factory):
    """Two 4-step runs of the 8-view tiny scene: every view, and --holdout 4 (views 0, 4)."""
    root = tmp_path_factory.mktemp("runs")
    return (_train(tiny_scene, small_overrides, root / "all"),
            _train(tiny_scene, [*small_overrides, "train.holdout=4"], root / "held"))


def test_a_holdout_run_renders_exactly_its_held_out_views(runs, tmp_path):
    res = render_run(runs[1], tmp_path / "t", RenderOptions(views="test", downscale=4,
                                                            video=False), progress=False)
    m = res.metrics
    assert [v["view"] for v in m["per_view"]] == [0, 4]
    assert m["views"] == "test" and m["held_out"] is True and m["trained_on"] == []
    train_views = render_run(runs[1], tmp_path / "tr", RenderOptions(
        views="train", downscale=4, video=False), progress=False).metrics["per_view"]
    assert [v["view"] for v in train_views] == [1, 2, 3, 5, 6, 7]


def test_a_run_trained_on_every_view_refuses_or_says_train_views(runs, tmp_path, capsys):
    code = main(["render", str(runs[0]), "--views", "test", "--out", str(tmp_path / "o"),
                 "--quiet", "--no-video", "--threads", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "trained on every view" in err[0]
    assert "no held-out views" in err[0]
    assert main(["render", str(runs[0]), "--views", "test", "--holdout", "4", "--downscale",
                 "4", "--out", str(tmp_path / "p"), "--quiet", "--no-video",
                 "--threads", "1"]) == 0
    out, err = capsys.readouterr()
    line = json.loads(out.strip().splitlines()[-1])
    assert line["views"] == "train" and line["held_out"] is False
    assert line["trained_on"] == [0, 4] and "views 0, 4 were trained on" in err
    assert "held-out" not in json.dumps(line)


def test_render_test_flags_on_a_holdout_run_keep_the_label_honest(runs, tmp_path):
    m = render_run(runs[1], tmp_path / "x", RenderOptions(
        views="test", test_views=(0, 1), downscale=4, video=False), progress=False).metrics
    assert m["views"] == "train" and m["trained_on"] == [1]
    with pytest.raises(NeusL0Error, match="no held-out views"):
        render_run(runs[0], tmp_path / "y", RenderOptions(views="test"), progress=False)

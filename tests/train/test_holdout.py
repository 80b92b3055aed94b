"""`train --holdout K`: every K-th view is kept out of training and recorded in run.json;
validation renders the held-out views, logs their PSNR and gives each view one TensorBoard
tag with a step per image. Also the small things of `train` / `config` (#36)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from neus_l0.cli import build_parser, main
from neus_l0.config.describe import describe, field_docs
from neus_l0.config.load import conf_names, load_config
from neus_l0.data.split import holdout_split
from neus_l0.train.loop import train


@pytest.fixture(scope="module")
def held_run(sphere_scene, small_overrides, tmp_path_factory):
    """A run of the 6-view sphere trained 8 steps with --holdout 3 (views 0 and 3 out)."""
    scene = sphere_scene(tmp_path_factory.mktemp("scene"))
    cfg = load_config("demo", [*small_overrides, "train.iters=8", "train.val_every=2",
                               "train.val_downscale=2", "train.holdout=3"])
    run = tmp_path_factory.mktemp("held") / "run"
    train(scene, cfg, run, progress=False)
    return run


def test_holdout_split_partitions_the_views(sphere_scene, tmp_path):
    scene = sphere_scene(tmp_path)
    part, held, record = holdout_split(scene, 3)
    assert record == {"holdout": 3, "n_views": 6, "train": [1, 2, 4, 5], "heldout": [0, 3]}
    assert part.image_names == [scene.image_names[i] for i in (1, 2, 4, 5)]
    assert held.image_names == [scene.image_names[i] for i in (0, 3)]
    assert holdout_split(scene, 0)[1] is None


def test_the_run_records_and_validates_only_held_out_views(held_run):
    meta = json.loads((held_run / "run.json").read_text())
    assert meta["views"]["heldout"] == [0, 3] and meta["views"]["train"] == [1, 2, 4, 5]
    names = sorted(p.name for p in (held_run / "validation").glob("*.png"))
    assert names == ["0000002_v003.png", "0000004_v000.png", "0000006_v003.png",
                     "0000008_v000.png"]
    lines = [json.loads(x) for x in (held_run / "metrics.jsonl").read_text().splitlines()]
    val = [m for m in lines if "val_psnr" in m]
    assert [m["iter"] for m in val] == [2, 4, 6, 8]
    assert all(m["val_heldout"] and m["val_view"] in (0, 3) and m["val_psnr"] > 0 for m in val)


def test_tensorboard_has_one_tag_per_view_with_a_step_slider(held_run):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(held_run), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    tags = acc.Tags()
    assert sorted(tags["images"]) == ["validation/v000", "validation/v003"]
    assert [e.step for e in acc.Images("validation/v000")] == [4, 8]
    assert [e.step for e in acc.Scalars("validation/psnr_heldout")] == [2, 4, 6, 8]


def test_train_help_lists_every_conf_and_the_end_line_names_what_exists(
        tiny_scene, small, tmp_path, capsys):
    helptext = build_parser()._subparsers._group_actions[0].choices["train"].format_help()
    flat = " ".join(helptext.split())
    assert f"({', '.join(conf_names())})" in flat and "fast" in conf_names()
    assert main(["train", str(tiny_scene), "--conf", "demo", "--out", str(tmp_path / "r"),
                 "--quiet", "--threads", "1", *small, "train.iters=2",
                 "train.tensorboard=false"]) == 0
    out = capsys.readouterr().out
    assert "metrics.jsonl" in out and "validation/" not in out and "TensorBoard" not in out


def test_config_show_full_keeps_every_word(capsys):
    long = max(field_docs().values(), key=len)
    assert main(["config", "show", "--conf", "demo", "--full"]) == 0
    shown = " ".join(line.strip().lstrip("#").strip() for line in capsys.readouterr().out
                     .splitlines())
    assert " ".join(long.split()) in " ".join(shown.split())
    cut = dict((k, d) for k, _, d in describe(load_config("demo")))
    assert max(len(d) for d in cut.values()) <= 110


def test_the_demo_folder_is_ignored_by_git():
    ignore = (Path(__file__).resolve().parents[2] / ".gitignore").read_text()
    assert "neus-l0-demo/" in ignore.split()

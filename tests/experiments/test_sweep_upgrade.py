"""A sweep folder made before an option existed still takes re-runs that leave the option at
its default, and refuses them when it is set (its runs would not be comparable)."""

import json

import pytest

from neus_l0.config.load import load_config, to_dict
from neus_l0.errors import NeusL0Error
from neus_l0.experiments.sweep import check_settings


def _older(config: dict) -> dict:
    """`config` as a version before `train.error_map.signal` and `model.color.view_warmup`."""
    old = json.loads(json.dumps(config))
    del old["train"]["error_map"]["signal"]
    del old["model"]["color"]["view_warmup"]
    return old


def test_new_options_at_their_defaults_match_an_older_folder(tmp_path):
    now = {"config": to_dict(load_config("demo")), "views": 24}
    (tmp_path / "sweep.json").write_text(json.dumps({**now, "config": _older(now["config"])}))
    check_settings(tmp_path, now)  # no error


def test_a_new_option_set_is_still_a_difference(tmp_path):
    base = to_dict(load_config("demo"))
    (tmp_path / "sweep.json").write_text(json.dumps({"config": _older(base), "views": 24}))
    now = {"config": to_dict(load_config("demo", ["train.error_map.signal=depth"])),
           "views": 24}
    with pytest.raises(NeusL0Error, match="config train.error_map.signal"):
        check_settings(tmp_path, now)
    changed = {"config": to_dict(load_config("demo", ["train.lr=0.01"])), "views": 24}
    with pytest.raises(NeusL0Error, match="config train.lr"):
        check_settings(tmp_path, changed)

"""Options that used to be silently ignored (issue #33 item 11) are refused with one line
naming the option: a skip index beyond the network's layers, ``--change-config`` without
``--resume``, ``render --test-views`` with the orbit."""

from __future__ import annotations

import pytest

from neus_l0.cli import main


@pytest.mark.parametrize("override, named", [
    ("model.sdf.skip=[99]", ("model.sdf.skip", "[99]", "1 .. 8")),
    ("model.sdf.skip=[0]", ("model.sdf.skip", "[0]")),
    ("model.background.skip=[7]", ("model.background.skip", "0 .. 6")),
])
def test_skip_beyond_layers_is_refused(override, named, refused):
    refused(["config", "show", "--conf", "wmask", override], *named)


def test_default_skip_with_fewer_layers_is_accepted(capsys):
    assert main(["config", "show", "--conf", "wmask", "model.sdf.layers=2"]) == 0
    capsys.readouterr()


def test_change_config_without_resume_is_refused(tmp_path, tiny_scene, refused):
    refused(["train", str(tiny_scene), "--out", str(tmp_path / "run"),
                       "--change-config", "--threads", "1"], "--change-config", "--resume")
    assert not (tmp_path / "run").exists()


def test_test_views_with_orbit_is_refused(tmp_path, refused):
    refused(["render", str(tmp_path), "--test-views", "1"], "--test-views",
              "--views test")


def test_a_viewer_port_out_of_range_is_refused_before_any_work(tiny_scene, tmp_path, refused):
    run = tmp_path / "run"
    refused(["train", str(tiny_scene), "--out", str(run), "--viewer", "99999", "--threads",
             "1"], "--viewer 99999", "0..65535")
    assert not run.exists()

"""Options that used to be silently ignored (issue #33 item 11) are refused with one line
naming the option: a skip index beyond the network's layers, ``--change-config`` without
``--resume``, ``render --test-views`` with the orbit."""

from __future__ import annotations

import pytest

from neus_l0.cli import main


def one_error(capsys, argv: list[str], *named: str) -> str:
    """Run the CLI; assert exit 2 and exactly one ``neus-l0 CMD: error:`` line naming every
    `named`, without a traceback."""
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith(f"neus-l0 {argv[0]}: error: ")]
    assert len(lines) == 1, err
    for needle in named:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.mark.parametrize("override, named", [
    ("model.sdf.skip=[99]", ("model.sdf.skip", "[99]", "1 .. 8")),
    ("model.sdf.skip=[0]", ("model.sdf.skip", "[0]")),
    ("model.background.skip=[7]", ("model.background.skip", "0 .. 6")),
])
def test_skip_beyond_layers_is_refused(capsys, override, named):
    one_error(capsys, ["config", "show", "--conf", "wmask", override], *named)


def test_default_skip_with_fewer_layers_is_accepted(capsys):
    assert main(["config", "show", "--conf", "wmask", "model.sdf.layers=2"]) == 0
    capsys.readouterr()


def test_change_config_without_resume_is_refused(capsys, tmp_path, tiny_scene):
    one_error(capsys, ["train", str(tiny_scene), "--out", str(tmp_path / "run"),
                       "--change-config", "--threads", "1"], "--change-config", "--resume")
    assert not (tmp_path / "run").exists()


def test_test_views_with_orbit_is_refused(capsys, tmp_path):
    one_error(capsys, ["render", str(tmp_path), "--test-views", "1"], "--test-views",
              "--views test")

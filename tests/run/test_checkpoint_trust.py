"""Issue #33 items 1 and 14: no code runs from a checkpoint, and a checkpoint's schema is
checked on load.

A planted checkpoint whose pickle would create a file goes through `mesh RUN`, `mesh
--checkpoint F`, `render RUN` and `train --resume`: each exits 2 with one line naming the file
and the upgrade command, and no file appears. An old checkpoint that needs pickle converts
with `neus-l0 checkpoint upgrade F --trust-pickle` only. A checkpoint missing ``rng`` or
``scale_mat``, or with ``iteration: "abc"``, is set aside like a damaged one when an older one
loads, and is one line naming the file when none does.
"""

from __future__ import annotations

import builtins
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from neus_l0.cli import main
from neus_l0.run.checkpoint_schema import schema_problem, to_plain
from neus_l0.run.checkpoints import list_checkpoints, load_checkpoint, load_newest_checkpoint


class _Payload:
    """Unpickles as ``open(marker, "w")``: a file appears if the pickle is ever run."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (builtins.open, (self.marker, "w"))


@pytest.fixture
def run(tiny_trained, tmp_path) -> Path:
    """A copy of `tiny_trained` to plant files in."""
    return Path(shutil.copytree(tiny_trained, tmp_path / "run"))


def _plant(run: Path, extra: dict, iteration: int = 6) -> Path:
    """The newest checkpoint's state with `extra` merged in, saved as a newer checkpoint."""
    state = torch.load(list_checkpoints(run)[-1], weights_only=True)
    state.update(extra)
    path = run / "checkpoints" / f"ckpt_{iteration:07d}.pt"
    torch.save(state, path)
    return path


def test_every_checkpoint_training_writes_is_plain_data(tiny_trained):
    for path in list_checkpoints(tiny_trained):
        state = torch.load(path, weights_only=True)
        assert schema_problem(state) is None
        assert isinstance(state["scene_fingerprint"], str) and state["scene_fingerprint"]


def test_a_planted_pickle_runs_through_no_command(run, tiny_scene, tmp_path, refused):
    marker = tmp_path / "PWNED"
    evil = _plant(run, {"note": _Payload(marker)})
    argvs = [
        ["mesh", str(run), "--resolution", "16", "--out", str(tmp_path / "m.ply")],
        ["mesh", str(run), "--checkpoint", str(evil), "--resolution", "16", "--out",
         str(tmp_path / "m2.ply")],
        ["render", str(run), "--frames", "2", "--quiet", "--threads", "1"],
        ["train", str(tiny_scene), "--out", str(run), "--resume", "--quiet", "--threads", "1",
         "train.iters=8"],
    ]
    for argv in argvs:
        line = refused(argv, str(evil), "not loaded",
                        f"neus-l0 checkpoint upgrade {evil} --trust-pickle")
        assert "runs any code" in line
        assert not marker.exists(), argv
    assert evil.is_file()  # not set aside: it is not damaged, it is refused
    assert not (tmp_path / "m.ply").exists() and not (run / "render").exists()


def test_upgrade_converts_only_when_trusted(run, tmp_path, capsys, refused):
    """An older checkpoint (numpy scale_mat, numpy iteration) is refused with the command;
    the command refuses without --trust-pickle; with it, the file loads safely."""
    old = _plant(run, {"scale_mat": np.eye(4), "iteration": np.int64(6)})
    before = old.read_bytes()
    refused(["mesh", str(run), "--resolution", "16", "--out", str(tmp_path / "m.ply")],
             str(old), "checkpoint upgrade")
    refused(["checkpoint", "upgrade", str(old)], str(old), "--trust-pickle",
             "runs any code")
    assert old.read_bytes() == before
    assert main(["checkpoint", "upgrade", str(old), "--trust-pickle"]) == 0
    assert "as plain data" in capsys.readouterr().out
    state = load_checkpoint(old)
    assert state["scale_mat"] == np.eye(4).tolist() and state["iteration"] == 6
    assert main(["checkpoint", "upgrade", str(old)]) == 0  # already plain: nothing to do
    assert "nothing to do" in capsys.readouterr().out


BROKEN = {
    "no rng": ("rng", None, "missing rng"),
    "no scale_mat": ("scale_mat", None, "missing scale_mat"),
    "iteration abc": ("iteration", "abc", "'iteration' is not a whole number"),
    "rng not tensors": ("rng", {"generator": [1, 2], "torch": [3]}, "'rng' has no uint8"),
    "scale_mat 3x3": ("scale_mat", np.eye(3).tolist(), "'scale_mat' is not a 4x4"),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_a_checkpoint_of_the_wrong_shape_is_set_aside(run, capsys, case):
    key, value, why = BROKEN[case]
    state = torch.load(list_checkpoints(run)[-1], weights_only=True)
    if value is None:
        del state[key]
    else:
        state[key] = value
    bad = run / "checkpoints" / "ckpt_0000006.pt"
    torch.save(state, bad)
    path, _ = load_newest_checkpoint(run)
    assert path.name == "ckpt_0000004.pt"
    err = capsys.readouterr().err
    assert "ckpt_0000006.pt" in err and why in err and len(err.strip().splitlines()) == 1
    assert (run / "checkpoints" / "ckpt_0000006.pt.corrupt").is_file()


@pytest.mark.parametrize("case", ["no rng", "iteration abc"])
def test_a_wrong_shape_checkpoint_given_explicitly_is_one_line(run, tmp_path, case,
                                                                refused):
    key, value, why = BROKEN[case]
    state = torch.load(list_checkpoints(run)[-1], weights_only=True)
    if value is None:
        del state[key]
    else:
        state[key] = value
    bad = tmp_path / "ckpt_0000006.pt"
    torch.save(state, bad)
    refused(["mesh", str(run), "--checkpoint", str(bad), "--resolution", "16",
                      "--out", str(tmp_path / "m.ply")], str(bad), why)


def test_to_plain_turns_numpy_into_plain_values_and_refuses_objects():
    t = torch.zeros(2)
    tree = {"a": np.eye(2), "b": [np.float32(1.5), (np.int64(2), Path("x"))], "t": t}
    plain = to_plain(tree)
    assert plain == {"a": [[1.0, 0.0], [0.0, 1.0]], "b": [1.5, (2, "x")], "t": t}
    assert plain["t"] is t
    same = {"x": [1, 2], "t": t}
    assert to_plain(same) is same
    with pytest.raises(TypeError, match="cannot go into a checkpoint"):
        to_plain({"x": object()})

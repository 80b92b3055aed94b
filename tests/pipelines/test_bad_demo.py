"""`neus-l0 demo`'s bad inputs (issue #27): a signal stops it after the checkpoint, its numbers
and config are checked before any work, a re-run with another sampler is refused.
"""

from __future__ import annotations

import shutil
import signal

import pytest

from neus_l0.cli import main


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_demo_stops_after_the_checkpoint_on_a_signal(tiny_scene, small, tmp_path, sig, one_line,
                                                     cli_process):
    out = tmp_path / "demo"
    shutil.copytree(tiny_scene, out / "scene")  # the demo reuses a scene it finds
    proc = cli_process.start(["demo", "--out", str(out), "--quiet", "--threads", "1", *small,
                   "train.iters=100000", "train.max_seconds=120", "train.compile=false"])
    cli_process.wait_for(lambda: (out / "run" / "metrics.jsonl").is_file(), proc)
    proc.send_signal(sig)
    _, err = cli_process.finish(proc)
    assert proc.returncode == 128 + int(sig)
    line = one_line(err)
    assert f"stopped by {signal.Signals(sig).name}" in line and "checkpoint" in line
    assert list((out / "run" / "checkpoints").glob("ckpt_*.pt"))
    assert not (out / "mesh.ply").exists() and not (out / "metrics.json").exists()


@pytest.mark.parametrize("flags, named", [
    (["--resolution", "0"], "--resolution 0"),
    (["--resolution", "7"], "--resolution 7"),
    (["--threads", "0"], "--threads 0"),
    (["--threads", "-2"], "--threads -2"),
    (["--resolution", "100000"], "--resolution 100000"),
])
def test_demo_checks_its_numbers_before_any_work(tmp_path, flags, named, refused):
    out = tmp_path / "demo"
    refused(["demo", "--out", str(out), *flags], named, alone=True)
    assert not out.exists()


def test_demo_checks_its_config_before_any_work(tmp_path, refused):
    out = tmp_path / "demo"
    refused(["demo", "--out", str(out), "train.iters=0"], "train.iters", alone=True)
    assert not out.exists()


def test_demo_rerun_with_another_sampler_is_refused(scene96, small, train_cli, tmp_path, capsys,
                                                    refused, snapshot):
    """An --out whose run trained with l0, re-run with sampler=hvs: refused naming the key
    (it resumed the l0 run and labelled it hvs); the run is untouched."""
    out = tmp_path / "demo"
    shutil.copytree(scene96, out / "scene")
    assert main(train_cli(out / "scene", out / "run", "train.iters=2")) == 0
    before = snapshot(out / "run" / "checkpoints")
    capsys.readouterr()
    refused(["demo", "--out", str(out), "--quiet", "--threads", "1", "--resolution",
             "24", *small, "train.iters=4", "sampler=hvs"],
            "sampler.name", "another --out")
    assert snapshot(out / "run" / "checkpoints") == before
    assert not (out / "mesh.ply").exists()

"""CPU threads by the machine's state (issue #24 item 3): the free cores when a command
starts, unless asked."""

import os

import pytest

from neus_l0.device import free_cpu_threads, use_cpu_threads


@pytest.mark.parametrize("cores, load, expected", [
    (2, 0.0, 2), (2, 0.4, 2), (2, 0.6, 1), (2, 1.4, 1), (2, 5.0, 1), (16, 3.2, 13), (1, 0.0, 1),
])
def test_free_threads_are_the_cores_less_the_load(monkeypatch, cores, load, expected):
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: set(range(cores)), raising=False)
    monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))
    assert free_cpu_threads() == expected
    assert free_cpu_threads(3) == min(3, cores)  # asked for: as asked, at most the cores


def test_cuda_keeps_torch_default():
    assert use_cpu_threads(None, "cuda") is None


def test_train_says_how_many_threads_it_took(tiny_scene, tmp_path, small, capsys):
    import torch

    from neus_l0.cli import main

    before = torch.get_num_threads()
    try:
        assert main(["train", str(tiny_scene), "--conf", "demo", "--out", str(tmp_path / "r"),
                     "--quiet", "--threads", "1", *small, "train.iters=2"]) == 0
        err = capsys.readouterr().err
        assert "1 torch thread (as asked" in err and torch.get_num_threads() == 1
        assert main(["train", str(tiny_scene), "--out", str(tmp_path / "s"), "--threads",
                     "0"]) == 2
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("command", ["mesh", "render"])
def test_mesh_and_render_take_the_free_cores_or_as_asked(tiny_scene, tmp_path, small,
                                                         monkeypatch, capsys, command):
    import torch

    from neus_l0.cli import main

    before = torch.get_num_threads()
    run = tmp_path / "r"
    try:
        assert main(["train", str(tiny_scene), "--conf", "demo", "--out", str(run), "--quiet",
                     "--threads", "1", *small, "train.iters=2"]) == 0
        extra = (["--resolution", "16", "--out", str(tmp_path / "m.ply")] if command == "mesh"
                 else ["--frames", "1", "--width", "8", "--height", "8", "--no-video",
                       "--out", str(tmp_path / "v")])
        assert main([command, str(run), "--quiet", "--threads", "2", *extra]) == 0
        assert torch.get_num_threads() == 2
        monkeypatch.setattr(os, "getloadavg", lambda: (9.0, 9.0, 9.0))  # a busy machine
        assert main([command, str(run), "--quiet", *extra]) == 0
        assert torch.get_num_threads() == 1
        capsys.readouterr()
        assert main([command, str(run), "--threads", "0", *extra]) == 2
        assert "--threads 0: must be at least 1" in capsys.readouterr().err
    finally:
        torch.set_num_threads(before)

"""`neus-l0 bench`'s bad inputs (issue #27): signals reach its runs (in subprocesses and on
Ray), a failed run fails the bench, a busy --out is refused, numbers are checked first.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import time
from pathlib import Path

import pytest

from neus_l0.cli import main

#: A tiny network and an iteration count no run reaches: only the signal or the budget ends
#: training (eager: a long run would compile under `train.compile: auto`).
TINY = ["model.sdf.hidden=32", "model.sdf.layers=2", "model.sdf.skip=[]",
        "model.sdf.feature_dim=16", "model.sdf.encoding.n_freqs=2", "model.color.hidden=32",
        "model.color.layers=1", "render.n_samples=16", "render.n_importance=16",
        "render.up_sample_steps=2", "train.batch_size=64", "train.warm_up=0",
        "train.iters=100000", "train.log_every=4", "train.compile=false"]


#: The bench's flags that keep a run small.
BENCH_SMALL = ["--resolution", "24", "--eval-density", "3", "--sample-rays", "32",
               "--holdout", "4", "--quiet", "--no-plots"]


def _bench_args(scene: Path, out: Path, samplers: str = "hvs,l0", seconds: str = "60"):
    return ["bench", "--scenes", str(scene), "--samplers", samplers, "--seconds", seconds,
            "--out", str(out), *BENCH_SMALL, *TINY]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_bench_passes_a_signal_to_its_run_and_records_it_interrupted(tiny_scene, tmp_path, sig,
                                                                     refused, one_line,
                                                                     cli_process):
    out = tmp_path / "sweep"
    proc = cli_process.start(_bench_args(tiny_scene, out))
    cli_process.wait_for(lambda: list(out.glob("runs/*/metrics.jsonl")), proc)
    child = json.loads(next(out.glob("runs/*/.lock")).read_text())["pid"]
    if sig == signal.SIGTERM:  # meanwhile a second bench into the same folder is refused
        line = refused(_bench_args(tiny_scene, out), alone=True)
        assert str(out.resolve()) in line and f"PID {proc.pid}" in line
    proc.send_signal(sig)
    out_text, err = cli_process.finish(proc)
    assert proc.returncode == 128 + int(sig)
    assert cli_process.gone(child), "the run's process outlived the bench"
    line = one_line(err)
    assert f"stopped by {signal.Signals(sig).name}" in line and "interrupted" in line
    rows = json.loads((out / "results.json").read_text())
    assert [r["status"] for r in rows] == ["interrupted"]  # the second run never started
    assert f"stopped by {signal.Signals(sig).name} at iteration" in rows[0]["error"]
    run = out / rows[0]["run_dir"]
    assert list((run / "checkpoints").glob("ckpt_*.pt"))  # training checkpointed
    assert not (run / "mesh.ply").exists()
    assert not (out / ".lock").exists()


def test_a_run_stops_when_its_bench_is_killed_outright(tiny_scene, tmp_path, cli_process):
    out = tmp_path / "sweep"
    proc = cli_process.start(_bench_args(tiny_scene, out))
    cli_process.wait_for(lambda: list(out.glob("runs/*/metrics.jsonl")), proc)
    child = json.loads(next(out.glob("runs/*/.lock")).read_text())["pid"]
    proc.kill()  # SIGKILL: nothing can pass a signal on
    cli_process.finish(proc)
    status = next(out.glob("runs/*")) / "status.json"
    deadline = time.monotonic() + 30
    while not cli_process.gone(child) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert cli_process.gone(child), "the run's process trains on without its bench"
    row = json.loads(status.read_text())["row"]
    assert row["status"] == "interrupted" and "stopped by SIGTERM" in row["error"]


class FakeRay:
    """Just enough of Ray for `run_with_ray`: tasks never run; `on_wait` is called at each
    ``ray.wait`` and gives what it returns; cancels are recorded."""

    def __init__(self, on_wait):
        self.on_wait, self.refs, self.cancelled = on_wait, [], []

    def is_initialized(self):
        return True  # the caller's Ray: neither started nor shut down here

    def remote(self, **_options):
        ray = self

        class Task:
            def options(self, **_kw):
                return self

            def remote(self, spec, _timeout):
                ray.refs.append((f"ref{len(ray.refs)}", spec))
                return ray.refs[-1][0]

        return lambda fn: Task()

    def wait(self, refs, num_returns=1, timeout=None):
        assert timeout is not None, "the sweep must not block without looking for signals"
        return self.on_wait(refs)

    def get(self, ref):
        return {"ref": ref}

    def cancel(self, ref, force=False):
        self.cancelled.append((ref, force))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_bench_on_ray_cancels_its_tasks_on_a_signal(tiny_scene, tmp_path, capsys, monkeypatch, sig,
                                                    one_line):
    """--backend ray: a signal force-cancels every task (the run, orphaned, checkpoints and
    stops), records the started run interrupted, exits 143 / 130."""
    def first_run_starts_then_signal(refs):
        if not fake.cancelled and not getattr(fake, "signalled", False):
            spec = fake.refs[0][1]  # what a run's start leaves: spec.json, no status.json
            spec.run_dir.mkdir(parents=True, exist_ok=True)
            (spec.run_dir / "spec.json").write_text("{}")
            fake.signalled = True
            os.kill(os.getpid(), sig)
        return [], list(refs)

    fake = FakeRay(first_run_starts_then_signal)
    monkeypatch.setitem(sys.modules, "ray", fake)
    out = tmp_path / "sweep"
    args = _bench_args(tiny_scene, out)
    assert main([args[0], "--backend", "ray", *args[1:]]) == 128 + int(sig)
    name = signal.Signals(sig).name
    line = one_line(capsys.readouterr().err)
    assert f"stopped by {name}" in line and "1 not started" in line
    assert fake.cancelled == [(ref, True) for ref, _ in fake.refs] and len(fake.refs) == 2
    (row,) = json.loads((out / "results.json").read_text())
    assert row["status"] == "interrupted" and row["error"].startswith(f"stopped by {name}")
    assert row["run_dir"] == f"runs/{fake.refs[0][1].name}" and row["run_dir"] in line
    assert not (out / ".lock").exists()


def test_a_second_ctrl_c_under_ray_still_cancels_the_tasks(monkeypatch):
    """KeyboardInterrupt while waiting (a second Ctrl-C): every task cancelled, then raised."""
    from neus_l0.experiments.ray_backend import run_with_ray

    class Spec:
        device, threads, name = "cpu", 1, "a"

    def interrupted(_refs):
        raise KeyboardInterrupt

    fake = FakeRay(interrupted)
    monkeypatch.setitem(sys.modules, "ray", fake)
    with pytest.raises(KeyboardInterrupt):
        run_with_ray([Spec(), Spec()], lambda row, name: None)
    assert fake.cancelled == [("ref0", True), ("ref1", True)]


def test_ray_rows_come_back_as_tasks_finish():
    """Without a signal, the polling loop hands every task's row on."""
    from neus_l0.experiments.ray_backend import run_with_ray
    from neus_l0.train.signals import StopOnSignal

    class Spec:
        device, threads = "cpu", 1

        def __init__(self, name):
            self.name = name

    waits = []

    def one_by_one(refs):
        waits.append(len(refs))
        return ([refs[0]], refs[1:]) if len(waits) > 1 else ([], list(refs))

    fake = FakeRay(one_by_one)
    seen = []
    with pytest.MonkeyPatch.context() as mp, StopOnSignal() as stop:
        mp.setitem(sys.modules, "ray", fake)
        run_with_ray([Spec("a"), Spec("b")], lambda row, name: seen.append((row, name)),
                     stop=stop)
    assert seen == [({"ref": "ref0"}, "a"), ({"ref": "ref1"}, "b")]
    assert waits == [2, 2, 1] and fake.cancelled == []


def test_bench_exits_non_zero_naming_the_failed_run(tiny_scene, tmp_path, capsys, one_line):
    broken = tmp_path / "broken"
    shutil.copytree(tiny_scene, broken)
    (broken / "cameras_sphere.npz").unlink()  # the run's process fails to open the scene
    out = tmp_path / "sweep"
    assert main(_bench_args(broken, out, samplers="hvs", seconds="5")) == 1
    line = one_line(capsys.readouterr().err)
    assert "1 of 1 runs failed: broken__hvs__5s__seed0" in line
    assert f"its log: {out / 'runs' / 'broken__hvs__5s__seed0' / 'log.txt'}" in line
    assert (out / "runs" / "broken__hvs__5s__seed0" / "log.txt").is_file()
    assert not (out / ".lock").exists()


def test_bench_shows_progress_over_its_runs(tiny_scene, tmp_path, capsys):
    """(bench printed nothing for minutes.) Without --quiet a bar counts the runs."""
    broken = tmp_path / "broken"
    shutil.copytree(tiny_scene, broken)
    (broken / "cameras_sphere.npz").unlink()  # a run that ends at once
    args = [a for a in _bench_args(broken, tmp_path / "sweep", "hvs", "5") if a != "--quiet"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "1/1" in err and "last broken__hvs__5s__seed0: failed" in err


def test_bench_refuses_a_busy_out(tiny_scene, tmp_path, refused):
    from neus_l0.run.lock import RunLock

    out = tmp_path / "sweep"
    with RunLock(out):  # as another bench holds it
        refused(_bench_args(tiny_scene, out),
                f"{out.resolve()}: in use by PID {os.getpid()}", alone=True)
    assert not (out / "runs").exists() and not (out / "sweep.json").exists()


@pytest.mark.parametrize("flags, named", [
    (["--seconds", "0"], "--seconds 0"),
    (["--seconds", "-3"], "--seconds -3"),
    (["--seconds", "inf"], "--seconds inf"),
    (["--seconds", "60,nan"], "--seconds nan"),
    (["--seeds", "-1"], "--seeds -1"),
    (["--resolution", "0"], "--resolution 0"),
    (["--resolution", "100000"], "--resolution 100000"),
    (["--threads", "-1"], "--threads -1"),
    (["--views", "0"], "--views 0"),
    (["--width", "4"], "--width 4"),
    (["--height", "0"], "--height 0"),
    (["--holdout", "1"], "--holdout 1"),
    (["--holdout", "-2"], "--holdout -2"),
    (["--holdout", "4", "--views", "1"], "--holdout 4"),
    (["--eval-density", "0"], "--eval-density 0"),
    (["--eval-density", "inf"], "--eval-density inf"),
    (["--sample-rays", "0"], "--sample-rays 0"),
    (["--psnr-pixels", "0"], "--psnr-pixels 0"),
    (["--timeout", "0"], "--timeout 0"),
    (["--timeout", "nan"], "--timeout nan"),
])
def test_bench_checks_its_numbers_before_any_work(tmp_path, flags, named, refused):
    out = tmp_path / "sweep"
    base = {"--seconds": "60", "--scenes": "demo"}
    for flag in flags[::2]:
        base.pop(flag, None)
    args = ["bench", "--out", str(out), *[x for kv in base.items() for x in kv], *flags]
    refused(args, named, alone=True)
    assert not out.exists()

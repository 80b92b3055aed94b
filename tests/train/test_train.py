"""Training: losses fall with every sampler, resume is exact, checkpoints are safe, CLI."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from neus_l0.config.load import load_config
from neus_l0.config.schema import SAMPLERS
from neus_l0.errors import ConfigError, NeusL0Error
from neus_l0.run.checkpoints import (
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    load_trained_model,
)
from neus_l0.train.loop import train
from neus_l0.train.schedule import cos_anneal_ratio, lr_factor


@pytest.fixture
def scene(sphere_scene, tmp_path):
    return sphere_scene(tmp_path / "scene")


def read_metrics(run):
    return [json.loads(line) for line in (Path(run) / "metrics.jsonl").read_text().splitlines()]


def test_schedules():
    assert lr_factor(0, 10, 100, 0.05) == 0.0
    assert lr_factor(5, 10, 100, 0.05) == 0.5
    assert lr_factor(10, 10, 100, 0.05) == pytest.approx(1.0)
    assert lr_factor(100, 10, 100, 0.05) == pytest.approx(0.05)
    assert lr_factor(55, 10, 100, 0.05) == pytest.approx(0.525)
    assert cos_anneal_ratio(10, 0) == 1.0 and cos_anneal_ratio(25, 50) == 0.5
    assert cos_anneal_ratio(80, 50) == 1.0


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_a_few_steps_lower_the_loss(small, scene, tmp_path, sampler):
    cfg = load_config("demo", small + [f"sampler={sampler}", "train.iters=30"])
    res = train(scene, cfg, tmp_path / "run", progress=False)
    m = read_metrics(tmp_path / "run")
    assert len(m) == 6 and res.iteration == 30
    for row in m:
        assert all(np.isfinite(row[k]) for k in ("loss", "color_loss", "eikonal_loss", "psnr"))
    assert m[-1]["loss"] < 0.8 * m[0]["loss"], [r["loss"] for r in m]
    model, cfg2, info = load_trained_model(tmp_path / "run")
    assert cfg2.sampler.name == sampler and info["iteration"] == 30
    # the logged sharpness is NeuS's inv_s (mean over the last 5 steps), not 1 / inv_s
    assert m[-1]["inv_s"] == pytest.approx(float(model.variance.inv_s().reshape(())), rel=0.05)
    for p in model.parameters():
        assert torch.isfinite(p).all()


def test_run_folder_layout(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=4", "train.val_every=2",
                                       "train.val_downscale=2", "train.save_every=2",
                                       "train.keep_checkpoints=1", "train.log_every=2"])
    run = tmp_path / "run"
    train(scene, cfg, run, progress=False)
    saved = load_config(str(run / "config.yaml"))
    assert saved.train.compile is False  # `auto`, resolved: a 4-step run does not compile
    assert saved == dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, compile=False))
    assert [p.name for p in list_checkpoints(run)] == ["ckpt_0000004.pt"]
    pngs = sorted((run / "validation").glob("*.png"))
    assert len(pngs) == 2
    import cv2

    img = cv2.imread(str(pngs[0]))
    assert img.shape == (8, 30, 3)  # gt | colour | normals of a 2x downscaled 16x20 view
    state = load_checkpoint(latest_checkpoint(run))
    assert {"model", "optimizer", "rng", "config", "iteration", "scale_mat"} <= set(state)
    assert np.allclose(state["scale_mat"], scene.scale_mat)
    with pytest.raises(NeusL0Error, match="--resume"):
        train(scene, cfg, run, progress=False)


def test_resume_equals_uninterrupted(small, scene, tmp_path):
    full = load_config("demo", small + ["train.iters=12"])
    train(scene, full, tmp_path / "a", progress=False)
    part = train(scene, full, tmp_path / "b", progress=False, stop_at=5)
    assert part.stopped_early and part.iteration == 5
    train(scene, full, tmp_path / "b", resume=True, progress=False)
    a = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    b = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    assert a["iteration"] == b["iteration"] == 12
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert torch.equal(a["rng"]["generator"], b["rng"]["generator"])
    ma, mb = read_metrics(tmp_path / "a"), read_metrics(tmp_path / "b")
    assert [r["iter"] for r in ma] == [r["iter"] for r in mb]
    assert ma[-1]["loss"] == mb[-1]["loss"]
    for k in a["optimizer"]["state"]:
        for name, v in a["optimizer"]["state"][k].items():
            assert torch.equal(v, b["optimizer"]["state"][k][name]), (k, name)


def test_interrupted_checkpoint_write_keeps_the_previous_one(small, scene, tmp_path, monkeypatch):
    cfg = load_config("demo", small + ["train.iters=2", "train.save_every=2"])
    run = tmp_path / "run"
    train(scene, cfg, run, progress=False)
    before = latest_checkpoint(run).read_bytes()

    real_save = torch.save

    def failing_save(obj, f, *a, **k):
        real_save(obj, f, *a, **k)  # the temporary file is complete ...
        raise OSError("disk full")  # ... but the write fails before the rename

    monkeypatch.setattr(torch, "save", failing_save)
    cfg4 = load_config("demo", small + ["train.iters=4", "train.save_every=2"])
    with pytest.raises(OSError, match="disk full"):
        train(scene, cfg4, run, resume=True, progress=False)
    monkeypatch.undo()
    assert [p.name for p in list_checkpoints(run)] == ["ckpt_0000002.pt"]
    assert latest_checkpoint(run).read_bytes() == before
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["ckpt_0000002.pt"]
    assert load_checkpoint(latest_checkpoint(run))["iteration"] == 2


def test_nan_checkpoint_is_refused(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=2"])
    run = tmp_path / "run"
    train(scene, cfg, run, progress=False)
    path = latest_checkpoint(run)
    state = torch.load(path, weights_only=True)
    key = next(k for k in state["model"] if state["model"][k].is_floating_point())
    state["model"][key].view(-1)[0] = float("nan")
    torch.save(state, path)
    with pytest.raises(NeusL0Error, match="NaN"):
        train(scene, cfg, run, resume=True, progress=False)
    with pytest.raises(NeusL0Error, match="NaN"):
        load_trained_model(run)


def test_resume_without_checkpoint_and_missing_masks(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=2"])
    with pytest.raises(NeusL0Error, match="nothing to resume"):
        train(scene, cfg, tmp_path / "empty", resume=True, progress=False)
    import dataclasses

    no_masks = dataclasses.replace(scene, has_masks=False)
    with pytest.raises(ConfigError, match="mask"):
        train(no_masks, cfg, tmp_path / "r", progress=False)


def test_max_seconds_stops_and_checkpoints(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=100000", "train.max_seconds=0.5"])
    res = train(scene, cfg, tmp_path / "run", progress=False)
    assert res.stopped_early and 0 < res.iteration < 100000
    assert latest_checkpoint(tmp_path / "run").name == f"ckpt_{res.iteration:07d}.pt"


def test_hooks_join_the_metrics_and_do_not_count_as_training_time(small, scene, tmp_path,
                                                                   monkeypatch):
    import neus_l0.train.state as state_module

    real = state_module.time.monotonic
    fake = {"offset": 0.0}

    class Clock:  # real time plus 100 s for every hook call
        @staticmethod
        def monotonic():
            return real() + fake["offset"]

    monkeypatch.setattr(state_module, "time", Clock)
    calls = []

    def slow_hook(iteration, model, scene_, cfg_):
        calls.append(iteration)
        assert not model.sdf.training and not torch.is_grad_enabled()
        fake["offset"] += 100.0
        return {"probe": float(iteration) * 2}

    cfg = load_config("demo", small + ["train.iters=6", "train.max_seconds=50",
                                       "train.log_every=2"])
    res = train(scene, cfg, tmp_path / "run", progress=False, hooks=[slow_hook])
    rows = read_metrics(tmp_path / "run")
    # Counted as training time, the first hook's 100 s would end the 50 s budget at once.
    assert not res.stopped_early and res.iteration == 6
    assert calls == [r["iter"] for r in rows] == [2, 4, 6]
    assert all(r["probe"] == 2.0 * r["iter"] for r in rows)
    assert res.seconds < 50


def test_background_model_trains(small, sphere_scene, tmp_path):
    import dataclasses

    scene = dataclasses.replace(sphere_scene(tmp_path / "s"), has_masks=False)
    cfg = load_config("womask", small + ["model.background.hidden=32",
                                         "model.background.layers=2",
                                         "model.background.skip=[]",
                                         "render.n_outside=8", "train.iters=4",
                                         "train.log_every=2", "train.warm_up=0"])
    train(scene, cfg, tmp_path / "run", progress=False)
    assert all(np.isfinite(r["loss"]) for r in read_metrics(tmp_path / "run"))


# ------------------------------------------------------------------------------------------
# Command line: train -> mesh on a scene folder, and the demo.


def write_scene_folder(scene, root):
    """Write an in-memory Scene as a NeuS-format folder (image/, mask/, cameras_sphere.npz)."""
    import cv2

    root = Path(root)
    (root / "image").mkdir(parents=True)
    (root / "mask").mkdir()
    cams = {}
    for i in range(scene.n_views):
        rgb = (scene.images[i].numpy() * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(root / "image" / f"{i:03d}.png"), rgb[..., ::-1])
        m = (scene.masks[i].numpy() * 255).astype(np.uint8)
        cv2.imwrite(str(root / "mask" / f"{i:03d}.png"), np.repeat(m[..., None], 3, -1))
        w2c = np.linalg.inv(scene.c2w[i].numpy().astype(np.float64))
        P = np.eye(4)
        P[:3, :4] = scene.intrinsics[i].numpy().astype(np.float64) @ w2c[:3, :4]
        cams[f"world_mat_{i}"] = P @ np.linalg.inv(scene.scale_mat)
        cams[f"scale_mat_{i}"] = scene.scale_mat
    np.savez(root / "cameras_sphere.npz", **cams)
    return root


def test_cli_train_then_mesh(small, scene, tmp_path, capsys):
    import trimesh

    from neus_l0.cli import main

    data = write_scene_folder(scene, tmp_path / "data")
    run = tmp_path / "run"
    args = ["train", str(data), "--conf", "demo", "--out", str(run), "--quiet",
            *small, "train.iters=3"]
    assert main(args) == 0
    assert (run / "metrics.jsonl").is_file() and latest_checkpoint(run) is not None
    # resume with a longer schedule, overrides placed before the options
    assert main(["train", str(data), "train.iters=4", "--out", str(run), "--resume",
                 "--quiet"]) == 0
    assert load_checkpoint(latest_checkpoint(run))["iteration"] == 4
    out = tmp_path / "m.ply"
    assert main(["mesh", str(run), "--resolution", "32", "--out", str(out), "--colors"]) == 0
    mesh = trimesh.load(out, force="mesh")
    # the (nearly initial) SDF is a blob of radius ~0.5-0.75 around the scene centre, in
    # world units: scale 2, centre (1, -2, 0.5) (in the normalised frame it would be 2.3 off)
    r = np.linalg.norm(mesh.vertices - scene.scale_mat[:3, 3], axis=1)
    assert 0.5 < r.mean() < 2.0
    assert "vertices" in capsys.readouterr().out


def test_cli_errors_are_one_line(scene, tmp_path, capsys):
    from neus_l0.cli import main

    data = write_scene_folder(scene, tmp_path / "data")
    assert main(["train", str(data), "--out", str(tmp_path / "r"), "model.sdf.hiden=3"]) == 2
    err = capsys.readouterr().err
    assert "model.sdf.hiden" in err and len(err.strip().splitlines()) == 1
    assert main(["train", str(data), "--conf", "nope", "--out", str(tmp_path / "r")]) == 2
    assert main(["mesh", str(tmp_path / "no-run")]) == 2
    assert "train first" in capsys.readouterr().err


def _tiny_demo(small, tmp_path, iters):
    """The demo on the `tiny_demo` fixture's scene (the calling test requests it)."""
    from neus_l0.cli import main

    out = tmp_path / "demo"
    rc = main(["demo", "--out", str(out), "--quiet", "--resolution", "40",
               *[o for o in small[:-3] if not o.startswith("model.sdf.encoding")],
               f"train.iters={iters}", "train.val_every=0"])
    assert rc == 0
    for p in ("scene/cameras_sphere.npz", "run/config.yaml", "mesh.ply", "metrics.json",
              "comparison.png"):
        assert (out / p).exists(), p
    return json.loads((out / "metrics.json").read_text())


def test_demo_quick(small, tiny_demo, tmp_path):
    m = _tiny_demo(small, tmp_path, 3)
    assert m["iterations"] == 3 and m["mesh"]["faces"] > 0
    # the demo's training is a budget run capped at the config's iterations: a schedule that
    # fits is trained as it is, not stretched to the time
    plan = json.loads((tmp_path / "demo" / "run" / "budget.json").read_text())
    assert plan["planned_iters"] == plan["done_iters"] == plan["most_iters"] == 3


def test_demo_rerun_with_another_sampler_is_refused_not_mislabelled(small, tiny_demo,
                                                                    tmp_path, capsys):
    """Re-running the demo into the same --out resumes its run: with sampler=hvs instead of
    the run's l0 it would train on and label an l0 run hvs (issue #27)."""
    from neus_l0.cli import main

    _tiny_demo(small, tmp_path, 3)
    capsys.readouterr()
    rc = main(["demo", "--out", str(tmp_path / "demo"), "--quiet", "--resolution", "40",
               *[o for o in small[:-3] if not o.startswith("model.sdf.encoding")],
               "train.iters=5", "train.val_every=0", "sampler=hvs"])
    err = capsys.readouterr().err
    assert rc == 2 and "sampler.name" in err and "another --out" in err


@pytest.mark.slow
def test_demo_end_to_end_small(small, tiny_demo, tmp_path):
    m = _tiny_demo(small, tmp_path, 300)
    assert m["chamfer"] is None or np.isfinite(m["chamfer"]["overall"])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_training_on_cuda_matches_resume(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=6"])
    train(scene, cfg, tmp_path / "a", device="cuda", progress=False)
    train(scene, cfg, tmp_path / "b", device="cuda", progress=False, stop_at=3)
    train(scene, cfg, tmp_path / "b", device="cuda", resume=True, progress=False)
    a = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    b = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    for k in a["model"]:
        assert torch.allclose(a["model"][k], b["model"][k], atol=1e-6), k


def test_resume_with_other_network_sizes_is_refused(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=2"])
    train(scene, cfg, tmp_path / "run", progress=False)
    wider = load_config("demo", small + ["train.iters=4", "model.sdf.hidden=40"])
    with pytest.raises(NeusL0Error, match="does not fit"):
        train(scene, wider, tmp_path / "run", resume=True, progress=False)


# ------------------------------------------------------------------------------------------
# Skipping work: occupancy grid, Eikonal subset, mixed precision.

GRID = ["render.occupancy.enabled=true", "render.occupancy.resolution=32",
        "render.occupancy.update_every=4"]


def test_a_few_steps_with_the_grid_lower_the_loss(small, scene, tmp_path):
    # the photometric term off: it counts more rays as they turn opaque, so the total loss
    # does not measure the grid's fit (its own tests: tests/train/test_photometric.py)
    cfg = load_config("demo", small + GRID + ["train.iters=30", "train.eikonal_fraction=0.5",
                                              "train.photo.weight=0"])
    train(scene, cfg, tmp_path / "run", progress=False)
    m = read_metrics(tmp_path / "run")
    for row in m:
        assert all(np.isfinite(row[k]) for k in ("loss", "color_loss", "eikonal_loss", "psnr"))
    assert m[-1]["loss"] < 0.8 * m[0]["loss"], [r["loss"] for r in m]
    state = load_checkpoint(latest_checkpoint(tmp_path / "run"))
    occ = state["occupancy"]["occ"]
    assert occ.shape == (32, 32, 32) and 0 < occ.float().mean() < 1.0
    # the scene's sphere (radius 0.5) is kept: cells on its surface stay occupied
    from neus_l0.bounds.grid import cell_centres

    r = cell_centres(32).norm(dim=-1)
    assert occ[(r - 0.5).abs() < 0.01].all()


def test_resume_with_the_grid_equals_uninterrupted(small, scene, tmp_path):
    full = load_config("demo", small + GRID + ["train.iters=10"])
    train(scene, full, tmp_path / "a", progress=False)
    train(scene, full, tmp_path / "b", progress=False, stop_at=6)
    train(scene, full, tmp_path / "b", resume=True, progress=False)
    a = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    b = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert torch.equal(a["occupancy"]["counter"], b["occupancy"]["counter"])


def test_amp_is_a_no_op_on_the_cpu(small, scene):
    from neus_l0.fields.model import make_model
    from neus_l0.train.step import autocast, make_optimizer, make_scaler, train_step

    cfg = load_config("demo", small)
    amp = load_config("demo", small + ["train.amp=fp16"])
    assert not make_scaler(amp, "cpu").is_enabled()
    assert autocast(amp, "cpu").__class__.__name__ == "nullcontext"
    outs = []
    for c in (cfg, amp):
        model = make_model(c)
        opt = make_optimizer(model, c)
        g = torch.Generator().manual_seed(0)
        outs.append(train_step(model, opt, scene, c, 0, g, scaler=make_scaler(c, "cpu")))
    assert torch.equal(outs[0], outs[1])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("amp", ["bf16", "fp16"])
def test_amp_trains_on_cuda(small, scene, tmp_path, amp):
    cfg = load_config("demo", small + GRID + ["train.iters=30", f"train.amp={amp}"])
    train(scene, cfg, tmp_path / "run", device="cuda", progress=False)
    m = read_metrics(tmp_path / "run")
    assert all(np.isfinite(r["loss"]) for r in m)
    assert m[-1]["loss"] < 0.8 * m[0]["loss"]


def test_next_batch_size_closed_form():
    from neus_l0.train.step import next_batch_size

    cfg = load_config("demo", ["train.batch_size=128", "train.sample_budget=8192"])
    assert next_batch_size(128, 4096.0, cfg) == 256    # half the budget: twice the rays
    assert next_batch_size(200, 8192.0, cfg) == 200    # on budget: unchanged
    assert next_batch_size(128, 1.0, cfg) == 1024      # at most 8 x batch_size
    assert next_batch_size(128, 1e9, cfg) == 16        # at least batch_size / 8
    assert next_batch_size(128, 0.0, cfg) == 1024      # no ray got samples
    assert next_batch_size(77, 4096.0, load_config("demo", ["train.batch_size=128"])) == 77
    with pytest.raises(ConfigError, match="sample_budget"):
        load_config("demo", ["train.sample_budget=-1"])


def test_sample_budget_adapts_the_rays_and_resumes_exactly(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=12", "train.log_every=3",
                                       "render.cull_outside_sphere=true",
                                       "train.sample_budget=6000"])
    train(scene, cfg, tmp_path / "a", progress=False)
    logs = [m for m in read_metrics(tmp_path / "a") if "rays" in m]
    assert [m["iter"] for m in logs] == [3, 6, 9, 12]
    assert logs[0]["rays"] == 64 and logs[1]["rays"] != 64  # adapted after the first log
    per_ray = cfg.render.n_samples + cfg.render.n_importance
    for m in logs:
        assert 0 < m["samples"] <= m["rays"] * per_ray
    assert max(m["rays"] for m in logs) <= 8 * 64
    # 64 rays x 32 samples cannot reach 6000 samples: the count grows, up to 8 x 64
    assert logs[1]["rays"] > 64
    a = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    assert 64 < a["batch_size"] <= 8 * 64
    # interrupted mid-window (iteration 5), resumed: bitwise the same run
    train(scene, cfg, tmp_path / "b", progress=False, stop_at=5)
    train(scene, cfg, tmp_path / "b", resume=True, progress=False)
    b = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    assert a["iteration"] == b["iteration"] == 12 and a["batch_size"] == b["batch_size"]
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert torch.equal(a["rng"]["generator"], b["rng"]["generator"])

"""Faults a trusted tool survives (issue 18): output paths that are files, meshes too large
for memory, a damaged newest checkpoint, an empty mask."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest
import torch

from neus_l0.cli import main
from neus_l0.config.load import load_config
from neus_l0.device import available_memory
from neus_l0.errors import NeusL0Error, SceneError
from neus_l0.formats.neus import load_scene, validate_scene
from neus_l0.mesh.memory import (
    BYTES_PER_FACE,
    EVAL_BYTES_PER_POINT,
    extraction_bytes,
    largest_resolution,
    mesh_faces,
    plan_extraction,
)
from neus_l0.run.checkpoints import (
    CorruptCheckpointError,
    list_checkpoints,
    load_newest_checkpoint,
    load_trained_model,
)


def _one_line_error(capsys, *fragments):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for f in fragments:
        assert f in err, err
    return err


# --- 1. an output path that is a file -------------------------------------------------------

@pytest.mark.parametrize("argv", [
    ["train", "DATA", "--out", "{f}", "--quiet"],
    ["demo", "--out", "{f}", "--quiet"],
    ["synth", "demo", "{f}"],
    ["colmap", "DATA", "{f}"],
    ["figures", "--bench", "DATA", "--out", "{f}"],
    ["train", "DATA", "--out", "{f}/run", "--quiet"],
    ["synth", "demo", "{f}/scene"],
    ["mesh", "RUN", "--out", "{f}/mesh.ply"],
    ["eval", "DATA/m.ply", "--scene", "DATA", "--error-maps", "{f}"],
    ["eval", "DATA/m.ply", "--scene", "DATA", "--json", "{f}/m.json"],
])
def test_an_output_folder_that_is_a_file_is_one_line(tmp_path, capsys, argv):
    f = tmp_path / "afile"
    f.write_text("keep me\n")
    args = [a.format(f=f) for a in argv]
    args = [a.replace("DATA", str(tmp_path / "data")) for a in args]
    args = [str(tmp_path / "run") if a == "RUN" else a for a in args]
    assert main(args) == 2
    _one_line_error(capsys, str(f))
    assert f.read_text() == "keep me\n"


def test_mesh_out_that_is_a_folder_is_one_line(tmp_path, capsys):
    (tmp_path / "dir.ply").mkdir()
    assert main(["mesh", str(tmp_path), "--out", str(tmp_path / "dir.ply")]) == 2
    _one_line_error(capsys, "is a folder")


# --- 2. memory of a mesh extraction ---------------------------------------------------------

def test_extraction_bytes_grids_are_exact():
    for R in (9, 64, 257):
        faces = mesh_faces(R)
        batch = EVAL_BYTES_PER_POINT * min(2**18, R**3)
        assert extraction_bytes("dense", R) == int(4 * R**3 + batch + BYTES_PER_FACE * faces)
        nb = -(-(R - 1) // 8)
        assert extraction_bytes("sparse", R) >= 4 * (nb + 1) ** 3 + batch + BYTES_PER_FACE * faces
    # the case: the sparse path's coarse grid alone is 7.1 TiB at 100000^3
    assert extraction_bytes("sparse", 100_000) > 7.1 * 2**40
    assert extraction_bytes("dense", 100_000) > 4 * 1e15


def test_largest_resolution_is_the_boundary():
    for budget in (2**26, 2**30, 8 * 2**30, 64 * 2**30):
        for method in ("dense", "sparse"):
            r = largest_resolution(method, budget)
            assert extraction_bytes(method, r) <= budget < extraction_bytes(method, r + 1)
    assert largest_resolution("dense", 1000) == 0
    with pytest.raises(NeusL0Error, match="not even --resolution 8 fits"):
        plan_extraction("sparse", 64, available=1000)


def test_plan_refuses_with_the_largest_resolution_that_fits():
    gib = 2**30
    with pytest.raises(NeusL0Error) as info:
        plan_extraction("sparse", 100_000, available=16 * gib)
    msg = str(info.value)
    best = largest_resolution("sparse", 16 * gib)
    assert "\n" not in msg and f"about {best}" in msg and "16 GiB is available" in msg
    assert "TiB" in msg
    assert 1000 < best < 100_000
    # dense that does not fit, sparse that does: routed, with a note
    R = 1024
    avail = (extraction_bytes("dense", R) + extraction_bytes("sparse", R)) // 2
    assert extraction_bytes("sparse", R) < avail < extraction_bytes("dense", R)
    method, note = plan_extraction("dense", R, available=avail)
    assert method == "sparse" and "sparse path" in note
    assert plan_extraction("dense", 64, available=16 * gib) == ("dense", None)


def test_plan_without_a_memory_figure_does_not_refuse(monkeypatch):
    import neus_l0.mesh.memory as mm

    monkeypatch.setattr(mm, "available_memory", lambda: None)
    assert plan_extraction("sparse", 10**6) == ("sparse", None)


def test_available_memory_is_plausible():
    avail = available_memory()
    assert avail is None or 2**20 < avail < 2**50


def test_estimate_covers_the_measured_sparse_peak():
    """tracemalloc peak of the sparse path on a sphere of about the assumed area."""
    import tracemalloc

    from neus_l0.mesh.extract import sparse_marching_cubes
    from neus_l0.synthetic.shapes import Sphere

    r = 0.7  # area 4 pi r^2 = 6.16, the estimator assumes 2 pi = 6.28
    R = 160
    tracemalloc.start()
    try:
        V, F, _ = sparse_marching_cubes(Sphere((0.0, 0.0, 0.0), r), R)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert abs(len(F) / mesh_faces(R, area=4 * np.pi * r**2) - 1) < 0.15
    assert peak < extraction_bytes("sparse", R)


# --- a tiny real run with two checkpoints ---------------------------------------------------

@pytest.fixture(scope="module")
def tiny_run(small_overrides, sphere_scene, tmp_path_factory):
    from neus_l0.train.loop import train

    root = tmp_path_factory.mktemp("faults")
    cfg = load_config("demo", [*small_overrides, "train.iters=2", "train.save_every=1"])
    train(sphere_scene(root / "scene"), cfg, root / "run", progress=False)
    assert [p.name for p in list_checkpoints(root / "run")] == ["ckpt_0000001.pt",
                                                                "ckpt_0000002.pt"]
    return root / "run"


@pytest.fixture
def run(tiny_run, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(tiny_run, dst)
    return dst


def test_mesh_resolution_too_large_is_refused_before_loading(run, capsys):
    assert main(["mesh", str(run), "--resolution", "100000"]) == 2
    err = _one_line_error(capsys, "--resolution 100000", "largest resolution that fits")
    assert "TiB" in err or "PiB" in err
    assert not (run / "mesh.ply").exists()


# --- 3. a damaged newest checkpoint ---------------------------------------------------------

def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_truncated_newest_checkpoint_falls_back_and_is_kept(run, capsys):
    ckpt1, ckpt2 = list_checkpoints(run)
    _truncate(ckpt2)
    damaged = ckpt2.read_bytes()
    path, state = load_newest_checkpoint(run)
    assert path == ckpt1 and state["iteration"] == 1
    err = _one_line_error(capsys, "ckpt_0000002.pt", "ckpt_0000002.pt.corrupt",
                          "using ckpt_0000001.pt")
    assert "\n" not in err
    assert not ckpt2.exists() and (run / "checkpoints" / "ckpt_0000002.pt.corrupt"
                                   ).read_bytes() == damaged
    assert list_checkpoints(run) == [ckpt1]
    # the next call finds nothing damaged and says nothing
    assert load_newest_checkpoint(run)[0] == ckpt1
    assert capsys.readouterr().err == ""


def test_load_trained_model_and_mesh_fall_back(run, tiny_run, tmp_path, capsys):
    ckpt1, ckpt2 = list_checkpoints(run)
    ref = torch.load(ckpt1, weights_only=True)["model"]
    _truncate(ckpt2)
    model, cfg, info = load_trained_model(run)
    assert info["iteration"] == 1 and info["path"] == ckpt1
    for k, v in model.state_dict().items():
        assert torch.equal(v, ref[k]), k
    assert not model.training and cfg.train.iters == 2
    _one_line_error(capsys, "ckpt_0000002.pt.corrupt")

    shutil.rmtree(run)
    shutil.copytree(tiny_run, run)
    _truncate(list_checkpoints(run)[-1])
    out = tmp_path / "m.ply"
    assert main(["mesh", str(run), "--resolution", "24", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "iteration 1" in captured.out and out.is_file()
    assert "using ckpt_0000001.pt" in captured.err
    assert (run / "checkpoints" / "ckpt_0000002.pt.corrupt").is_file()


def test_nan_newest_checkpoint_falls_back(run, capsys):
    ckpt1, ckpt2 = list_checkpoints(run)
    state = torch.load(ckpt2, weights_only=True)
    key = next(k for k in state["model"] if state["model"][k].is_floating_point())
    state["model"][key].view(-1)[0] = float("nan")
    torch.save(state, ckpt2)
    assert load_newest_checkpoint(run)[0] == ckpt1
    _one_line_error(capsys, "NaN", "ckpt_0000002.pt.corrupt")


def test_all_damaged_is_an_error_and_nothing_is_renamed(run):
    ckpts = list_checkpoints(run)
    for p in ckpts:
        _truncate(p)
    with pytest.raises(NeusL0Error, match="none of the 2 checkpoints") as info:
        load_newest_checkpoint(run)
    assert "\n" not in str(info.value) and "ckpt_0000002.pt" in str(info.value)
    assert list_checkpoints(run) == ckpts
    with pytest.raises(NeusL0Error):
        load_trained_model(run)


def test_a_failure_that_is_not_the_file_renames_nothing(run, monkeypatch):
    def no_module(*args, **kwargs):
        raise ModuleNotFoundError("No module named 'gone'")

    monkeypatch.setattr(torch, "load", no_module)
    with pytest.raises(NeusL0Error) as info:
        load_newest_checkpoint(run)
    assert not isinstance(info.value, CorruptCheckpointError)
    assert len(list_checkpoints(run)) == 2


def test_explicit_checkpoint_does_not_fall_back(run):
    ckpt2 = list_checkpoints(run)[-1]
    _truncate(ckpt2)
    with pytest.raises(CorruptCheckpointError, match="cannot read checkpoint"):
        load_trained_model(run, checkpoint=ckpt2)
    assert ckpt2.exists()


def test_no_checkpoint_is_none(tmp_path):
    assert load_newest_checkpoint(tmp_path) is None
    with pytest.raises(NeusL0Error, match="train first"):
        load_trained_model(tmp_path)


# --- 6. empty masks -------------------------------------------------------------------------

def _blank(root, name):
    cv2.imwrite(str(root / "mask" / name), np.full((48, 64, 3), 100, np.uint8))


def test_one_empty_mask_is_a_warning(scene_copy, capsys):
    _blank(scene_copy, "005.png")
    scene = load_scene(scene_copy)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "005.png" in err and "1 of 8" in err
    assert scene.masks[5].sum() == 0 and (scene.masks.sum(dim=(1, 2)) > 0).sum() == 7
    info = validate_scene(scene_copy)
    assert info["empty_masks"] == [5]
    assert any("mask/005.png" in w for w in info["warnings"])
    assert main(["inspect", str(scene_copy)]) == 0
    assert "mask/005.png" in capsys.readouterr().out


def test_all_masks_empty_is_an_error(scene_copy):
    for p in sorted((scene_copy / "mask").iterdir()):
        _blank(scene_copy, p.name)
    with pytest.raises(SceneError, match="every mask is empty") as info:
        load_scene(scene_copy)
    assert "\n" not in str(info.value)

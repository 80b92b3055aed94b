"""`neus-l0 render`: orbit cameras (closed form), frames and videos of a tiny trained run,
PSNR / SSIM on training and held-out views, and the one-line errors."""

from __future__ import annotations

import argparse
import json
import os

import cv2
import numpy as np
import pytest
import torch

from neus_l0.commands.render import add_parser, run
from neus_l0.config.load import load_config
from neus_l0.data.rays import pixel_rays
from neus_l0.data.split import split_views
from neus_l0.errors import NeusL0Error
from neus_l0.formats.neus import load_scene
from neus_l0.pipelines.render_run import RenderOptions, render_run, select_views
from neus_l0.render.cameras import (
    camera_elevations,
    depth_range,
    orbit_from_training,
    orbit_poses,
    resize_intrinsics,
    up_direction,
)
from neus_l0.render.video import check_video
from neus_l0.render.views import MSE_FLOOR, mean_metrics, psnr, view_metrics
from neus_l0.train.loop import train


@pytest.fixture(scope="module")
def trained_run(tiny_scene, small_overrides, tmp_path_factory):
    """A run folder trained for 10 iterations on the tiny demo scene (64x48, 8 views, masks,
    so a visual hull)."""
    run_dir = tmp_path_factory.mktemp("render") / "run"
    cfg = load_config("demo", [*small_overrides, "train.iters=10"])
    train(load_scene(tiny_scene), cfg, run_dir, progress=False)
    assert (run_dir / "hull.pt").is_file()
    return run_dir


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers(), "render")
    return parser.parse_args(["render", *argv])


def _json_line(capsys) -> dict:
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1, lines
    return json.loads(lines[0])


def _frames(path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while (got := cap.read())[0]:
        frames.append(got[1])
    cap.release()
    return frames


# ------------------------------------------------------------------------------------------
# Cameras (pure).


def test_orbit_cameras_look_at_the_centre_at_the_given_distance_and_elevation():
    up = np.array([0.3, -0.2, 0.9])
    up /= np.linalg.norm(up)
    start = np.array([1.0, 2.0, 0.5])
    poses = orbit_poses(8, 2.7, 25.0, up, start=start)
    assert poses.shape == (8, 4, 4)
    centres = poses[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 2.7, atol=1e-12)
    np.testing.assert_allclose(camera_elevations(poses, up), 25.0, atol=1e-9)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # the optical axis (z) points at the origin; image up (-y) leans towards `up`
    np.testing.assert_allclose(R[:, :, 2], -centres / 2.7, atol=1e-12)
    assert (-R[:, :, 1] @ up > 0).all()
    # equal azimuth steps of 2 pi / 8 about `up`, frame 0 at `start`'s azimuth
    flat = centres - (centres @ up)[:, None] * up
    flat /= np.linalg.norm(flat, axis=1, keepdims=True)
    steps = np.arctan2(np.cross(flat, np.roll(flat, -1, 0)) @ up,
                       (flat * np.roll(flat, -1, 0)).sum(1))
    np.testing.assert_allclose(steps, 2 * np.pi / 8, atol=1e-12)
    s = start - (start @ up) * up
    np.testing.assert_allclose(flat[0], s / np.linalg.norm(s), atol=1e-12)
    # the ray through the principal point passes through the centre
    K = torch.tensor([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    o, d = pixel_rays(K, torch.tensor(poses, dtype=torch.float32),
                      torch.tensor([[15.5, 11.5]]).expand(8, 2))
    t = -(o * d).sum(-1, keepdim=True)
    assert (o + t * d).norm(dim=-1).max() < 1e-5


def test_orbit_from_training_takes_the_mean_distance_and_elevation(sphere_scene, tmp_path):
    scene = sphere_scene(tmp_path)  # 6 cameras at 2.5, elevations 0.3 and 0.6 rad, up +z
    c2w = scene.c2w.double().numpy()
    np.testing.assert_allclose(up_direction(c2w), [0, 0, 1], atol=1e-6)
    poses = orbit_from_training(c2w, 5)
    np.testing.assert_allclose(np.linalg.norm(poses[:, :3, 3], axis=1), 2.5, atol=1e-5)
    np.testing.assert_allclose(camera_elevations(poses, np.array([0, 0, 1.0])),
                               np.degrees(0.45), atol=1e-4)
    high = orbit_from_training(c2w, 5, elevation_deg=60.0)
    np.testing.assert_allclose(np.degrees(np.arcsin(high[:, 2, 3] / 2.5)), 60.0, atol=1e-4)


def test_resized_intrinsics_match_the_loaders_integer_downscale():
    K = np.array([[100.0, 0.5, 31.5], [0, 98.0, 23.5], [0, 0, 1]])
    s = 4
    S = np.array([[1 / s, 0, -(s - 1) / (2 * s)], [0, 1 / s, -(s - 1) / (2 * s)], [0, 0, 1]])
    np.testing.assert_allclose(resize_intrinsics(K, (48, 64), (12, 16)), S @ K, atol=1e-12)
    np.testing.assert_allclose(resize_intrinsics(K, (48, 64), (48, 64)), K, atol=1e-12)


def test_held_out_views_match_the_bench_split():
    for k in (2, 3, 8):
        train_v, held = split_views(17, k)
        assert select_views(17, RenderOptions(views="test", holdout=k)) == held
        assert select_views(17, RenderOptions(views="train", holdout=k)) == train_v
    assert select_views(5, RenderOptions(views="train", test_views=(4, 0))) == [1, 2, 3]
    assert select_views(5, RenderOptions(views="train")) == [0, 1, 2, 3, 4]


# ------------------------------------------------------------------------------------------
# Metrics.


def test_a_perfect_image_scores_100_db_and_ssim_1():
    img = np.random.default_rng(0).random((24, 32, 3)).astype(np.float32)
    mask = np.zeros((24, 32), bool)
    m = view_metrics(img, img, mask)
    assert m["psnr"] == pytest.approx(-10 * np.log10(MSE_FLOOR)) == pytest.approx(100.0)
    assert m["ssim"] == pytest.approx(1.0)
    assert m["psnr_mask"] is None  # an empty mask has no PSNR
    json.dumps(m, allow_nan=False)  # finite: valid JSON
    assert psnr(img * 0 + 0.5, img * 0 + 0.6) == pytest.approx(20.0)
    assert mean_metrics([m, {"psnr": 20.0, "ssim": 0.5, "psnr_mask": 30.0}]) == {
        "psnr": pytest.approx(60.0), "ssim": pytest.approx(0.75), "psnr_mask": 30.0}


# ------------------------------------------------------------------------------------------
# Rendering a run.


def test_orbit_writes_frames_and_videos_that_read_back(trained_run, tmp_path, capsys):
    out = tmp_path / "orbit"
    assert run(_args(str(trained_run), "--out", str(out), "--frames", "4", "--downscale", "2",
                     "--quiet")) == 0
    line = _json_line(capsys)
    assert (line["frames"], line["width"], line["height"]) == (4, 32, 24)
    for ch in ("color", "normal", "depth"):
        pngs = sorted(p.name for p in (out / ch).iterdir())
        assert pngs == ["0000.png", "0001.png", "0002.png", "0003.png"]
        assert cv2.imread(str(out / ch / "0003.png")).shape == (24, 32, 3)
        frames = _frames(out / f"{ch}.mp4")
        assert len(frames) == 4 and frames[0].shape == (24, 32, 3)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files
    assert not (out / "metrics.json").exists()
    # a shorter render into the same folder leaves no stale frames; odd sizes are padded
    run(_args(str(trained_run), "--out", str(out), "--frames", "2", "--width", "15",
              "--quiet", "--no-video"))
    assert sorted(p.name for p in (out / "color").iterdir()) == ["0000.png", "0001.png"]
    assert cv2.imread(str(out / "color" / "0000.png")).shape == (11, 15, 3)
    assert len(_frames(out / "color.mp4")) == 4  # --no-video: the old video is untouched


def test_train_views_report_psnr_and_ssim_as_one_json_line(trained_run, tmp_path, capsys):
    out = tmp_path / "train"
    run(_args(str(trained_run), "--out", str(out), "--views", "train", "--downscale", "2",
              "--quiet", "--no-video"))
    line = _json_line(capsys)
    assert [v["view"] for v in line["per_view"]] == list(range(8))
    for v in line["per_view"]:
        assert 0 < v["psnr"] < 100 and -1 <= v["ssim"] <= 1 and v["psnr_mask"] > 0
    assert line["psnr"] == pytest.approx(np.mean([v["psnr"] for v in line["per_view"]]))
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["per_view"] == line["per_view"] and saved["ssim"] == line["ssim"]
    assert not (out / "color.mp4").exists()


def test_held_out_views_and_a_video_at_full_size(trained_run, tmp_path):
    res = render_run(trained_run, tmp_path / "test",
                     RenderOptions(views="test", test_views=(2, 5)), progress=False)
    assert res.size == (48, 64) and [v["view"] for v in res.metrics["per_view"]] == [2, 5]
    assert len(_frames(res.videos["depth"])) == 2


# ------------------------------------------------------------------------------------------
# Errors: one line each.


def _one_line_error(args: argparse.Namespace, match: str) -> None:
    with pytest.raises(NeusL0Error, match=match) as exc:
        run(args)
    assert "\n" not in str(exc.value)


def test_a_run_without_checkpoints_is_refused(tmp_path):
    (tmp_path / "empty").mkdir()
    _one_line_error(_args(str(tmp_path / "empty")), "no checkpoints")
    assert not (tmp_path / "empty" / "render").exists()


def test_test_views_without_held_out_views_are_refused(trained_run, tmp_path):
    _one_line_error(_args(str(trained_run), "--views", "test", "--out", str(tmp_path / "o")),
                    "no held-out views")
    _one_line_error(_args(str(trained_run), "--views", "test", "--test-views", "3,99"),
                    "out of range")
    _one_line_error(_args(str(trained_run), "--test-views", "a,b"), "comma-separated")


@pytest.mark.parametrize("flags, match", [
    (["--width", "0"], "--width 0: must be at least 1"),
    (["--height", "0"], "--height 0: must be at least 1"),
    (["--downscale", "0"], "--downscale 0.0: must be > 0"),
    (["--downscale", "1000"], "--downscale 1000.0: leaves"),
    (["--frames", "0"], "--frames 0: must be at least 1"),
    (["--width", "8", "--downscale", "2"], "not both"),
])
def test_a_size_of_zero_is_refused(trained_run, tmp_path, flags, match):
    _one_line_error(_args(str(trained_run), "--out", str(tmp_path / "o"), *flags), match)


def test_an_unwritable_out_is_refused(trained_run, tmp_path):
    (tmp_path / "file").write_text("x")
    _one_line_error(_args(str(trained_run), "--out", str(tmp_path / "file" / "o")),
                    "is a file, not a folder")
    with pytest.raises(NeusL0Error, match="cannot write there"):
        render_run(trained_run, tmp_path / "file" / "o", RenderOptions(frames=1),
                   progress=False)
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(NeusL0Error, match="cannot write there"):
            render_run(trained_run, locked, RenderOptions(frames=1), progress=False)


def test_a_video_that_does_not_read_back_is_an_error(trained_run, tmp_path):
    bogus = tmp_path / "bogus.mp4"
    bogus.write_bytes(b"not a video")
    with pytest.raises(NeusL0Error, match="bogus.mp4"):
        check_video(bogus, 3, (24, 32))
    res = render_run(trained_run, tmp_path / "v", RenderOptions(frames=2, downscale=2),
                     progress=False)
    with pytest.raises(NeusL0Error, match="reads back as 2 frames"):
        check_video(res.videos["color"], 3, (24, 32))


def test_depth_range_is_the_unit_spheres_narrowed_to_a_box():
    poses = orbit_poses(4, 3.0, 0.0, np.array([0, 0, 1.0]), start=np.array([1.0, 0, 0]))
    assert depth_range(poses) == pytest.approx((2.0, 4.0))
    box = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    assert depth_range(poses, box) == pytest.approx((2.5, 3.5))
    assert depth_range(poses, box * 10) == pytest.approx((2.0, 4.0))  # never past the sphere

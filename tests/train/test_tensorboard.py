"""`neus_l0.train.tensorboard.TensorBoardLogger`: what is written reads back from the events."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing import event_accumulator

from neus_l0.train.tensorboard import TensorBoardLogger


def _read(run_dir):
    acc = event_accumulator.EventAccumulator(
        str(run_dir), size_guidance={event_accumulator.SCALARS: 0, event_accumulator.IMAGES: 0})
    acc.Reload()
    return acc


def test_scalars_and_an_image_read_back(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (6, 10, 3), dtype=np.uint8)
    with TensorBoardLogger(tmp_path / "run") as tb:
        tb.scalars(50, {"loss": 0.25, "inv_s": 12.5, "lr": np.float32(1e-3),
                        "samples_per_ray": torch.tensor(64), "its_per_s": 7,
                        "note": "skipped", "none": None, "flag": True})
        tb.scalars(100, {"loss": 0.125, "psnr": float("nan")})
        tb.scalars(100, {"psnr": 21.5}, prefix="val/")
        tb.image(100, "val/rgb", img)
    assert list((tmp_path / "run").glob("events.out.tfevents.*"))
    acc = _read(tmp_path / "run")
    tags = set(acc.Tags()["scalars"])
    assert tags == {"train/loss", "train/inv_s", "train/lr", "train/samples_per_ray",
                    "train/its_per_s", "train/psnr", "val/psnr"}
    assert [(e.step, e.value) for e in acc.Scalars("train/loss")] == [(50, 0.25), (100, 0.125)]
    assert acc.Scalars("train/lr")[0].value == pytest.approx(1e-3)
    assert acc.Scalars("train/samples_per_ray")[0].value == 64.0
    assert math.isnan(acc.Scalars("train/psnr")[0].value)
    assert [(e.step, e.value) for e in acc.Scalars("val/psnr")] == [(100, 21.5)]
    (event,) = acc.Images("val/rgb")
    assert (event.step, event.width, event.height) == (100, 10, 6)
    from PIL import Image

    decoded = np.asarray(Image.open(io.BytesIO(event.encoded_image_string)).convert("RGB"))
    np.testing.assert_array_equal(decoded, img)  # PNG: lossless


def test_nothing_is_written_before_the_first_value(tmp_path):
    tb = TensorBoardLogger(tmp_path / "run")
    tb.close()
    assert not (tmp_path / "run").exists()


def test_bad_images_are_refused(tmp_path):
    with TensorBoardLogger(tmp_path) as tb:
        with pytest.raises(ValueError, match="uint8"):
            tb.image(0, "x", np.zeros((4, 4, 3), dtype=np.float32))
        with pytest.raises(ValueError, match="uint8"):
            tb.image(0, "x", np.zeros((4, 4), dtype=np.uint8))


def test_a_resume_purges_the_overlap(tmp_path):
    with TensorBoardLogger(tmp_path) as tb:
        for step in (100, 200, 300):
            tb.scalars(step, {"loss": float(step)})
    with TensorBoardLogger(tmp_path, purge_step=200) as tb:  # resumed from iteration 200
        tb.scalars(200, {"loss": -2.0})
        tb.scalars(300, {"loss": -3.0})
    values = [(e.step, e.value) for e in _read(tmp_path).Scalars("train/loss")]
    assert values == [(100, 100.0), (200, -2.0), (300, -3.0)]

"""`train` checks that one step fits in memory before the run (issue #33 item 12): a batch
or a sample count far too large is one line naming the largest batch that fits."""

from __future__ import annotations

import pytest

from neus_l0.config.load import load_config
from neus_l0.errors import NeusL0Error
from neus_l0.fields.model import make_model
from neus_l0.train.preflight import check_step_memory, step_bytes


@pytest.mark.parametrize("override", ["train.batch_size=3000000", "render.n_samples=100000"])
def test_step_too_large_is_refused(tmp_path, tiny_scene, override, refused):
    run = tmp_path / "run"
    line = refused(["train", str(tiny_scene), "--out", str(run), "--conf", "demo",
                              "--threads", "1", "--quiet", override],
                     "one training step", "GiB", "largest batch that fits")
    assert not (run / "checkpoints").exists() or not any((run / "checkpoints").iterdir()), line


def test_estimate_grows_with_rays_samples_and_width():
    small = load_config("demo", [])
    wide = load_config("demo", ["model.sdf.hidden=256", "render.n_samples=64"])
    m_small, m_wide = make_model(small, "cpu"), make_model(wide, "cpu")
    assert step_bytes(m_small, small, 2048) == pytest.approx(2 * step_bytes(m_small, small,
                                                                            1024), rel=1e-6)
    assert step_bytes(m_wide, wide, 1024) > 2 * step_bytes(m_small, small, 1024)


def test_largest_batch_fits():
    cfg = load_config("demo", ["train.batch_size=100000"])
    model = make_model(cfg, "cpu")
    available = step_bytes(model, cfg, 4000)
    with pytest.raises(NeusL0Error) as caught:
        check_step_memory(model, cfg, available)
    best = int(str(caught.value).rsplit("train.batch_size=", 1)[1])
    assert 0.8 * 3000 <= best <= 0.8 * 4000
    fit = load_config("demo", [f"train.batch_size={best}"])
    check_step_memory(model, fit, available)

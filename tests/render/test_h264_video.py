"""`render`'s videos are H.264 that Chromium plays: the codec read back with the bundled
ffmpeg, and a ``<video>`` in headless Chromium with a duration."""

from __future__ import annotations

import numpy as np
import pytest

from neus_l0.errors import NeusL0Error
from neus_l0.render.video import Mp4Writer, check_video, count_frames, probe
from neus_l0.viewer.browser import find_chromium, open_page


def _write(path, n=6, size=(23, 31)):
    writer = Mp4Writer(path, size, fps=12)
    rng = np.random.default_rng(0)
    for _ in range(n):
        writer.write(rng.integers(0, 255, (*size, 3), dtype=np.uint8))
    writer.close()
    return writer


def test_the_mp4_is_h264_with_every_frame(tmp_path):
    writer = _write(tmp_path / "a.mp4")
    assert probe(tmp_path / "a.mp4") == {"codec": "h264", "width": 32, "height": 24}
    assert count_frames(tmp_path / "a.mp4") == 6
    check_video(tmp_path / "a.mp4", 6, writer.size)
    with pytest.raises(NeusL0Error, match="reads back as 6 frames"):
        check_video(tmp_path / "a.mp4", 7, writer.size)


def test_chromium_plays_the_mp4(tmp_path):
    if find_chromium() is None:
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    _write(tmp_path / "a.mp4", n=12)
    (tmp_path / "index.html").write_text('<video src="a.mp4" muted></video>')
    js = ("new Promise(r => { const v = document.querySelector('video');"
          " const done = () => r(v.error ? -v.error.code : v.duration);"
          " if (v.readyState >= 1 || v.error) done();"
          " v.onloadedmetadata = done; v.onerror = done; })")
    shot = open_page((tmp_path / "index.html").as_uri(), evaluate=js, settle=0.0)
    assert shot.value == pytest.approx(1.0, abs=0.1), f"<video> error or duration {shot.value}"
    assert not shot.outside

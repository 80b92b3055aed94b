"""H.264 MP4 videos that browsers play, through the ffmpeg that imageio-ffmpeg bundles
(built with libx264): writing, reading back, and the codec of a file.

The videos are H.264 (High profile), ``yuv420p`` and ``+faststart`` (the index first, so a
browser starts playing before the whole file has arrived): what Chromium, Firefox and Safari
play in a ``<video>``. Sides are padded to even numbers (``yuv420p`` needs them) by
repeating the last row / column.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error

#: The codec `Mp4Writer` writes (as ffmpeg names it).
CODEC = "h264"


def ffmpeg_exe() -> str:
    """The path of imageio-ffmpeg's bundled ffmpeg.

    Raises:
        NeusL0Error: imageio-ffmpeg is missing or has no binary for this platform.
    """
    try:
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as exc:
        raise NeusL0Error(f"imageio-ffmpeg: no ffmpeg ({exc}); pip install imageio-ffmpeg, "
                          "or use --no-video") from None


class Mp4Writer:
    """Frames -> an H.264 MP4 at `path` (written by the bundled ffmpeg).

    Args:
        path: the file to write; size: (H, W) of the frames; fps: frames per second.
    """

    def __init__(self, path: Path, size: tuple[int, int], fps: float) -> None:
        import imageio_ffmpeg

        H, W = size
        self.path, self.size, self.count = Path(path), (H + H % 2, W + W % 2), 0
        ffmpeg_exe()
        self.gen = imageio_ffmpeg.write_frames(
            str(path), (self.size[1], self.size[0]), fps=fps, codec="libx264",
            pix_fmt_out="yuv420p", macro_block_size=1, quality=None,
            output_params=["-crf", "18", "-preset", "medium", "-movflags", "+faststart",
                           "-f", "mp4"])
        self.gen.send(None)

    def write(self, rgb: np.ndarray) -> None:
        """Append an (H, W, 3) uint8 RGB frame."""
        H, W = rgb.shape[:2]
        pad = ((0, self.size[0] - H), (0, self.size[1] - W), (0, 0))
        self.gen.send(np.ascontiguousarray(np.pad(rgb, pad, mode="edge")))
        self.count += 1

    def close(self) -> None:
        """Finish the file (idempotent)."""
        if self.gen is not None:
            self.gen.close()
            self.gen = None


def probe(path: Path) -> dict:
    """What ``ffmpeg -i`` says of a video: ``{"codec", "width", "height"}`` of its first video
    stream (empty when it has none or is not a video)."""
    out = subprocess.run([ffmpeg_exe(), "-hide_banner", "-i", str(path)], capture_output=True,
                         text=True, check=False).stderr
    m = re.search(r"Stream #\S+.*?: Video: (\w+).*?, (\d+)x(\d+)", out)
    if m is None:
        return {}
    return {"codec": m.group(1), "width": int(m.group(2)), "height": int(m.group(3))}


def count_frames(path: Path) -> int:
    """The frames of a video, decoded by the bundled ffmpeg (0 when it does not decode)."""
    import imageio_ffmpeg

    try:
        return int(imageio_ffmpeg.count_frames_and_secs(str(path))[0])
    except (RuntimeError, OSError, ValueError):
        return 0


def check_video(path: Path, n_frames: int, size: tuple[int, int], name: Path | None = None
                ) -> None:
    """Check an MP4 is H.264 with `n_frames` frames of (H, W) = `size`.

    Raises:
        NeusL0Error: it does not decode, or has another codec, frame count or size.
    """
    name = name or path
    info = probe(path)
    if not info:
        raise NeusL0Error(f"{name}: the written video does not open with ffmpeg (use "
                          "--no-video and encode the PNGs yourself)")
    n = count_frames(path)
    got = (info["height"], info["width"])
    if info["codec"] != CODEC or n != n_frames or got != tuple(size):
        raise NeusL0Error(f"{name}: the written video reads back as {n} frames of {got} "
                          f"({info['codec']}), not {n_frames} of {tuple(size)} ({CODEC}; use "
                          "--no-video)")

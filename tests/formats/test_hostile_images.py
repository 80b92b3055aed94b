"""Scene images a hostile or careless user leaves (second attack of #33): a PNG declaring
60000x60000 pixels (a decompression bomb) and a scene folder whose name is not UTF-8, which
crashed OpenCV's own file open (`neus_l0.formats.neus`)."""

from __future__ import annotations

import os
import shutil
import struct
import zlib

import numpy as np

from neus_l0.cli import main
from neus_l0.formats.neus import read_image


def _bomb(path) -> None:
    """A valid-looking PNG header declaring 60000x60000 grey pixels, almost no data."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)
    header = struct.pack(">IIBBBBB", 60000, 60000, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
                     + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))


def test_a_png_bomb_is_refused_from_its_header(scene_copy, refused):
    """inspect and train: one line naming the file and its declared size, nothing decoded."""
    _bomb(scene_copy / "image" / "000.png")
    refused(["inspect", str(scene_copy)], "000.png", "60000x60000", "decompression bomb")
    _bomb(scene_copy / "mask" / "001.png")
    refused(["inspect", str(scene_copy)], "decompression bomb")


def test_a_scene_whose_name_is_not_utf8_reads(tiny_scene, tmp_path, capsys):
    """A folder named with a 0xff byte: inspect succeeds (it was a segmentation fault)."""
    odd = os.fsdecode(bytes(tmp_path) + b"/bad\xffname")
    shutil.copytree(tiny_scene, odd)
    rgb, _alpha = read_image(next((tmp_path / os.path.basename(odd) / "image").glob("*.png")))
    assert rgb.ndim == 3 and np.isfinite(rgb).all()
    assert main(["inspect", odd]) == 0, capsys.readouterr().err

"""Pictures people look at: enlarged, captioned previews and the truth/calibrated/oracle panel."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from hsi_torch.colour import (
    cube_to_srgb,
    labelled_image,
    save_labelled_png,
    save_preview_panel,
    save_preview_png,
)
from hsi_torch.spectral import DEFAULT_GRID


def _rgb(h=20, w=30, seed=0):
    return torch.rand(3, h, w, generator=torch.Generator().manual_seed(seed))


def test_labelled_image_enlarges_by_an_integer_factor_and_keeps_pixels():
    rgb = _rgb()
    img = labelled_image(rgb, min_size=100)  # 30 px wide -> factor ceil(100 / 30) = 4
    assert img.shape == (80, 120, 3) and img.dtype == np.uint8
    native = labelled_image(rgb)
    assert native.shape == (20, 30, 3)
    assert np.array_equal(img[::4, ::4], native)  # nearest neighbour: every 4x4 block one pixel
    assert np.array_equal(img[3::4, 3::4], native)
    expect = (rgb.permute(1, 2, 0).double().clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    assert np.array_equal(native, expect)
    assert labelled_image(rgb, min_size=10).shape == (20, 30, 3)  # never shrunk


def test_caption_and_label_strips():
    rgb = _rgb()
    img = labelled_image(rgb, min_size=200, caption="scene | bundle calib.npz | beta 10000",
                         label="truth")  # fmt: skip
    big = labelled_image(rgb, min_size=200)
    h = big.shape[0]
    assert img.shape[1] == big.shape[1] and img.shape[0] > h + 30  # a strip above and below
    # the image itself sits between the strips, unchanged
    lab = labelled_image(rgb, min_size=200, label="truth").shape[0] - h
    assert np.array_equal(img[lab : lab + h], big)
    # text is drawn: light pixels in the dark caption strip
    caption = img[lab + h :]
    assert caption.min() == 32 and caption.max() > 200
    # a long caption wraps instead of running off the image
    long = labelled_image(rgb, min_size=200, caption=" ".join(["word"] * 60))
    assert long.shape[0] > labelled_image(rgb, min_size=200, caption="word").shape[0]


def test_save_preview_png_caption_and_default(tmp_path):
    M = DEFAULT_GRID.num_bands
    cube = torch.rand(M, 12, 16, generator=torch.Generator().manual_seed(1))
    plain = save_preview_png(cube, DEFAULT_GRID, tmp_path / "plain.png")
    assert cv2.imread(str(plain)).shape == (12, 16, 3)  # without options: the cube's pixels
    big = save_preview_png(cube, DEFAULT_GRID, tmp_path / "big.png", caption="x | beta 1",
                           min_size=512)  # fmt: skip
    arr = cv2.imread(str(big))[..., ::-1]
    assert arr.shape[1] == 16 * 32 and arr.shape[0] > 12 * 32
    ref = labelled_image(cube_to_srgb(cube, DEFAULT_GRID, normalise="percentile"),
                         caption="x | beta 1", min_size=512)  # fmt: skip
    assert np.array_equal(arr, ref)


def test_panel(tmp_path):
    a, b = _rgb(seed=1), _rgb(seed=2)
    p = save_preview_panel([("truth", a), ("calibrated", b)], tmp_path / "panel.png",
                           caption="scene | beta 1e4", min_size=90, gap=8)  # fmt: skip
    arr = cv2.imread(str(p))[..., ::-1]
    tile = labelled_image(a, label="truth", min_size=90)
    assert arr.shape[1] == 2 * tile.shape[1] + 8
    assert np.array_equal(arr[: tile.shape[0], : tile.shape[1]], tile)
    assert (arr[: tile.shape[0], tile.shape[1] : tile.shape[1] + 8] == 255).all()  # the gap
    with pytest.raises(ValueError, match="differ in size"):
        save_preview_panel([("a", a), ("b", _rgb(10, 10))], tmp_path / "bad.png")
    out = save_labelled_png(a, tmp_path / "one.png", label="x", caption="y", min_size=60)
    assert cv2.imread(str(out)).shape[1] == 60

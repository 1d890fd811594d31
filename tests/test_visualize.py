"""Comparison grids: column titles sit above their own columns."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from fastgha_core.train.visualize import add_column_titles, make_grid, save_grid


def test_titles_band_labels_each_column_and_keeps_the_grid(tmp_path):
    rows = [[torch.rand(3, 40, 60) for _ in range(4)] for _ in range(2)]
    grid = make_grid(rows)
    titled = add_column_titles(grid, ["input 1", "ground truth", "FastGHA"], ncol=4, height=22)
    assert titled.shape == (grid.shape[0] + 22, grid.shape[1], 3)
    assert np.array_equal(titled[22:], grid)  # the images are untouched
    band = titled[:22].min(axis=2)  # dark where text is
    for j in range(4):
        col = band[:, 2 + j * 62 : 2 + j * 62 + 60]
        if j < 3:
            assert (col < 128).sum() > 10, j  # a title was drawn inside its own column
        else:
            assert (col < 128).sum() == 0  # no title for the last column
    out = save_grid(tmp_path / "g.png", rows, titles=["a", "b"])
    assert np.asarray(Image.open(out)).shape[0] == grid.shape[0] + 22


def test_too_many_titles_is_an_error():
    grid = make_grid([[torch.rand(3, 8, 8)]])
    with pytest.raises(ValueError, match="3 titles for 1 columns"):
        add_column_titles(grid, ["a", "b", "c"], ncol=1)

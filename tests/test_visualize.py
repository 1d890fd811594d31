"""Comparison grids: column titles sit above their own columns, cell labels inside their own cells."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from fastgha_core.train.visualize import add_cell_labels, add_column_titles, make_grid, save_grid


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


def test_cell_labels_are_written_inside_their_own_cells_only(tmp_path):
    rows = [[torch.ones(3, 40, 90) for _ in range(3)] for _ in range(2)]  # white cells, 2 px padding
    grid = make_grid(rows)
    labels = [["phone-5 01", None, "17.2 dB, id 0.47"], ["", "a label far too long to fit in one cell of ninety pixels"]]
    out = add_cell_labels(grid, rows, labels, height=14)
    assert out.shape == grid.shape and np.array_equal(grid, make_grid(rows))  # a copy: the grid is untouched
    dark = out.min(axis=2) < 128
    for i in range(2):
        for j in range(3):
            y, x = 2 + i * 42, 2 + j * 92
            cell = dark[y : y + 40, x : x + 90]
            labelled = bool(labels[i][j]) if j < len(labels[i]) else False
            assert (cell.sum() > 10) == labelled, (i, j)
            assert cell[14:].sum() == 0  # only the top strip is written
    assert dark.sum() == sum(dark[2 + i * 42 : 2 + i * 42 + 40, 2 + j * 92 : 2 + j * 92 + 90].sum() for i in range(2) for j in range(3))
    saved = np.asarray(Image.open(save_grid(tmp_path / "l.png", rows, titles=["a"], labels=labels)))
    assert saved.shape[0] == grid.shape[0] + 22 and np.array_equal(saved[22:], out)


def test_labels_without_a_cell_are_an_error():
    rows = [[torch.rand(3, 8, 8)]]
    with pytest.raises(ValueError, match="do not fit"):
        add_cell_labels(make_grid(rows), rows, [["a", "b"]])
    with pytest.raises(ValueError, match="do not fit"):
        add_cell_labels(make_grid(rows), rows, [["a"], ["b"]])

"""Image grids for validation renders and the evaluation comparison figure."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = ["make_grid", "save_grid", "add_column_titles", "add_cell_labels", "error_map"]


def error_map(pred: Tensor, target: Tensor, max_err: float = 0.25) -> Tensor:
    """``[3, H, W]`` x2 -> ``[3, H, W]`` heat map of the mean absolute error (black 0, yellow >= max_err)."""
    e = ((pred - target).abs().mean(0) / max_err).clamp(0, 1)  # [H, W]
    return torch.stack([(e * 2).clamp(0, 1), (e * 2 - 1).clamp(0, 1) * 0.9 + 0.1 * e, torch.zeros_like(e)])


def _cell_size(rows: Sequence[Sequence[Tensor | None]]) -> tuple[int, int]:
    """``(height, width)`` of ``make_grid``'s cells: the largest image's. Raises ``ValueError`` without images."""
    cells = [t for r in rows for t in r if t is not None]
    if not cells:
        raise ValueError("make_grid needs at least one image")
    return max(int(t.shape[-2]) for t in cells), max(int(t.shape[-1]) for t in cells)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def _fit_text(draw, text: str, font, width: int) -> tuple[str, tuple[int, int, int, int]]:
    """``(text, its bounding box)``, the text shortened with "…" until it is at most ``width`` pixels wide."""
    box = draw.textbbox((0, 0), text, font=font)
    while box[2] - box[0] > width and len(text) > 2:
        text = text[:-2] + "…"
        box = draw.textbbox((0, 0), text, font=font)
    return text, box


def make_grid(rows: Sequence[Sequence[Tensor | None]], pad: int = 2, fill: float = 1.0) -> np.ndarray:
    """Rows of ``[3, H, W]`` images in [0, 1] (None = empty cell) -> ``[H', W', 3]`` uint8; every cell
    has the size of the largest image, smaller ones are centred."""
    ch, cw = _cell_size(rows)
    ncol = max(len(r) for r in rows)
    H = len(rows) * (ch + pad) + pad
    W = ncol * (cw + pad) + pad
    out = torch.full((3, H, W), fill)
    for i, r in enumerate(rows):
        for j, t in enumerate(r):
            if t is None:
                continue
            t = t.detach().float().cpu().clamp(0, 1)
            if t.shape[0] == 1:
                t = t.expand(3, -1, -1)
            h, w = t.shape[-2:]
            y = pad + i * (ch + pad) + (ch - h) // 2
            x = pad + j * (cw + pad) + (cw - w) // 2
            out[:, y : y + h, x : x + w] = t
    return (out.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def add_column_titles(grid: np.ndarray, titles: Sequence[str], ncol: int, pad: int = 2, height: int = 22) -> np.ndarray:
    """A ``[H, W, 3]`` uint8 grid of ``ncol`` equal columns (as ``make_grid`` lays them out) with a
    white band of ``height`` pixels on top holding one centred title per column (black text).

    Raises ``ValueError`` when there are more titles than columns."""
    from PIL import Image, ImageDraw

    if len(titles) > ncol:
        raise ValueError(f"{len(titles)} titles for {ncol} columns")
    h, w = grid.shape[:2]
    cw = (w - pad) // ncol - pad
    band = Image.new("RGB", (w, height), (255, 255, 255))
    draw = ImageDraw.Draw(band)
    font = _font(max(8, height - 8))
    for j, title in enumerate(titles):
        x0 = pad + j * (cw + pad)
        title, (left, top, right, bottom) = _fit_text(draw, title, font, cw)
        draw.text((x0 + (cw - (right - left)) // 2 - left, (height - (bottom - top)) // 2 - top), title, fill=(0, 0, 0), font=font)
    return np.concatenate([np.asarray(band), grid], axis=0)


def add_cell_labels(grid: np.ndarray, rows: Sequence[Sequence[Tensor | None]], labels: Sequence[Sequence[str | None]], pad: int = 2,
                    height: int = 14) -> np.ndarray:
    """A copy of ``make_grid(rows, pad)``'s ``[H, W, 3]`` uint8 ``grid`` with ``labels[i][j]`` written in
    black on a white strip of ``height`` pixels across the top of cell ``(i, j)`` (None or "" = none;
    text too wide for the cell is shortened with "…"). The strip covers the top of the image in that
    cell, so labels suit renders whose top rows are background (heads framed with headroom).

    Raises ``ValueError`` when a label has no cell: more label rows than ``rows``, or a row with more
    labels than it has cells."""
    from PIL import Image, ImageDraw

    if len(labels) > len(rows) or any(len(lab) > len(r) for lab, r in zip(labels, rows)):
        raise ValueError(f"labels {[len(x) for x in labels]} do not fit the grid's rows {[len(r) for r in rows]}")
    ch, cw = _cell_size(rows)
    img = Image.fromarray(grid.copy())
    draw = ImageDraw.Draw(img)
    font = _font(max(8, height - 3))
    for i, lab in enumerate(labels):
        for j, text in enumerate(lab):
            if not text:
                continue
            x0, y0 = pad + j * (cw + pad), pad + i * (ch + pad)
            text, (left, top, right, bottom) = _fit_text(draw, text, font, cw - 2)
            draw.rectangle((x0, y0, x0 + cw - 1, y0 + height - 1), fill=(255, 255, 255))
            draw.text((x0 + 1 - left, y0 + (height - (bottom - top)) // 2 - top), text, fill=(0, 0, 0), font=font)
    return np.asarray(img)


def save_grid(path: str | Path, rows: Sequence[Sequence[Tensor | None]], pad: int = 2, titles: Sequence[str] | None = None,
              labels: Sequence[Sequence[str | None]] | None = None) -> Path:
    """``make_grid(rows)`` saved as a PNG at ``path``; ``titles`` label the columns (``add_column_titles``),
    ``labels`` the cells (``add_cell_labels``)."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    grid = make_grid(rows, pad=pad)
    if labels:
        grid = add_cell_labels(grid, rows, labels, pad=pad)
    if titles:
        grid = add_column_titles(grid, titles, max(len(r) for r in rows), pad=pad)
    Image.fromarray(grid).save(path)
    return path

import numpy as np

from sefm_recon.geometry.refine import GRID_CELLS, grid_subset


def test_grid_subset_keeps_the_most_confident_match_of_each_cell():
    rng = np.random.default_rng(3)
    w, h = 400, 300
    cell = np.sqrt(w * h / GRID_CELLS)  # 7.75 px, under MIN_CELL_PX: cells of 8 px
    uv = rng.uniform([0, 0], [w, h], (20000, 2))
    score = rng.integers(0, 5, len(uv)).astype(np.float32)  # many ties: the first of them is kept
    idx = grid_subset(uv, score, (w, h))
    key = np.floor(uv / max(cell, 8.0)).astype(int)
    cells = {}
    for i, k in enumerate(map(tuple, key)):
        if k not in cells or score[i] > score[cells[k]]:
            cells[k] = i
    assert sorted(idx.tolist()) == sorted(cells.values())
    # x-major cell order, as the tracks are handed to RANSAC
    assert [tuple(key[i]) for i in idx] == sorted(cells)


def test_grid_subset_of_no_match_is_empty():
    assert len(grid_subset(np.zeros((0, 2)), np.zeros(0), (100, 100))) == 0

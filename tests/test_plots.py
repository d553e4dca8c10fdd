"""Report figures: files are written, north is up, unknown cells are grey."""

import cv2
import numpy as np

from companion.plots import Series, bar_chart, height_map, line_chart, nice_ticks


def test_nice_ticks_cover_range_with_round_steps():
    t = nice_ticks(0.3, 47.0)
    assert t[0] >= 0.3 - 1e-9 and t[-1] <= 47.0 + 1e-9
    steps = np.diff(t)
    np.testing.assert_allclose(steps, steps[0])
    assert steps[0] in (5.0, 10.0)


def test_height_map_is_north_up_with_grey_unknown(tmp_path):
    h = np.full((20, 30), np.nan)
    h[15:20, 0:5] = 12.0  # north-west corner block is high
    h[0:5, 25:30] = 0.0   # south-east corner block is low
    p = height_map(tmp_path / "map.png", h, 0.0, 0.0, 1.0, "test", scale_px=4)
    img = cv2.imread(str(p))
    # Map area starts at (x=20, y=40) with 4 px per cell.
    nw = img[40 + 2, 20 + 2].astype(int)
    se = img[40 + 19 * 4 + 2, 20 + 29 * 4 + 2].astype(int)
    middle = img[40 + 10 * 4, 20 + 15 * 4].astype(int)
    assert tuple(middle) == (200, 200, 200)
    # viridis: high = yellow (high red+green), low = purple (low green)
    assert nw[1] > 180 and se[1] < 60


def test_charts_are_written(tmp_path):
    x = np.linspace(0, 100, 50)
    p = line_chart(tmp_path / "p.png", [Series(x, np.sin(x / 10) * 5 + 15, "alt"), Series(x, np.where(x > 50, np.nan, 3.0), "terrain")], "t", "m", "m")
    assert cv2.imread(str(p)).shape == (420, 900, 3)
    b = bar_chart(tmp_path / "b.png", ["lap 1", "lap 2"], {"a": [1.0, 2.0], "b": [np.nan, 3.0]}, "t", "m", reference=(2.5, "ref"))
    assert cv2.imread(str(b)) is not None

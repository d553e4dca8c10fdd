"""Report figures (matplotlib, the desk extra): files written, sizes within bounds, colour where
the data is, unknown cells grey, labels and legends as matplotlib text; the vehicle's import path
never loads matplotlib."""

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

pytest.importorskip("matplotlib")

from companion.desk import plots  # noqa: E402
from companion.desk.plots import PALETTE, Series, bar_chart, height_map, line_chart, nice_ticks  # noqa: E402


def test_nice_ticks_cover_range_with_round_steps():
    t = nice_ticks(0.3, 47.0)
    assert t[0] >= 0.3 - 1e-9 and t[-1] <= 47.0 + 1e-9
    steps = np.diff(t)
    np.testing.assert_allclose(steps, steps[0])
    assert steps[0] in (5.0, 10.0)


def _capture_figures(monkeypatch):
    """The text of each figure handed to plots._save, read after it is drawn."""
    kept, save = [], plots._save

    def keep(fig, path):
        out = save(fig, path)  # drawn: the tick labels exist now
        kept.append([t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text"))])
        return out

    monkeypatch.setattr(plots, "_save", keep)
    return kept


def _pixel_of(img, ax_px_bounds, east_frac, north_frac):
    x0, x1, y0, y1 = ax_px_bounds
    return img[int(round(y1 - north_frac * (y1 - y0))), int(round(x0 + east_frac * (x1 - x0)))].astype(int)


def _map_panel_bounds(img):
    """Pixel box (x0, x1, y0, y1) of the map panel: the largest connected region of the unknown
    cells' grey (the test maps keep a border of unknown cells)."""
    grey = np.all(np.abs(img.astype(int) - 204) <= 2, axis=2).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(grey)
    x, y, w, h, _ = stats[1 + np.argmax(stats[1:, cv2.CC_STAT_AREA])]
    return x, x + w - 1, y, y + h - 1


def test_small_map_is_north_up_readable_with_grey_unknown_and_a_metre_colour_bar(tmp_path, monkeypatch):
    texts = _capture_figures(monkeypatch)
    h = np.full((14, 10), np.nan)  # 14 m north x 10 m east at 1 m, a border of unknown cells
    h[10:13, 1:4] = 12.0  # north-west block high
    h[1:4, 6:9] = 0.0     # south-east block low
    p = height_map(tmp_path / "map.png", h, 0.0, 0.0, 1.0, "small map")
    img = cv2.imread(str(p))
    assert 500 <= img.shape[0] <= 1400 and 400 <= img.shape[1] <= 1400, img.shape
    box = _map_panel_bounds(img)
    assert box[1] - box[0] > 300 and box[3] - box[2] > 450, box  # the map itself is large, not a thumbnail
    nw = _pixel_of(img, box, 0.25, 0.82)
    se = _pixel_of(img, box, 0.75, 0.18)
    middle = _pixel_of(img, box, 0.5, 0.5)
    assert np.all(np.abs(middle - 204) <= 2)
    # viridis: high = yellow (high red and green), low = purple (low green); BGR order
    assert nw[1] > 180 and nw[2] > 180 and se[1] < 60, (nw, se)
    words = texts[0]
    assert "height (m)" in words and "east (m)" in words and "north (m)" in words and "unknown" in words
    ticks = [w for w in words if w.replace("−", "-").replace(".", "", 1).lstrip("-").isdigit()]
    assert ticks and all(len(w.split(".")[-1]) <= 2 for w in ticks if "." in w), ticks


def test_large_map_is_not_huge(tmp_path):
    h = np.random.default_rng(0).normal(5.0, 3.0, (200, 300))
    img = cv2.imread(str(height_map(tmp_path / "big.png", h, 0.0, 0.0, 1.0, "300 x 200 m", vmin=0, vmax=10)))
    assert 400 <= img.shape[0] <= 1200 and 600 <= img.shape[1] <= 1400, img.shape


def test_line_chart_draws_series_and_puts_the_legend_below(tmp_path, monkeypatch):
    texts = _capture_figures(monkeypatch)
    x = np.linspace(0, 100, 50)
    p = line_chart(tmp_path / "p.png", [Series(x, np.sin(x / 10) * 5 + 15, "altitude", PALETTE[1]),
                                        Series(x, np.where(x > 50, np.nan, 3.0), "terrain", dashed=True)],
                   "profile", "distance (m)", "altitude (m)")
    img = cv2.imread(str(p))
    assert 300 <= img.shape[0] <= 700 and 600 <= img.shape[1] <= 1100, img.shape
    red = (img[:, :, 2] > 180) & (img[:, :, 1] < 80) & (img[:, :, 0] < 80)  # PALETTE[1] is red
    assert red.sum() > 200
    assert {"altitude", "terrain", "distance (m)", "altitude (m)", "profile"} <= set(texts[0])


def test_bar_chart_labels_values_and_missing_bars(tmp_path, monkeypatch):
    texts = _capture_figures(monkeypatch)
    b = bar_chart(tmp_path / "b.png", ["lap 1", "lap 2"], {"a": [1.0, 2.0], "b": [np.nan, 3.0]}, "bars", "m",
                  reference=[(2.5, "ref"), (1.5, "second", plots.GREY)])
    assert cv2.imread(str(b)) is not None
    assert {"1.0", "2.0", "3.0", "n/a", "lap 1", "lap 2", "ref", "second", "a", "b"} <= set(texts[0])


def test_the_service_import_path_never_loads_matplotlib():
    """`companion run` builds every subcommand's parser (importing demo, replay and plots) and
    then the daemon: none of that may import matplotlib, which the vehicle does not install."""
    code = ("import sys; from companion import cli; args = cli.build_parser().parse_args(['run', '--config', 'config/sitl.yaml']); "
            "import importlib; importlib.import_module(args._module); "
            "print('matplotlib' in sys.modules, 'companion.desk.plots' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**os.environ}).stdout.split()
    assert out == ["False", "True"], out


@pytest.mark.parametrize("command", [["demo", "--output", "out"], ["replay", "no-such-recording"]])
def test_a_desk_tool_without_matplotlib_says_how_to_install_it(tmp_path, command):
    """matplotlib hidden by a module that refuses to load: the desk tool exits 2 with one line,
    before its work."""
    blocker = tmp_path / "block"
    blocker.mkdir()
    (blocker / "matplotlib.py").write_text("raise ModuleNotFoundError(\"No module named 'matplotlib'\", name='matplotlib')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(blocker), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "companion.cli", *command], capture_output=True, text=True,
                          timeout=120, env=env, cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'companion[desk]'" in lines[0], proc.stderr

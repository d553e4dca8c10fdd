"""Frame admission: wrong format or size, blank frames, timestamps going backwards or repeating,
and long gaps are counted; admitted frames are grey uint8 of the configured size in time order."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.cameras.checks import CameraStats, FrameChecker, FrameFormatError, to_gray

W, H = 40, 30


def textured(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W), dtype=np.uint8)


def checker(**kw) -> FrameChecker:
    return FrameChecker(W, H, CameraStats(), name="test", nominal_period_s=0.1, **kw)


def test_to_gray_converts_colour_and_refuses_what_is_not_an_8_bit_image():
    bgr = np.random.default_rng(1).integers(0, 256, (H, W, 3), dtype=np.uint8)
    assert np.array_equal(to_gray(bgr), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    bgra = np.dstack([bgr, np.full((H, W), 255, np.uint8)])
    assert np.array_equal(to_gray(bgra), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    g = textured()
    assert to_gray(g) is g and np.array_equal(to_gray(g[:, :, None]), g)
    for bad, what in [
        (g.astype(np.uint16), "uint16"),
        (g.astype(np.float32), "float32"),
        (np.zeros((H, W, 2), np.uint8), "shape"),
        (np.zeros((H,), np.uint8), "shape"),
        ([[1, 2]], "list"),
    ]:
        with pytest.raises(FrameFormatError, match=what):
            to_gray(bad)


def test_each_kind_of_bad_frame_is_counted_and_good_ones_pass():
    c = checker()
    assert c.admit(textured(1), 1.0) is not None
    assert c.admit(textured(2).astype(np.uint16), 1.1) is None
    assert c.admit(np.zeros((H, W + 1), np.uint8), 1.2) is None
    assert c.admit(np.zeros((H, W), np.uint8), 1.3) is None  # black
    assert c.admit(np.full((H, W), 255, np.uint8), 1.4) is None  # white
    assert c.admit(np.full((H, W), 77, np.uint8), 1.5) is None  # flat grey
    assert c.admit(textured(3), 1.0) is None  # repeats the last admitted time
    assert c.admit(textured(4), 0.5) is None  # goes backwards
    assert c.admit(textured(5), float("nan")) is None
    assert c.admit(textured(6), 1.05) is not None
    s = c.stats
    assert (s.rejected_format, s.rejected_size, s.rejected_blank, s.rejected_time) == (1, 1, 3, 3)
    assert s.delivered == 2 and s.rejected == 8 and s.gaps == 0


def test_blank_check_threshold_and_switch():
    dim = (np.random.default_rng(0).integers(0, 3, (H, W))).astype(np.uint8)  # dark, noise of ~0.8 levels
    assert checker(blank_std_max=1.0).admit(dim, 1.0) is None
    assert checker(blank_std_max=0.5).admit(dim, 1.0) is not None
    assert checker(blank_std_max=0.0).admit(np.zeros((H, W), np.uint8), 1.0) is not None  # off


def test_long_gaps_are_counted_and_the_frame_kept():
    c = checker(gap_factor=3.0)  # nominal period 0.1 s
    times = [0.0, 0.1, 0.2, 0.45, 0.55, 1.0]
    assert all(c.admit(textured(i), t) is not None for i, t in enumerate(times))
    assert c.stats.gaps == 1 and c.stats.delivered == 6


@settings(deadline=None, max_examples=60)
@given(st.lists(st.floats(min_value=-5, max_value=5, allow_nan=False), min_size=1, max_size=40))
def test_admitted_times_strictly_increase_and_every_frame_is_accounted_for(times):
    c = checker()
    admitted = [t for i, t in enumerate(times) if c.admit(textured(i % 3), t) is not None]
    assert all(b > a for a, b in zip(admitted, admitted[1:]))
    assert c.stats.delivered + c.stats.rejected_time == len(times)
    assert admitted[0] == times[0]

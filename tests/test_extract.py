"""Depth-map clean-up at extraction (slwarp.neural.extract): the neighbourhood stack and the flying-pixel filter,
on hand-made depth maps."""
from types import SimpleNamespace

import numpy as np

from slwarp.neural.extract import flying_pixel_filter, neighbour_stack

CAMERA = SimpleNamespace(fx=500.0, fy=500.0)  # a pixel footprint of 1 mm at 500 mm


def test_neighbour_stack_holds_the_8_neighbours():
    d = np.arange(9, dtype=np.float32).reshape(3, 3)
    s = neighbour_stack(d)
    assert s.shape == (8, 3, 3)
    np.testing.assert_array_equal(np.sort(s[:, 1, 1]), [0, 1, 2, 3, 5, 6, 7, 8])
    assert np.isnan(s[:, 0, 0]).sum() == 5  # a corner has 3 neighbours inside the image


def test_flying_pixel_filter_drops_both_sides_of_a_jump_and_keeps_a_slope():
    d = np.full((6, 6), 500.0, np.float32)
    d[:, 3:] = 600.0  # a 100 mm jump: 100 footprints
    out = flying_pixel_filter(d, CAMERA, footprints=10.0)
    assert np.isnan(out[:, 2:4]).all()
    assert np.isfinite(out[:, :2]).all() and np.isfinite(out[:, 4:]).all()
    slope = 500.0 + 3.0 * np.arange(6, dtype=np.float32)[None, :].repeat(6, 0)  # 3 footprints per pixel
    np.testing.assert_array_equal(flying_pixel_filter(slope, CAMERA, footprints=10.0), slope)

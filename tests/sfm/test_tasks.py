"""What the camera-motion workers send back (omnipipe.sfm.tasks)."""

from __future__ import annotations

import numpy as np

from omnipipe.sfm.tasks import compact_gray


def test_compact_gray_is_the_smallest_exact_integer_type() -> None:
    rng = np.random.default_rng(4)
    eight = rng.integers(0, 256, (20, 30)).astype(np.float32)
    sixteen = rng.integers(0, 65536, (20, 30)).astype(np.float32)
    fractional = eight + np.float32(0.5)
    negative = eight - np.float32(300.0)
    for gray, dtype in ((eight, np.uint8), (sixteen, np.uint16), (fractional, np.float32), (negative, np.float32)):
        small = compact_gray(gray)
        assert small.dtype == dtype
        assert np.array_equal(small.astype(np.float32), gray)  # the same values back

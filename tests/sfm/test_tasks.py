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


def test_frame_gray_is_the_compact_grey_image_without_the_laser() -> None:
    from omnipipe.image import gray_without_laser
    from omnipipe.sfm.tasks import frame_gray

    rng = np.random.default_rng(5)
    rgb8 = rng.integers(0, 256, (20, 30, 3)).astype(np.uint8)
    rgb16 = rng.integers(0, 65536, (20, 30, 3)).astype(np.uint16)
    for image in (rgb8, rgb8[..., 0], rgb16, rgb16[..., 2]):
        for channel in ("red", "green", "blue", "none"):
            fast = frame_gray(image, channel)
            slow = compact_gray(gray_without_laser(image, channel))
            assert fast.dtype == slow.dtype and np.array_equal(fast, slow), (image.dtype, image.ndim, channel)

"""The wall texture's sampling on textures taller than cv2.remap takes."""

from __future__ import annotations

import numpy as np

from omnipipe.sim.texture import remap_samples


def test_banded_sampling_equals_one_remap() -> None:
    """Sampled band by band (as a long pipe's texture of more than 32k rows is), the
    bilinear samples equal those of one remap, at band edges and beyond the borders."""
    rng = np.random.default_rng(7)
    image = rng.random((230, 40, 3), dtype=np.float32)
    row = np.concatenate([rng.uniform(-3.0, 233.0, 2000), np.arange(0.0, 230.0, 0.25)])
    col = rng.uniform(-2.0, 41.0, len(row))
    whole = remap_samples(image, col, row)
    banded = remap_samples(image, col, row, max_rows=50)
    np.testing.assert_allclose(banded, whole, rtol=0, atol=1e-6)
    # An interior sample is the bilinear mix of its four neighbours.
    r, c = 100.25, 10.5
    expect = 0.75 * (0.5 * image[100, 10] + 0.5 * image[100, 11]) + 0.25 * (
        0.5 * image[101, 10] + 0.5 * image[101, 11]
    )
    np.testing.assert_allclose(remap_samples(image, [c], [r], max_rows=50)[0], expect, atol=1e-3)

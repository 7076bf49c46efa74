"""The compiled bump model of the defect sizing equals its NumPy reference, and its
analytic Jacobian equals central differences of that reference."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.analysis._kernels import seen_bump_with_jacobian
from omnipipe.analysis.sizing import seen_bump_model


@pytest.mark.parametrize("blur", [(0.0, 0.0), (0.8, 0.0), (0.0, 1.5), (0.8, 1.5)])
def test_bump_and_jacobian_equal_the_numpy_model(blur: tuple[float, float]) -> None:
    rng = np.random.default_rng(11)
    u = rng.uniform(-30.0, 30.0, 3000)
    z = rng.uniform(-40.0, 40.0, 3000)
    u[:5] = [0.0, 10.0, -10.0, 7.0, -7.0]  # the centre, half-height points, a ramp's start
    for params in (
        np.array([3.0, 1.0, -2.0, 20.0, 30.0, 0.4, 0.7, 0.1]),
        np.array([0.5, -3.0, 4.0, 6.0, 12.0, 1.0, 0.05, -0.2]),
        np.array([2.0, 0.0, 0.0, 14.0, 9.0, 0.05, 1.0, 0.0]),
    ):
        model, jac = seen_bump_with_jacobian(params, u, z, *blur)
        np.testing.assert_allclose(model, seen_bump_model(params, u, z, *blur), rtol=0, atol=1e-12)
        numeric = np.empty_like(jac)
        for k in range(len(params)):
            step = np.zeros(len(params))
            step[k] = 1e-6 * max(1.0, abs(params[k]))
            up = seen_bump_model(params + step, u, z, *blur)
            down = seen_bump_model(params - step, u, z, *blur)
            numeric[:, k] = (up - down) / (2.0 * step[k])
        # Central differences err by O(step^2 f''') and by the plateau's kinks in f''.
        np.testing.assert_allclose(jac, numeric, rtol=0, atol=2e-5 * max(1.0, float(np.abs(numeric).max())))

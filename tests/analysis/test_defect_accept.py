"""analysis.defect_accept.measured_only: a defect whose height its 1-sigma covers is a warning."""

from __future__ import annotations

import numpy as np

from omnipipe.analysis.defect_accept import measured_only
from omnipipe.contract import Defect


def test_a_defect_within_its_own_sigma_of_the_wall_is_a_warning_not_a_defect() -> None:
    """Seeded heights and sigmas: those with sigma >= height (a candidate shorter than
    the ring's blur, on a ring straddling a reducer's start) become warnings naming
    them; the others, and one without a sigma (its fit failed), are kept in order."""
    rng = np.random.default_rng(5)
    h = rng.uniform(1.0, 10.0, 12)
    s = h * rng.uniform(0.1, 2.0, 12)
    defects = [Defect("dent", float(a), 20.0, 3.4, 10.0 * i, 180.0, height_sigma_mm=float(b))
               for i, (a, b) in enumerate(zip(h, s, strict=True))]
    defects.append(Defect("bulge", 0.5, 20.0, 20.0, 500.0, 90.0))
    kept, warnings = measured_only(defects)
    assert kept == [d for d in defects if d.height_sigma_mm is None or d.height_sigma_mm < d.height_mm]
    dropped = [d for d in defects if d not in kept]
    assert len(dropped) == int(np.sum(s >= h)) >= 1 and len(warnings) == len(dropped)
    for d, w in zip(dropped, warnings, strict=True):
        assert f"at {d.axial_start_mm:.0f} mm" in w and "not measured" in w

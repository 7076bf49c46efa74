"""Baseline optimisation (paper Sec. IV, Eq. 6-9, Fig. 9): :mod:`.optimum`."""

from omnipipe.baseline.optimum import (
    BaselineConfig,
    BaselineResult,
    dr_dd,
    error_rate,
    image_radius,
    optimal_baseline,
    plot_fig9,
    quantisation_error_px,
    run,
)

__all__ = [
    "BaselineConfig",
    "BaselineResult",
    "dr_dd",
    "error_rate",
    "image_radius",
    "optimal_baseline",
    "plot_fig9",
    "quantisation_error_px",
    "run",
]

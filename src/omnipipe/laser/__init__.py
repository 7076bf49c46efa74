"""Light-section stage (paper Sec. III): metric laser-ring points of every frame.

Extraction (:mod:`~omnipipe.laser.extract`, sub-pixel peaks along radial lines), the
ring (:mod:`~omnipipe.laser.ring`), triangulation on the laser plane
(:mod:`~omnipipe.laser.triangulate`, Eq. 4-5) and the stage's ``run`` /
``run_dataset`` (:mod:`~omnipipe.laser.stage`).
"""

from omnipipe.laser.extract import ExtractionConfig, RingExtractor
from omnipipe.laser.ring import LaserRing
from omnipipe.laser.stage import (
    DecodeHandOn,
    LaserConfig,
    LaserResult,
    RingTask,
    decode_only,
    ring_extractor,
    run,
    run_dataset,
)
from omnipipe.laser.triangulate import (
    centroid_ring,
    intersect_plane,
    radial_mm_per_px,
    triangulate_ring,
)

__all__ = [
    "DecodeHandOn",
    "ExtractionConfig",
    "LaserConfig",
    "LaserResult",
    "LaserRing",
    "RingExtractor",
    "RingTask",
    "centroid_ring",
    "decode_only",
    "intersect_plane",
    "radial_mm_per_px",
    "ring_extractor",
    "run",
    "run_dataset",
    "triangulate_ring",
]

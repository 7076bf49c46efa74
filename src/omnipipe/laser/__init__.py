"""Light-section stage (paper Sec. III): metric laser-ring points of every frame.

``run(config, rig, frames)`` extracts each frame's laser ring with sub-pixel
Gaussian peak detection and intersects the rays with the calibrated laser plane.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from omnipipe.camera import camera_from_rig
from omnipipe.laser.extract import ExtractionConfig, LaserRing, RingExtractor
from omnipipe.laser.triangulate import intersect_plane, triangulate_ring
from omnipipe.rig import Rig


@dataclass(frozen=True)
class LaserConfig:
    """Light-section settings (see :class:`ExtractionConfig`)."""

    extraction: ExtractionConfig = field(default_factory=ExtractionConfig)


@dataclass
class LaserResult:
    """Rings of all frames, in frame order.

    Attributes:
        rings: one :class:`LaserRing` per frame (pixels, points_in_rig, sigma_mm, ...).
        warnings: per-frame problems, prefixed with the frame index.
    """

    rings: list[LaserRing]
    warnings: list[str]

    @property
    def recovered_fraction(self) -> np.ndarray:
        """(N,) fraction of scan lines with an accepted sample, per frame."""
        return np.array([r.fraction for r in self.rings])


def run(
    config: LaserConfig,
    rig: Rig,
    frames: Iterable[np.ndarray],
    progress: Callable[[int], None] | None = None,
) -> LaserResult:
    """Extract and triangulate the laser ring of every frame."""
    camera = camera_from_rig(rig)
    extractor = RingExtractor(camera, config.extraction)
    rings, warnings = [], []
    for i, frame in enumerate(frames):
        ring = triangulate_ring(extractor.extract(frame, rig.laser.channel), camera, rig.laser)
        warnings.extend(f"frame {i}: {w}" for w in ring.warnings)
        rings.append(ring)
        if progress:
            progress(i + 1)
    return LaserResult(rings, warnings)


__all__ = [
    "ExtractionConfig",
    "LaserConfig",
    "LaserResult",
    "LaserRing",
    "RingExtractor",
    "intersect_plane",
    "run",
]

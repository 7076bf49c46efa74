"""OCamCalib's calib_results.txt <-> the ``ocam`` camera model.

The file (OCamCalib toolbox, C export) holds, after ``#`` comment lines: the direct
polynomial (count, then a0 a1 ...), the inverse polynomial (count, then p0 p1 ...),
the centre "row column" (0-based, C convention), the affine "c d e", and the image
size "height width". Rows come first throughout; omnipipe's rig.yaml stores the centre
as cx = column, cy = row.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from omnipipe.errors import ConfigError
from omnipipe.rig import CameraIntrinsics, OcamParams, Rig

MAX_FILE_BYTES = 1_000_000


def _numbers(line: str, path: str, lineno: int) -> list[float]:
    try:
        values = [float(v) for v in line.split()]
    except ValueError:
        raise ConfigError(f"line {lineno}", f"expected numbers, got {line.strip()!r}", path) from None
    if not all(math.isfinite(v) for v in values):
        raise ConfigError(f"line {lineno}", "numbers must be finite", path)
    return values


def read_ocam(path: str | Path) -> tuple[CameraIntrinsics, OcamParams]:
    """Read calib_results.txt.

    Returns:
        (intrinsics, params): image size, centre (cx = column, cy = row) and the model.

    Raises:
        ConfigError: missing file, wrong layout (naming the line), impossible values.
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigError("calib_results", "file not found", str(p))
    if p.stat().st_size > MAX_FILE_BYTES:
        raise ConfigError("calib_results", "file too large for an OCamCalib result", str(p))
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        raise ConfigError("calib_results", "not a text file", str(p)) from None
    rows = [
        (i + 1, line)
        for i, line in enumerate(text.splitlines())
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if len(rows) < 5:
        raise ConfigError(
            "calib_results",
            f"expected 5 data lines (polynomial, inverse polynomial, centre, affine, size), "
            f"found {len(rows)}",
            str(p),
        )
    data = [(n, _numbers(line, str(p), n)) for n, line in rows[:5]]
    polys = []
    for (n, vals), what in zip(data[:2], ("polynomial", "inverse polynomial"), strict=True):
        if not vals or vals[0] != int(vals[0]) or int(vals[0]) != len(vals) - 1 or len(vals) < 3:
            raise ConfigError(
                f"line {n}", f"{what}: expected a count N then N coefficients", str(p)
            )
        polys.append(tuple(vals[1:]))
    (n_c, centre), (n_a, affine), (n_s, size) = data[2:]
    if len(centre) != 2:
        raise ConfigError(f"line {n_c}", "centre: expected 'row column'", str(p))
    if len(affine) != 3:
        raise ConfigError(f"line {n_a}", "affine: expected 'c d e'", str(p))
    if len(size) != 2 or any(v <= 0 or v != int(v) for v in size):
        raise ConfigError(f"line {n_s}", "image size: expected 'height width' in pixels", str(p))
    height, width = int(size[0]), int(size[1])
    if not polys[0][0] < 0:
        raise ConfigError(
            f"line {data[0][0]}", "polynomial: a0 must be < 0 (OCamCalib's convention)", str(p)
        )
    c, d, e = affine
    if abs(c - d * e) < 1e-9:
        raise ConfigError(f"line {n_a}", "affine matrix [[c, d], [e, 1]] is singular", str(p))
    row, col = centre
    intr = CameraIntrinsics(
        width=width, height=height, cx=col, cy=row, f=abs(polys[0][0])
    )
    return intr, OcamParams(polys[0], polys[1], c, d, e)


def write_ocam(intrinsics: CameraIntrinsics, params: OcamParams, path: str | Path) -> None:
    """Write calib_results.txt as OCamCalib does (rows first, 0-based centre)."""
    from omnipipe.camera.convert import ocam_inverse_polynomial

    inv = params.inverse_polynomial
    if inv is None:
        r_max = float(np.hypot(intrinsics.width, intrinsics.height)) / 2.0
        inv = tuple(ocam_inverse_polynomial(np.asarray(params.polynomial), r_max))

    def line(values: tuple[float, ...]) -> str:
        return f"{len(values)} " + " ".join(f"{v:.6e}" for v in values) + " \n"

    text = (
        "#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). "
        "These are used by cam2world\n\n"
        + line(tuple(params.polynomial))
        + "\n#polynomial coefficients for the inverse mapping function (ocam_model.invpol in "
        "MATLAB). These are used by world2cam\n\n"
        + f"{len(inv)} " + " ".join(f"{v:.6f}" for v in inv) + " \n"
        + '\n#center: "row" and "column", starting from 0 (C convention)\n\n'
        + f"{intrinsics.cy:.6f} {intrinsics.cx:.6f}\n"
        + '\n#affine parameters "c", "d", "e"\n\n'
        + f"{params.c:.6f} {params.d:.6f} {params.e:.6f}\n"
        + '\n#image size: "height" and "width"\n\n'
        + f"{intrinsics.height} {intrinsics.width}\n\n"
    )
    Path(path).write_text(text, encoding="utf-8")


def rig_from_ocam(
    path: str | Path,
    laser_from: Rig | None = None,
    radius_min: float | None = None,
    radius_max: float | None = None,
) -> Rig:
    """A rig (model ``ocam``) from calib_results.txt, with the laser of another rig or none.

    The laser plane is copied as is: it must already be in this camera's rig frame
    (a laser calibrated with this camera model, ``omnipipe calibrate laser``).
    """
    from dataclasses import replace

    intr, params = read_ocam(path)
    intr = replace(intr, radius_min=radius_min, radius_max=radius_max)
    laser = None if laser_from is None else laser_from.laser
    if laser_from is not None and (laser_from.camera.width, laser_from.camera.height) != (
        intr.width,
        intr.height,
    ):
        raise ConfigError(
            "--laser-from",
            f"its image is {laser_from.camera.width}x{laser_from.camera.height}, "
            f"calib_results.txt's {intr.width}x{intr.height}: not the same camera",
        )
    if laser_from is not None and laser is None:
        raise ConfigError("--laser-from", "that rig has no laser section")
    return Rig(camera=intr, mirror=None, laser=laser, model=params)

"""OCamCalib's calib_results.txt <-> the ``ocam`` camera model.

The file (OCamCalib toolbox, C export) holds, after ``#`` comment lines: the direct
polynomial (count, then a0 a1 ...), the inverse polynomial (count, then p0 p1 ...),
the centre "row column" (0-based, C convention), the affine "c d e", and the image
size "height width". Rows come first throughout; omnipipe's rig.yaml stores the centre
as cx = column, cy = row.

Two optional blocks may follow the image size, each after a comment line naming it
(as a rig's owner adds them beside the toolbox's own blocks; :func:`write_ocam` writes
them so):

* ``#ROI radii: "radius_min" and "radius_max" in pixels`` then ``R_MIN R_MAX``: the
  valid annulus (blind centre, mirror rim) around the centre; kept as the rig's
  ``radius_min`` / ``radius_max``.
* ``#crop: "row" "column" of the top-left corner, "height" "width"`` then
  ``ROW COL HEIGHT WIDTH``: the recorded frames are this window of the calibration
  image. The rig then has the crop's size and the centre shifted into it (the model's
  polynomials depend only on the distance from the centre, so nothing else changes).

Any other data line after the image size is refused, naming it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from omnipipe.errors import ConfigError
from omnipipe.rig import CameraIntrinsics, OcamParams, Rig

MAX_FILE_BYTES = 1_000_000


@dataclass(frozen=True)
class OcamCrop:
    """The window of the calibration image that the recorded frames are (px, 0-based).

    Attributes:
        row, col: top-left corner in the calibration image.
        height, width: size of the frames.
    """

    row: int
    col: int
    height: int
    width: int


def apply_crop(intrinsics: CameraIntrinsics, crop: OcamCrop | None) -> CameraIntrinsics:
    """The camera of the cropped frames: the crop's size, the centre moved into it."""
    if crop is None:
        return intrinsics
    return replace(
        intrinsics, width=crop.width, height=crop.height,
        cx=intrinsics.cx - crop.col, cy=intrinsics.cy - crop.row,
    )


def _numbers(line: str, path: str, lineno: int) -> list[float]:
    try:
        values = [float(v) for v in line.split()]
    except ValueError:
        raise ConfigError(f"line {lineno}", f"expected numbers, got {line.strip()!r}", path) from None
    if not all(math.isfinite(v) for v in values):
        raise ConfigError(f"line {lineno}", "numbers must be finite", path)
    return values


def read_ocam(path: str | Path) -> tuple[CameraIntrinsics, OcamParams]:
    """Read calib_results.txt: the camera of the recorded frames (the crop applied).

    Returns:
        (intrinsics, params): image size, centre (cx = column, cy = row), the ROI radii
        (None when the file has none) and the model.

    Raises:
        ConfigError: missing file, wrong layout (naming the line), impossible values.
    """
    intr, params, crop = read_ocam_file(path)
    return apply_crop(intr, crop), params


def _data_lines(p: Path) -> list[tuple[int, str, str]]:
    """(line number, data line, the comment line before it) of calib_results.txt."""
    if not p.is_file():
        raise ConfigError("calib_results", "file not found", str(p))
    if p.stat().st_size > MAX_FILE_BYTES:
        raise ConfigError("calib_results", "file too large for an OCamCalib result", str(p))
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        raise ConfigError("calib_results", "not a text file", str(p)) from None
    rows, comment = [], ""
    for i, line in enumerate(text.splitlines()):
        if line.lstrip().startswith("#"):
            comment = line.lower()
        elif line.strip():
            rows.append((i + 1, line, comment))
    return rows


def read_ocam_file(path: str | Path) -> tuple[CameraIntrinsics, OcamParams, OcamCrop | None]:
    """Read calib_results.txt as it is: the calibration image's camera (with the ROI
    radii) and the crop, if the file has one (module docstring).

    Raises:
        ConfigError: missing file, wrong layout (naming the line), impossible values.
    """
    p = Path(path)
    rows = _data_lines(p)
    if len(rows) < 5:
        raise ConfigError(
            "calib_results",
            f"expected 5 data lines (polynomial, inverse polynomial, centre, affine, size), "
            f"found {len(rows)}",
            str(p),
        )
    data = [(n, _numbers(line, str(p), n)) for n, line, _ in rows[:5]]
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
    radii, crop = _extras(rows[5:], str(p), (height, width))
    intr = CameraIntrinsics(
        width=width, height=height, cx=col, cy=row, f=abs(polys[0][0]),
        radius_min=radii[0], radius_max=radii[1],
    )
    return intr, OcamParams(polys[0], polys[1], c, d, e), crop


def _extras(
    rows: list[tuple[int, str, str]], path: str, size: tuple[int, int]
) -> tuple[tuple[float | None, float | None], OcamCrop | None]:
    """The optional ROI radii and crop blocks after the image size (module docstring)."""
    radii: tuple[float | None, float | None] = (None, None)
    crop = None
    for n, line, comment in rows:
        vals = _numbers(line, path, n)
        if "crop" in comment:
            if len(vals) != 4 or any(v != int(v) for v in vals) or vals[0] < 0 or vals[1] < 0 \
                    or vals[2] <= 0 or vals[3] <= 0:
                raise ConfigError(f"line {n}", "crop: expected 'row column height width' (px)", path)
            r0, c0, h, w = (int(v) for v in vals)
            if r0 + h > size[0] or c0 + w > size[1]:
                raise ConfigError(
                    f"line {n}", f"crop {h}x{w} at ({r0}, {c0}) leaves the {size[0]}x{size[1]} image",
                    path,
                )
            crop = OcamCrop(r0, c0, h, w)
        elif "roi" in comment or "radi" in comment:
            if len(vals) != 2 or not 0 <= vals[0] < vals[1]:
                raise ConfigError(
                    f"line {n}", "ROI radii: expected 'radius_min radius_max' (px, min < max)", path
                )
            radii = (vals[0], vals[1])
        else:
            raise ConfigError(
                f"line {n}",
                "unexpected data after the image size (known blocks: '#ROI radii', '#crop')",
                path,
            )
    return radii, crop


def write_ocam(
    intrinsics: CameraIntrinsics,
    params: OcamParams,
    path: str | Path,
    crop: OcamCrop | None = None,
) -> None:
    """Write calib_results.txt as OCamCalib does (rows first, 0-based centre), plus the
    ROI radii block when ``intrinsics`` has both radii and the crop block with ``crop``
    (``intrinsics`` are then the calibration image's, :func:`read_ocam_file`)."""
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
    if intrinsics.radius_min is not None and intrinsics.radius_max is not None:
        text += (
            '#ROI radii: "radius_min" and "radius_max" in pixels (valid annulus)\n\n'
            + f"{intrinsics.radius_min:.6f} {intrinsics.radius_max:.6f}\n\n"
        )
    if crop is not None:
        text += (
            '#crop: "row" "column" of the top-left corner, "height" "width" of the frames\n\n'
            + f"{crop.row} {crop.col} {crop.height} {crop.width}\n\n"
        )
    Path(path).write_text(text, encoding="utf-8")


def rig_from_ocam(
    path: str | Path,
    laser_from: Rig | None = None,
    radius_min: float | None = None,
    radius_max: float | None = None,
) -> Rig:
    """A rig (model ``ocam``) of the recorded frames (the file's crop applied) from
    calib_results.txt, with the laser of another rig or none.

    ``radius_min`` / ``radius_max`` replace the file's ROI radii when given. The laser
    plane is copied as is: it is in mm in the rig frame, which does not depend on the
    image size, so ``laser_from`` may be a rig of another size (e.g. a full-frame
    calibration of the same camera and mirror, whose laser ``omnipipe calibrate laser``
    found); it must be of the same camera, mirror and laser.
    """
    intr, params = read_ocam(path)
    intr = replace(
        intr,
        radius_min=intr.radius_min if radius_min is None else radius_min,
        radius_max=intr.radius_max if radius_max is None else radius_max,
    )
    if laser_from is not None and laser_from.laser is None:
        raise ConfigError("--laser-from", "that rig has no laser section")
    laser = None if laser_from is None else laser_from.laser
    return Rig(camera=intr, mirror=None, laser=laser, model=params)

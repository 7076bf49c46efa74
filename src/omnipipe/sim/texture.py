"""Procedural wall texture (albedo) of a simulated pipe, deterministic from a seed.

The texture lives on the unrolled wall: rows are arc length along the centreline
(mm), columns the arc length around the nominal circumference (mm), periodic. It
mixes what a corroded steel or cast-iron pipe shows: mill-scale grey, rust
patches, stains, pits, scratches, a longitudinal weld seam and girth welds. The
renderer samples it through a mip-map pyramid chosen from each pixel's footprint,
so fine texture never aliases.

Besides that default ``steel`` family, ``TextureConfig.family`` selects other walls
(randomised scenarios, docs/simulator.md): ``brick`` (running bond with mortar
joints), ``tiles`` (square glazed tiles with grout), ``joints`` (concrete or plastic
pipe sections with circumferential joints, or corrugated metal), ``smooth`` (low
contrast plastic or lined wall), ``photo`` (aperiodic, with a natural photograph's
1/f^2 spectrum and edges at every scale: weathered concrete, scale, deposits); any family can carry extra ``stains`` and a
reduced ``contrast``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft as sfft

from omnipipe.errors import ConfigError

TEXTURE_FAMILIES = ("steel", "brick", "tiles", "joints", "smooth", "photo")


@dataclass(frozen=True)
class TextureConfig:
    """Procedural texture knobs.

    Attributes:
        texel_mm: texture sample spacing on the wall (mm).
        family: "steel" (the knobs below), "brick", "tiles", "joints", "smooth" or "photo".
        rust_cover: fraction of the wall covered by rust (0..1).
        pit_density_per_cm2: small dark pits per square centimetre.
        girth_weld_spacing_mm: distance between circumferential welds (0: none).
        seam_angle_deg: angle of the longitudinal weld seam (None: no seam).
        period_mm: brick: brick length; tiles: tile size; joints: joint spacing (mm).
        course_mm: brick: course height (mm).
        joint_mm: width of mortar joints, grout lines or pipe joints (mm).
        variant: brick: "along" (long side along the axis, courses around it) or
            "around" (courses are rings along the axis); tiles: "grid", "offset" or
            "mosaic" (a grid of small tiles of several glaze colours);
            joints: "concrete", "plastic" or "corrugated"; smooth: "pvc" or "lined".
        base_rgb: main colour of bricks, tiles or wall (None: the family's default).
        contrast: scales the albedo's deviation from its mean (1: as generated).
        stain_strength: extra dark stains and deposits (0: none .. 1: strong).
    """

    texel_mm: float = 0.25
    rust_cover: float = 0.35
    pit_density_per_cm2: float = 0.6
    girth_weld_spacing_mm: float = 600.0
    seam_angle_deg: float | None = 250.0
    family: str = "steel"
    period_mm: float = 0.0
    course_mm: float = 0.0
    joint_mm: float = 0.0
    variant: str = ""
    base_rgb: tuple[float, float, float] | None = None
    contrast: float = 1.0
    stain_strength: float = 0.0

    def __post_init__(self) -> None:
        if self.family not in TEXTURE_FAMILIES:
            raise ConfigError(
                "texture.family",
                f"must be one of {', '.join(TEXTURE_FAMILIES)}, got {self.family!r}",
            )
        if self.family in ("brick", "tiles", "joints") and not self.period_mm > 0:
            raise ConfigError("texture.period_mm", f"must be > 0 for {self.family}")
        if self.family == "brick" and not self.course_mm > 0:
            raise ConfigError("texture.course_mm", "must be > 0 for brick")
        if not self.contrast >= 0:
            raise ConfigError("texture.contrast", f"must be >= 0, got {self.contrast}")

    @property
    def axial_period_mm(self) -> float | None:
        """Period of the pattern along the pipe axis (mm), None for aperiodic walls."""
        if self.family == "brick":
            return self.period_mm if self.variant != "around" else self.course_mm
        if self.family in ("tiles", "joints"):
            return self.period_mm
        return None


def fractal_noise(
    shape: tuple[int, int],
    rng: np.random.Generator,
    beta: float,
    cutoff: float = 0.0,
    coarse: int = 1,
) -> np.ndarray:
    """Periodic 1/f^beta noise of ``shape``, zero mean, unit standard deviation.

    ``cutoff`` (cycles per sample) removes frequencies below it (large-scale trends).
    ``coarse`` > 1 synthesises at 1/coarse resolution and upsamples (cubic, wrapping
    around the columns): for smooth fields (beta >= 2) this loses nothing visible.
    """
    if coarse > 1:
        small = (max(8, -(-shape[0] // coarse)), max(8, -(-shape[1] // coarse)))
        low = fractal_noise(small, rng, beta, cutoff * coarse)
        pad = 3
        low = cv2.copyMakeBorder(low, pad, pad, pad, pad, cv2.BORDER_WRAP)
        up = cv2.resize(low, None, fx=coarse, fy=coarse, interpolation=cv2.INTER_CUBIC)
        off = pad * coarse
        up = up[off : off + shape[0], off : off + shape[1]]
        sx = small[1] * coarse / shape[1]
        if abs(sx - 1.0) > 1e-9:  # make the column period exact
            up = cv2.resize(up, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
        return (up - up.mean()) / max(float(up.std()), 1e-12)
    white = rng.standard_normal(shape).astype(np.float32)
    spec = sfft.rfft2(white, workers=1)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    freq = np.sqrt(fx * fx + fy * fy)
    freq[0, 0] = 1.0
    filt = freq ** (-beta / 2.0)
    filt[0, 0] = 0.0
    if cutoff > 0:
        filt[freq < cutoff] = 0.0
    field = sfft.irfft2(spec * filt.astype(np.float32), s=shape, workers=1).astype(np.float32)
    field -= field.mean()
    std = field.std()
    return field / std if std > 0 else field


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


class WallTexture:
    """Albedo texture of the pipe wall with a mip-map pyramid.

    Args:
        circumference_mm: nominal inner circumference (mm), the period of columns.
        sigma_range_mm: (start, end) arc length along the centreline covered (mm).
        seed: random seed; the same seed gives the same texture.
        config: texture knobs.
    """

    def __init__(
        self,
        circumference_mm: float,
        sigma_range_mm: tuple[float, float],
        seed: int,
        config: TextureConfig | None = None,
    ) -> None:
        self.config = config or TextureConfig()
        self.texel_mm = self.config.texel_mm
        self.sigma0 = float(sigma_range_mm[0])
        width = int(math.ceil(circumference_mm / self.texel_mm))
        self.width = width - width % 2
        self.texel_circ_mm = circumference_mm / self.width  # exact period
        height = int(math.ceil((sigma_range_mm[1] - sigma_range_mm[0]) / self.texel_mm)) + 1
        self.height = height + height % 2
        rng = np.random.default_rng(seed)
        self.albedo = self._generate(rng)
        self.levels = self._pyramid(self.albedo)
        # Each level padded by wrapped columns, so bilinear lookups wrap around the pipe.
        self._padded = [cv2.copyMakeBorder(lv, 0, 0, 2, 2, cv2.BORDER_WRAP) for lv in self.levels]

    # -- generation -------------------------------------------------------------------
    def _generate(self, rng: np.random.Generator) -> np.ndarray:
        cfg = self.config
        if cfg.family == "steel":
            img = self._steel(rng)
        else:
            rows = self.sigma0 + np.arange(self.height, dtype=np.float32) * self.texel_mm
            cols = np.arange(self.width, dtype=np.float32) * np.float32(self.texel_circ_mm)
            gen = {
                "brick": self._brick,
                "tiles": self._tiles,
                "joints": self._joints,
                "smooth": self._smooth,
                "photo": self._photo,
            }[cfg.family]
            img = gen(rng, rows, cols)
        if cfg.stain_strength > 0:
            img = self._stains(img, rng, cfg.stain_strength)
        if cfg.contrast != 1.0:
            mean = img.reshape(-1, 3).mean(axis=0)
            img = mean + cfg.contrast * (img - mean)
        if cfg.family != "steel" or cfg.stain_strength > 0 or cfg.contrast != 1.0:
            img = np.clip(img, 0.03, 0.95).astype(np.float32)
        return img

    def _steel(self, rng: np.random.Generator) -> np.ndarray:
        """Mill scale, rust, pits, scratches, seam and girth welds (the default wall)."""
        cfg = self.config
        shape = (self.height, self.width)
        tex = self.texel_mm
        # Large-scale stains and tone variation (features of ~20-100 mm).
        stains = fractal_noise(shape, rng, beta=3.2, cutoff=tex / 400.0, coarse=8)
        tone = fractal_noise(shape, rng, beta=2.4, coarse=4)
        grain = fractal_noise(shape, rng, beta=0.8)
        base = np.array([0.42, 0.40, 0.37], np.float32)
        img = base[None, None, :] * (1.0 + 0.18 * tone[..., None] + 0.05 * grain[..., None])
        img *= (1.0 - 0.25 * _smoothstep(stains, 0.3, 1.6))[..., None]
        # Rust: patches from a thresholded fractal field, with their own detail.
        rust_field = fractal_noise(shape, rng, beta=2.6, coarse=4)
        thresh = float(np.quantile(rust_field, 1.0 - cfg.rust_cover))
        rust_mask = _smoothstep(rust_field, thresh - 0.15, thresh + 0.25)
        rust_detail = fractal_noise(shape, rng, beta=1.6, coarse=2)
        rust_col = np.array([0.58, 0.31, 0.14], np.float32)
        dark_rust = np.array([0.30, 0.15, 0.08], np.float32)
        mix = _smoothstep(rust_detail, -1.0, 1.2)[..., None]
        rust = rust_col * mix + dark_rust * (1.0 - mix)
        img = img * (1.0 - rust_mask[..., None]) + rust * rust_mask[..., None]
        # Pits: small dark round spots with a slightly bright rim (blob features).
        area_cm2 = self.height * self.width * tex * tex / 100.0
        n_pits = rng.poisson(cfg.pit_density_per_cm2 * area_cm2)
        pits = np.zeros(shape, np.float32)
        rims = np.zeros(shape, np.float32)
        ys = rng.uniform(0, self.height, n_pits)
        xs = rng.uniform(0, self.width, n_pits)
        rs = rng.uniform(0.4, 2.2, n_pits) / tex
        depth = rng.uniform(0.3, 0.8, n_pits)
        for y, x, r, dpt in zip(ys, xs, rs, depth, strict=True):
            for dx in (0.0, -self.width, self.width):
                c = (int(round((x + dx) * 4)), int(round(y * 4)))
                cv2.circle(rims, c, int(round(r * 1.5 * 4)), 0.15, -1, cv2.LINE_AA, shift=2)
                cv2.circle(pits, c, int(round(r * 4)), float(dpt), -1, cv2.LINE_AA, shift=2)
        pits = cv2.GaussianBlur(pits, (0, 0), 0.6)
        img *= (1.0 + rims - pits)[..., None].clip(0.1, 2.0)
        # Scratches: thin short lines in random directions.
        scratches = np.zeros(shape, np.float32)
        n_scr = rng.poisson(0.02 * area_cm2)
        for _ in range(n_scr):
            x0, y0 = rng.uniform(0, self.width), rng.uniform(0, self.height)
            ang = rng.uniform(0, math.pi)
            length = rng.uniform(5, 40) / tex
            x1, y1 = x0 + length * math.cos(ang), y0 + length * math.sin(ang)
            cv2.line(
                scratches,
                (int(x0), int(y0)),
                (int(x1), int(y1)),
                rng.uniform(0.1, 0.3),
                1,
                cv2.LINE_AA,
            )
        img *= (1.0 + scratches)[..., None]
        # Welds: a longitudinal seam and girth welds (bright rippled beads, dark toes).
        rows = self.sigma0 + np.arange(self.height) * tex
        cols = np.arange(self.width) * self.texel_circ_mm
        if cfg.seam_angle_deg is not None:
            seam_c = math.radians(cfg.seam_angle_deg) % (2 * math.pi) * self.width / (2 * math.pi)
            dist = np.abs(
                ((np.arange(self.width) - seam_c + self.width / 2) % self.width) - self.width / 2
            )
            bead = np.exp(-0.5 * (dist * tex / 2.5) ** 2)[None, :]
            ripple = 0.5 + 0.5 * np.sin(rows * 2 * math.pi / 1.8)[:, None]
            img *= (
                1.0
                + (0.25 + 0.15 * ripple) * bead
                - 0.3 * np.exp(-0.5 * ((dist * tex - 4) / 0.7) ** 2)[None, :]
            )[..., None]
        if cfg.girth_weld_spacing_mm > 0:
            phase = (rows % cfg.girth_weld_spacing_mm) - 0.5 * cfg.girth_weld_spacing_mm
            bead = np.exp(-0.5 * (phase / 3.0) ** 2)[:, None]
            ripple = 0.5 + 0.5 * np.sin(cols * 2 * math.pi / 2.0)[None, :]
            img *= (1.0 + (0.2 + 0.15 * ripple) * bead)[..., None]
        return np.clip(img, 0.03, 0.95).astype(np.float32)

    # -- other wall families (randomised scenarios) ------------------------------------
    def _noise(self, rng: np.random.Generator, beta: float, coarse: int = 1) -> np.ndarray:
        return fractal_noise((self.height, self.width), rng, beta=beta, coarse=coarse)

    def _brick(self, rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Running bond: bricks offset by half a brick from course to course, mortar joints.

        "along": bricks' long side along the axis (axial period = brick length), courses
        around the circumference; "around": courses are rings (axial period = course height).
        Brick counts around the pipe are whole, so the pattern wraps seamlessly.
        """
        cfg = self.config
        circ = self.width * self.texel_circ_mm
        length, course_h, joint = cfg.period_mm, cfg.course_mm, cfg.joint_mm
        u_axis = rows - self.sigma0 + np.float32(rng.uniform(0.0, 2.0 * length))
        if cfg.variant != "around":
            n_c = max(3, round(circ / course_h))
            h_eff = circ / n_c
            course = np.floor(cols / h_eff).astype(np.int64)  # (W,)
            v = cols - course * h_eff
            u = u_axis[:, None] + ((course % 2) * 0.5 * length)[None, :].astype(np.float32)
            brick = np.floor(u / length)
            uu = u - brick * length
            d_bed = np.minimum(v, h_eff - v)[None, :]
            d_head = np.minimum(uu, length - uu)
            course_id = np.broadcast_to(course[None, :], u.shape)
            brick_id = brick.astype(np.int64)
            n_rows, n_cols = n_c, int(brick_id.max()) + 1
            ids = (course_id, brick_id)
        else:
            n_b = max(3, round(circ / length))
            l_eff = circ / n_b
            course = np.floor(u_axis / course_h).astype(np.int64)  # (H,)
            v = u_axis - course * course_h
            u = cols[None, :] + ((course % 2) * 0.5 * l_eff)[:, None].astype(np.float32)
            brick = np.floor(u / l_eff)
            uu = u - brick * l_eff
            d_bed = np.minimum(v, course_h - v)[:, None]
            d_head = np.minimum(uu, l_eff - uu)
            brick_id = brick.astype(np.int64) % n_b
            course_id = np.broadcast_to(course[:, None], u.shape)
            n_rows, n_cols = int(course.max()) + 1, n_b
            ids = (course_id, brick_id)
        del u, brick, uu
        # Chipped, irregular brick edges; each brick its own shade and hue.
        dist = np.minimum(d_bed, d_head)
        del d_head
        dist += 0.7 * self._noise(rng, 1.8, coarse=2)
        shade = 1.0 + 0.13 * rng.standard_normal((n_rows, n_cols, 1))
        hue = 1.0 + 0.05 * rng.standard_normal((n_rows, n_cols, 3))
        base = np.array(cfg.base_rgb or (0.55, 0.27, 0.18), np.float32)
        img = (base * shade * hue).astype(np.float32)[ids]
        del ids, brick_id
        grain = self._noise(rng, 0.8)
        surface = 1.0 + 0.10 * self._noise(rng, 2.2, coarse=4) + 0.06 * grain
        surface *= 1.0 - 0.15 * (1.0 - _smoothstep(dist, 0.5 * joint, 0.5 * joint + 3.0))
        mortar_rgb = np.array(
            (0.62, 0.60, 0.55) if rng.uniform() < 0.6 else (0.30, 0.29, 0.27), np.float32
        )
        m = 1.0 - _smoothstep(dist, 0.5 * joint - 0.4, 0.5 * joint + 0.4)
        surface *= 1.0 - m
        img *= surface[..., None]
        del surface
        # Mortar, recessed: darker towards the brick edges.
        m *= 1.0 - 0.35 * _smoothstep(dist, 0.15 * joint, 0.5 * joint)
        m *= 1.0 + 0.12 * grain
        img += mortar_rgb * m[..., None]
        return img

    def _tiles(self, rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Square glazed tiles (a whole number around the pipe) with grout lines."""
        cfg = self.config
        circ = self.width * self.texel_circ_mm
        size, grout = cfg.period_mm, cfg.joint_mm
        n_a = max(3, round(circ / size))
        s_c = circ / n_a
        u = rows - self.sigma0 + np.float32(rng.uniform(0.0, 2.0 * size))
        row_id = np.floor(u / size).astype(np.int64)  # (H,)
        ua = u - row_id * size
        d_ax = np.minimum(ua, size - ua)[:, None]
        shift = (row_id % 2) * 0.5 * s_c if cfg.variant == "offset" else np.zeros_like(row_id)
        w = cols[None, :] + shift[:, None].astype(np.float32)
        col_f = np.floor(w / s_c)
        wa = w - col_f * s_c
        d_circ = np.minimum(wa, s_c - wa)
        dist = np.minimum(d_ax, d_circ) + 0.15 * self._noise(rng, 1.5, coarse=2)
        n_rows = int(row_id.max()) + 1
        if cfg.variant == "mosaic":  # each tile one of a few glazes, +-10 % in tone
            shade = self._mosaic_shades(rng, n_rows, n_a)
        else:
            shade = 1.0 + 0.04 * rng.standard_normal((n_rows, n_a, 1))
        base = np.array(cfg.base_rgb or (0.78, 0.76, 0.70), np.float32)
        colour = (base * shade).astype(np.float32)[
            np.broadcast_to(row_id[:, None], w.shape), col_f.astype(np.int64) % n_a
        ]
        glaze = 1.0 + 0.03 * self._noise(rng, 2.0, coarse=4) + 0.02 * self._noise(rng, 0.8)
        tiles = colour * glaze[..., None]
        grout_rgb = np.array(
            (0.50, 0.49, 0.46) if rng.uniform() < 0.5 else (0.26, 0.25, 0.23), np.float32
        )
        grout_img = grout_rgb * (1.0 + 0.10 * self._noise(rng, 0.8))[..., None]
        m = (1.0 - _smoothstep(dist, 0.5 * grout - 0.3, 0.5 * grout + 0.3))[..., None]
        return (tiles * (1.0 - m) + grout_img * m).astype(np.float32)

    @staticmethod
    def _mosaic_shades(rng: np.random.Generator, n_rows: int, n_cols: int) -> np.ndarray:
        """(n_rows, n_cols, 3) colour factors of mosaic tiles: 2-4 glazes mixed at random."""
        n_glaze = int(rng.integers(2, 5))
        glazes = 1.0 + 0.25 * rng.uniform(-1.0, 1.0, (n_glaze, 3))
        pick = rng.integers(0, n_glaze, (n_rows, n_cols))
        tone = 1.0 + 0.10 * rng.uniform(-1.0, 1.0, (n_rows, n_cols, 1))
        return glazes[pick] * tone

    def _photo(self, rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """An aperiodic wall with a photograph's statistics: colour fields with a 1/f^2
        power spectrum, and patches (scale, deposits, spalls) cut out of further 1/f^2
        fields, so edges of every size and contrast appear, as on weathered concrete."""
        cfg = self.config
        base = np.array(cfg.base_rgb or (0.50, 0.48, 0.44), np.float32)
        lum = self._noise(rng, 2.0, coarse=2)
        tint = np.stack([self._noise(rng, 2.4, coarse=4) for _ in range(3)], axis=-1)
        img = base * (1.0 + 0.22 * lum[..., None] + 0.05 * tint)
        for level, colour in ((0.8, (0.30, 0.26, 0.20)), (1.3, (0.70, 0.68, 0.62))):
            field_ = self._noise(rng, 2.0, coarse=2) + 0.3 * self._noise(rng, 1.0)
            mask = _smoothstep(field_, level, level + 0.08)[..., None]
            detail = 1.0 + 0.15 * self._noise(rng, 1.2)[..., None]
            img = img * (1.0 - mask) + np.array(colour, np.float32) * detail * mask
        img *= (1.0 + 0.05 * self._noise(rng, 0.8))[..., None]  # fine grain
        return img.astype(np.float32)

    def _joints(self, rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Pipe sections with circumferential joints every ``period_mm`` (concrete, plastic)
        or a corrugated metal pipe (shading of the corrugation, period ``period_mm``)."""
        cfg = self.config
        period, joint = cfg.period_mm, cfg.joint_mm
        u = rows - self.sigma0 + np.float32(rng.uniform(0.0, period))
        pos = u - np.floor(u / period) * period  # (H,) position within a section
        d = np.minimum(pos, period - pos)[:, None]  # distance to the nearest joint
        variant = cfg.variant or "concrete"
        if variant == "corrugated":
            base = np.array(cfg.base_rgb or (0.55, 0.56, 0.57), np.float32)
            spangle = 1.0 + 0.08 * self._noise(rng, 0.8) + 0.08 * self._noise(rng, 2.4, coarse=4)
            wave = (1.0 + 0.35 * np.cos(2.0 * math.pi * pos / period)).astype(np.float32)
            return (base * (spangle * wave[:, None])[..., None]).astype(np.float32)
        if variant == "plastic":
            base = np.array(cfg.base_rgb or (0.72, 0.45, 0.22), np.float32)
            streaks = fractal_noise((8, self.width), rng, beta=1.5)
            streaks = cv2.resize(streaks, (self.width, 1), interpolation=cv2.INTER_AREA)
            body = 1.0 + 0.04 * self._noise(rng, 2.4, coarse=4) + 0.03 * streaks
            socket = (pos < 0.25 * period)[:, None] * np.float32(0.06)
            wall = base * (body + socket)[..., None]
        else:
            base = np.array(cfg.base_rgb or (0.50, 0.49, 0.46), np.float32)
            aggregate = 0.08 * self._noise(rng, 1.0) + 0.08 * self._noise(rng, 2.5, coarse=4)
            pores = _smoothstep(self._noise(rng, 0.3), 2.4, 3.2)
            wall = base * (1.0 + aggregate - 0.5 * pores)[..., None]
        gap = 1.0 - _smoothstep(d, 0.5 * joint - 0.4, 0.5 * joint + 0.4)
        chamfer = _smoothstep(d, 0.5 * joint, 0.5 * joint + 2.0) * (
            1.0 - _smoothstep(d, 0.5 * joint + 2.0, 0.5 * joint + 5.0)
        )
        shade = 1.0 - 0.75 * gap + 0.12 * chamfer
        return (wall * shade[..., None]).astype(np.float32)

    def _smooth(self, rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """A smooth wall (plastic, epoxy lining): gentle tone and fine grain; the scenario's
        ``contrast`` makes it low contrast."""
        cfg = self.config
        base = np.array(cfg.base_rgb or (0.60, 0.58, 0.55), np.float32)
        tone = self._noise(rng, 2.6, coarse=4)
        grain = self._noise(rng, 0.9)
        shade = 1.0 + 0.15 * tone + 0.06 * grain
        if cfg.variant == "pvc":  # extrusion streaks along the pipe
            streaks = fractal_noise((8, self.width), rng, beta=1.2)
            shade = shade + 0.08 * cv2.resize(streaks, (self.width, 1), interpolation=cv2.INTER_AREA)
        return (base * shade[..., None]).astype(np.float32)

    def _stains(self, img: np.ndarray, rng: np.random.Generator, strength: float) -> np.ndarray:
        """Dark patchy deposits and a sediment band along the invert (a random angle)."""
        field_ = self._noise(rng, 3.0, coarse=8)
        patches = _smoothstep(field_, 0.3, 1.8)
        angle = rng.uniform(0.0, 2.0 * math.pi)
        theta = np.arange(self.width, dtype=np.float32) * (2.0 * math.pi / self.width)
        dth = np.mod(theta - angle + math.pi, 2.0 * math.pi) - math.pi
        band = np.exp(-0.5 * (dth / 0.35) ** 2)[None, :] * _smoothstep(
            self._noise(rng, 2.4, coarse=4), -0.8, 0.8
        )
        mask = (np.clip(patches + band, 0.0, 1.0) * min(strength, 1.0))[..., None]
        tint = np.array([0.22, 0.17, 0.10], np.float32)
        return (img * (1.0 - mask) + tint * mask).astype(np.float32)

    @staticmethod
    def _pyramid(img: np.ndarray, levels: int = 6) -> list[np.ndarray]:
        out = [img]
        for _ in range(levels - 1):
            prev = out[-1]
            if min(prev.shape[:2]) < 8:
                break
            out.append(
                cv2.resize(
                    prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA
                )
            )
        return out

    # -- sampling ---------------------------------------------------------------------
    def sample(
        self, sigma_mm: np.ndarray, theta_rad: np.ndarray, footprint_mm: np.ndarray
    ) -> np.ndarray:
        """Albedo (M, 3) at wall coordinates, filtered to a footprint (mm per pixel)."""
        col = (np.mod(theta_rad, 2 * math.pi) * (self.width / (2 * math.pi))).astype(np.float32)
        row = ((np.asarray(sigma_mm) - self.sigma0) / self.texel_mm).astype(np.float32)
        level = np.log2(np.maximum(np.asarray(footprint_mm, np.float32), 1e-6) / self.texel_mm)
        level = np.clip(level, 0.0, len(self.levels) - 1.0)
        lo = np.floor(level).astype(int)
        frac = (level - lo).astype(np.float32)
        out = np.zeros((len(col), 3), np.float32)
        for k in range(len(self.levels)):
            sel_lo = lo == k
            sel_hi = (lo == k - 1) & (frac > 0)
            sel = sel_lo | sel_hi
            if not sel.any():
                continue
            vals = self._sample_level(k, col[sel], row[sel])
            weight = np.where(sel_lo[sel], 1.0 - frac[sel], frac[sel])[:, None]
            out[sel] += weight * vals
        return out

    def _sample_level(self, k: int, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        padded = self._padded[k]
        scale = 2.0**k
        w = self.levels[k].shape[1]
        pad = 2
        c = ((col / scale - 0.5 * (1 - 1 / scale)) % w + pad).astype(np.float32)
        r = (row / scale - 0.5 * (1 - 1 / scale)).astype(np.float32)
        return remap_samples(padded, c, r)


# cv2.remap takes images and maps of fewer than 2**15 rows and columns.
_REMAP_LIMIT = 32000


def remap_samples(
    image: np.ndarray, col: np.ndarray, row: np.ndarray, max_rows: int = _REMAP_LIMIT
) -> np.ndarray:
    """Bilinear samples (M, C) of ``image`` (H, W, C) at float pixel positions ``col``,
    ``row`` (M,), reflected at its borders. Images taller than ``max_rows`` (a long
    pipe's texture) are sampled band by band, each band with two rows of its
    neighbours, so the result equals one remap of the whole image."""
    col = np.asarray(col, np.float32)
    row = np.asarray(row, np.float32)
    height = image.shape[0]
    if height <= max_rows:
        return _remap(image, col, row)
    band = max_rows - 8
    which = np.clip(np.floor(row / band), 0, -(-height // band) - 1).astype(int)
    out = np.empty((len(col), image.shape[2]), image.dtype)
    for b in np.unique(which):
        sel = which == b
        r0 = max(int(b) * band - 4, 0)
        r1 = min((int(b) + 1) * band + 4, height)
        out[sel] = _remap(image[r0:r1], col[sel], row[sel] - np.float32(r0))
    return out


def _remap(image: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    n = len(col)
    # cv2.remap wants 2-D maps narrower than 32k: fold the samples into rows of 1024.
    rows = -(-n // 1024)
    mx = np.zeros(rows * 1024, np.float32)
    my = np.zeros(rows * 1024, np.float32)
    mx[:n], my[:n] = col, row
    res = cv2.remap(
        image,
        mx.reshape(rows, 1024),
        my.reshape(rows, 1024),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT,
    )
    return res.reshape(-1, image.shape[2])[:n]

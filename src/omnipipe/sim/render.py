"""Physically based rendering of the rangefinder's image inside a simulated pipe.

For every valid pixel the ray of the hyperboloid camera (Eq. 1-3) is cast into
the world and intersected with the true wall (defects included, first hit). The
pixel's radiance is the wall albedo (mip-mapped to the pixel footprint) lit by the
robot's LEDs (inverse-square falloff, Lambert cosine with the true surface
normal), plus the laser sheet of Eq. (4): a Gaussian sheet of finite thickness
whose radiance is integrated analytically over each pixel's area from the sheet's
distance to the pixel's wall point and its gradient across the image (so the thin
line never aliases), then blurred by the optics; it carries laser speckle. Optics
blur the LED image, then the sensor adds shot and read noise and quantises to 8 bits.

The robot body (camera housing and the front unit behind the laser) occludes
the steepest backward rays: that is the image's blind centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from omnipipe.camera import OmniCamera
from omnipipe.geometry import apply, rotate
from omnipipe.image import CHANNEL_INDEX
from omnipipe.rig import Rig
from omnipipe.sim.scene import Pipe
from omnipipe.sim.texture import TextureConfig, WallTexture

# A branch pipe's own wall: plain PVC-like plastic, unlike any main wall's colour.
BRANCH_TEXTURE = TextureConfig(
    family="smooth", variant="pvc", base_rgb=(0.70, 0.48, 0.30), contrast=0.35
)


@dataclass(frozen=True)
class RenderConfig:
    """Light, optics and sensor of the simulated rangefinder.

    Attributes:
        exposure: image value (0..1 of full scale) of a white wall 100 mm from the LEDs,
            facing them, in a pipe of 202 mm; the camera's auto exposure scales its gain
            with (pipe radius / 101 mm)^2 so other pipe sizes are exposed alike.
        laser_power: image value (0..1) of the laser sheet's line integral across the
            stripe (x px, at the frame's median footprint) on a white wall 100 mm from
            the emitter.
        laser_sheet_sigma_mm: 1-sigma half thickness of the laser sheet (mm).
        laser_crosstalk: fraction of the laser that leaks into the other channels.
        speckle_contrast: std/mean of the laser speckle (0: none).
        psf_sigma_px: optical blur of lens + mirror (px, Gaussian sigma).
        full_well_e: electrons at full scale (shot noise).
        read_noise_dn: read noise (8-bit digital numbers).
        vignetting: relative brightness loss at the mirror rim.
        housing_radius_mm, housing_top_mm: camera housing (cylinder around the axis,
            occluding z < -housing_top_mm in the rig frame).
        body_radius_mm, body_gap_mm: the robot's front unit, behind the laser plane by body_gap_mm.
        led_z_mm: axial position of the LED ring in the rig frame; None: at the lens (z = -2c).
    """

    exposure: float = 0.9
    laser_power: float = 2.5
    laser_sheet_sigma_mm: float = 0.35
    laser_crosstalk: float = 0.05
    speckle_contrast: float = 0.25
    psf_sigma_px: float = 0.7
    full_well_e: float = 8000.0
    read_noise_dn: float = 1.0
    vignetting: float = 0.25
    housing_radius_mm: float = 21.0
    housing_top_mm: float = 70.0
    body_radius_mm: float = 62.0
    body_gap_mm: float = 20.0
    led_z_mm: float | None = None


def body_slope(rig: Rig, config: RenderConfig) -> float:
    """Largest radial/axial slope of backward rays that the robot body occludes."""
    body_top = rig.laser.distance_mm + config.body_gap_mm
    return max(config.housing_radius_mm / config.housing_top_mm, config.body_radius_mm / body_top)


def blind_radius_px(rig: Rig, config: RenderConfig, margin_px: float = 3.0) -> float:
    """Image radius (px) of the robot body's silhouette plus a margin: rig.yaml's radius_min."""
    slope = body_slope(rig, config)
    direction = np.array([[slope, 0.0, -1.0]])
    cam = OmniCamera(rig.camera, rig.mirror)
    px, _ = cam.project(direction)
    return float(px[0, 0] - cam.cx) + margin_px


@dataclass
class WallHits:
    """Where rays meet the true wall.

    Attributes:
        points_in_rig: (M, 3) hit points in the rig frame (mm).
        points_in_world: (M, 3) hit points in the world frame (mm).
        sigma, theta: (M,) pipe coordinates (mm, rad).
        normals_in_world: (M, 3) unit wall normals pointing into the pipe.
        surface: (M,) int8 what each ray met, for pipes with laterals or water (None
            otherwise: all main wall): SURFACE_WALL, SURFACE_WATER, SURFACE_DARK (a
            branch's open far end) or 1 + k for lateral k's branch wall.
        branch_coords: (M, 2) the branch wall's texture coordinates (mm along its axis,
            rad around it) where ``surface`` is a branch, else NaN; None with ``surface``.
    """

    points_in_rig: np.ndarray
    points_in_world: np.ndarray
    sigma: np.ndarray
    theta: np.ndarray
    normals_in_world: np.ndarray
    surface: np.ndarray | None = None
    branch_coords: np.ndarray | None = None


SURFACE_WALL = 0
SURFACE_WATER = -1
SURFACE_DARK = -2

WATER_LINE_SUBPIXELS = 8
"""Rays per pixel side cast again where the water line's image crosses a pixel near the
laser sheet (:meth:`Renderer._water_line`): 64 sub-pixels, each a sheet-distance span of
an eighth of the pixel's (the sheet sampled finer than its own sigma where a pixel spans
up to a few mm of it)."""

WATER_LINE_NEAR_MM = 60.0
"""Pixels of the water line re-cast only within this distance (mm) of the sheet's plane
(their centre ray's hit): beyond it the sheet's light is nil."""


@dataclass(frozen=True)
class WaterLine:
    """Pixels the water line's image crosses near the sheet (:meth:`Renderer._water_line`).

    Attributes:
        index: (E,) indices into the wall-mask pixels.
        share: (E,) share of each one's area on the wall.
        wall_h: (E,) mean sheet distance (mm) of that wall part (the pixel's centre's if none).
        sub: hits of the (E * S) sub-pixel rays, S = WATER_LINE_SUBPIXELS ^ 2, pixel-major.
        on_wall: (E * S,) which sub-pixel rays met the wall.
    """

    index: np.ndarray
    share: np.ndarray
    wall_h: np.ndarray
    sub: WallHits
    on_wall: np.ndarray

    def subset(self, keep: np.ndarray) -> WaterLine:
        """The pixels ``keep`` (E,) bool."""
        rays = np.repeat(keep, len(self.on_wall) // max(len(keep), 1))
        sub = WallHits(*(None if v is None else v[rays] for v in (
            self.sub.points_in_rig, self.sub.points_in_world, self.sub.sigma, self.sub.theta,
            self.sub.normals_in_world, self.sub.surface, self.sub.branch_coords)))
        return WaterLine(self.index[keep], self.share[keep], self.wall_h[keep], sub, self.on_wall[rays])


def _one_sided_gradient(
    himg: np.ndarray, surface: np.ndarray, flat: np.ndarray, shape: tuple[int, int]
) -> np.ndarray:
    """(M,) |grad h| (mm/px) of the (H, W) image ``himg`` at the M pixels ``flat`` whose
    ``surface`` (M,) is wall, from wall neighbours only: central differences where both
    neighbours along an axis are wall, one-sided where one is; NaN where no axis has one."""
    cls = np.zeros(shape[0] * shape[1], bool)
    cls[flat] = surface == SURFACE_WALL
    hv = np.where(cls.reshape(shape), himg, np.nan)
    parts = []
    for axis in (0, 1):
        d = np.diff(hv, axis=axis)
        pad = [(0, 0), (0, 0)]
        pad[axis] = (0, 1)
        fwd = np.pad(d, pad, constant_values=np.nan)
        pad[axis] = (1, 0)
        bwd = np.pad(d, pad, constant_values=np.nan)
        with np.errstate(invalid="ignore"):
            both = np.where(np.isfinite(fwd) & np.isfinite(bwd), 0.5 * (fwd + bwd), np.where(np.isfinite(fwd), fwd, bwd))
        parts.append(both)
    g = np.hypot(np.nan_to_num(parts[0]), np.nan_to_num(parts[1]))
    g[~(np.isfinite(parts[0]) | np.isfinite(parts[1]))] = np.nan
    return g.ravel()[flat]
BRACKET_MARGIN_MM = 1.0
"""How far inside the smallest and outside the largest wall radius the shaped wall's ray
casting starts and ends its samples (mm; :meth:`Renderer._intersect_shaped`)."""

# Standing water: a dark, almost black surface (no laser return: the sheet does not
# scatter back from a still water surface).
WATER_ALBEDO = (0.025, 0.03, 0.028)


class Renderer:
    """Renders frames of one rig in one pipe.

    Args:
        rig: the rangefinder (its radius_min/max are the true silhouettes).
        pipe: the true pipe.
        texture: albedo of the wall.
        config: light, optics and sensor.
    """

    def __init__(
        self, rig: Rig, pipe: Pipe, texture: WallTexture, config: RenderConfig | None = None
    ):
        self.rig = rig
        self.pipe = pipe
        self.texture = texture
        self.config = config or RenderConfig()
        cam = OmniCamera(rig.camera, rig.mirror)
        self.camera = cam
        h, w = cam.height, cam.width
        rows, cols = np.mgrid[0:h, 0:w]
        r = np.hypot(cols - cam.cx, rows - cam.cy)
        # Every pixel that sees the mirror (the true rim), body pixels included.
        self.mirror_mask = r <= cam.radius_max
        self.index = np.flatnonzero(self.mirror_mask)
        pixels = np.stack([cols.ravel()[self.index], rows.ravel()[self.index]], axis=1).astype(
            float
        )
        self.rays_in_rig = cam.unproject(pixels)
        slope = np.hypot(self.rays_in_rig[:, 0], self.rays_in_rig[:, 1]) / np.maximum(
            -self.rays_in_rig[:, 2], 1e-12
        )
        self.body = (self.rays_in_rig[:, 2] < 0) & (slope < body_slope(rig, self.config))
        # Angle between neighbouring pixels' rays (rad/px): the footprint per unit distance
        # (the larger of the column and row steps; 0 where no ray).
        steps = (cam.pixel_angle(pixels, (1.0, 0.0)), cam.pixel_angle(pixels, (0.0, 1.0)))
        self.pixel_angle = np.fmax(0.0, np.fmax(*steps))
        self.vignette = 1.0 - self.config.vignetting * (r.ravel()[self.index] / cam.radius_max) ** 2
        self.laser_normal = rig.laser.normal_in_rig
        self.laser_offset = rig.laser.offset_mm
        self.laser_origin_in_rig = -self.laser_offset * self.laser_normal
        led_z = -2.0 * rig.mirror.c if self.config.led_z_mm is None else self.config.led_z_mm
        self.led_in_rig = np.array([0.0, 0.0, led_z])
        # Auto exposure: the gain that keeps the wall of this pipe as bright as in a 202 mm pipe.
        self.gain = (pipe.radius_mm / 101.0) ** 2
        n_lat = len(pipe.features.laterals)
        self.branch_geometry = [pipe.lateral_frame(k) for k in range(n_lat)]
        self.branch_textures = [self._branch_texture(k) for k in range(n_lat)]

    def _branch_texture(self, index: int) -> WallTexture:
        """Lateral ``index``'s own wall texture (fixed seed per lateral)."""
        lat = self.pipe.features.laterals[index]
        end = self.branch_geometry[index][4]
        cfg = replace(BRANCH_TEXTURE, texel_mm=max(self.texture.texel_mm, 0.5))
        return WallTexture(math.pi * lat.diameter_mm, (-10.0, end + 10.0), 7919 + index, cfg)

    # -- geometry ---------------------------------------------------------------------
    def intersect(
        self, origin_in_world: np.ndarray, rays_in_world: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """First wall hit along each unit ray.

        Returns:
            t: (M,) distance (mm) from the origin along each ray (capped at 5 m).
            near_defect: (M,) True for rays whose hit may lie on a defect.
        """
        pipe = self.pipe
        o = np.asarray(origin_in_world, float)
        D = rays_in_world
        if pipe.features.shapes_wall:
            return self._intersect_shaped(o, D), np.ones(len(D), bool)
        t = self._solve_radius(o, D, pipe.radius_mm)
        if pipe.ovality:
            t = self._newton_wall(o, D, t)
        cand = np.zeros(len(D), bool)
        if pipe.defects:
            inward, outward = pipe.max_deviation()
            t_in = self._solve_radius(o, D, pipe.radius_mm - inward, start=t)
            t_out = self._solve_radius(o, D, pipe.radius_mm + outward, start=t)
            cand = self._near_defects(o, D, t_in, t_out)
            if cand.any():
                t[cand] = self._first_root(o, D[cand], t_in[cand], t_out[cand])
        return t, cand

    def _solve_radius(
        self,
        o: np.ndarray,
        D: np.ndarray,
        radius: float,
        start: np.ndarray | None = None,
        iters: int = 8,
    ) -> np.ndarray:
        """Ray distance where the distance to the centreline equals ``radius``.

        Starts from the hit of the locally straight pipe (exact for straight pipes) or
        ``start``, then Newton on rho(t) = radius (d rho / dt = D . e_rho exactly),
        iterating only the rays that have not converged.
        """
        pipe = self.pipe
        if start is None or not pipe.centreline.has_bend:
            sig_o, *_ = pipe.pipe_coordinates(o[None])
            c_o, _, _, t_o = pipe.frame_at(sig_o)
            w = o - c_o[0]
            w_perp = w - (w @ t_o[0]) * t_o[0]
            d_perp = D - np.outer(D @ t_o[0], t_o[0])
            a = np.einsum("ij,ij->i", d_perp, d_perp)
            b = d_perp @ w_perp
            c = w_perp @ w_perp - radius * radius
            with np.errstate(invalid="ignore", divide="ignore"):
                t = (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a
            t = np.where(np.isfinite(t), np.minimum(t, 5000.0), 5000.0)
        else:
            t = start.copy()
        return pipe.ray_distance_to_radius(o, D, radius, t)

    def _wall_residual(
        self, o: np.ndarray, D: np.ndarray, t: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        X = o + t[:, None] * D
        sigma, rho, theta, radial, *_ = self.pipe.pipe_coordinates(X)
        return rho - self.pipe.wall_radius(sigma, theta), radial

    def _newton_wall(
        self, o: np.ndarray, D: np.ndarray, t: np.ndarray, iters: int = 4
    ) -> np.ndarray:
        for _ in range(iters):
            g, radial = self._wall_residual(o, D, t)
            slope = np.maximum(np.einsum("ij,ij->i", D, radial), 0.05)
            t = t - g / slope
        return t

    def _near_defects(
        self, o: np.ndarray, D: np.ndarray, t_in: np.ndarray, t_out: np.ndarray
    ) -> np.ndarray:
        pipe = self.pipe
        s1, th1 = pipe.sigma_theta(o + t_in[:, None] * D)
        s2, th2 = pipe.sigma_theta(o + t_out[:, None] * D)
        lo, hi = np.minimum(s1, s2), np.maximum(s1, s2)
        out = np.zeros(len(D), bool)
        for dft in pipe.defects:
            half_len = 0.5 * (dft.length_mm + dft.ramp_length_mm) + 1.0
            half_ang = (0.5 * (dft.width_mm + dft.ramp_width_mm) + 1.0) / pipe.radius_mm
            c_ang = math.radians(dft.angle_deg)
            d1 = np.mod(th1 - c_ang + np.pi, 2 * np.pi) - np.pi
            d2 = np.mod(th2 - c_ang + np.pi, 2 * np.pi) - np.pi
            ang_hit = (np.minimum(d1, d2) <= half_ang) & (np.maximum(d1, d2) >= -half_ang)
            ax_hit = (lo <= dft.axial_centre_mm + half_len) & (hi >= dft.axial_centre_mm - half_len)
            out |= ang_hit & ax_hit
        return out

    def _first_root(
        self, o: np.ndarray, D: np.ndarray, t_in: np.ndarray, t_out: np.ndarray
    ) -> np.ndarray:
        """First sign change of the wall residual in [t_in, t_out], refined by bisection."""
        n_samples = 16
        ts = t_in[:, None] + (t_out - t_in)[:, None] * np.linspace(0.0, 1.0, n_samples)[None, :]
        g = np.stack([self._wall_residual(o, D, ts[:, k])[0] for k in range(n_samples)], axis=1)
        crossing = (g[:, :-1] < 0) & (g[:, 1:] >= 0)
        has = crossing.any(axis=1)
        k = np.where(has, np.argmax(crossing, axis=1), n_samples - 2)
        rows = np.arange(len(D))
        lo, hi = ts[rows, k], ts[rows, k + 1]
        g_lo, g_hi = g[rows, k], g[rows, k + 1]
        mid = lo
        for _ in range(8):  # Illinois regula falsi: superlinear, keeps the bracket
            mid = lo - g_lo * (hi - lo) / np.where(g_hi > g_lo, g_hi - g_lo, 1.0)
            gm, _ = self._wall_residual(o, D, mid)
            below = gm < 0
            lo, g_lo, g_hi = (
                np.where(below, mid, lo),
                np.where(below, gm, 0.5 * g_lo),
                np.where(below, 0.5 * g_hi, g_hi),
            )
            hi, g_hi = np.where(below, hi, mid), np.where(below, g_hi, gm)
        return mid

    def wall_normals(self, points_in_world: np.ndarray) -> np.ndarray:
        """(M, 3) unit wall normals pointing into the pipe, from the true wall function."""
        pipe = self.pipe
        sigma, rho, theta, radial, tangent, _, _ = pipe.pipe_coordinates(points_in_world)
        e_theta = np.cross(tangent, radial)
        ds, dth = 0.05, 0.05 / pipe.radius_mm
        dr_ds = (pipe.wall_radius(sigma + ds, theta) - pipe.wall_radius(sigma - ds, theta)) / (
            2 * ds
        )
        dr_dth = (pipe.wall_radius(sigma, theta + dth) - pipe.wall_radius(sigma, theta - dth)) / (
            2 * dth
        )
        grad = (
            radial - dr_ds[:, None] * tangent - (dr_dth / np.maximum(rho, 1e-9))[:, None] * e_theta
        )
        return -grad / np.linalg.norm(grad, axis=1, keepdims=True)

    # -- features (joints, tapers, ovality, laterals, water) ------------------------
    def _intersect_shaped(self, o: np.ndarray, D: np.ndarray, n_samples: int = 20) -> np.ndarray:
        """First wall hit (mm along each ray) of a pipe with joints, tapers or local ovality.

        The wall radius lies within :meth:`Pipe.wall_bounds`, so the first hit lies between
        the distances where each ray reaches those radii. The wall residual is sampled
        there (``n_samples`` evenly) and on every plane where the wall bends sharply (joint
        edges, taper ends: no narrow gap edge is stepped over), and the first sign change
        is refined by regula falsi.
        """
        pipe = self.pipe
        lo, hi = pipe.wall_bounds()
        # The bracket strictly inside and outside the wall: a ray starting its samples on
        # the narrowest section's wall itself (residual 0, not < 0) found no crossing and
        # landed in the bracket's last interval (random-features seed 18: the rings past
        # a 196 -> 164 mm reducer drawn at 187 mm).
        lo, hi = lo - BRACKET_MARGIN_MM, hi + BRACKET_MARGIN_MM
        t0 = self._solve_radius(o, D, pipe.radius_mm)
        t_in = self._solve_radius(o, D, lo, start=t0)
        t_out = np.maximum(self._solve_radius(o, D, hi, start=t0), t_in)
        return pipe.first_wall_crossing(o, D, t_in, t_out, n_samples)

    def _in_hole(self, index: int, points_in_world: np.ndarray) -> np.ndarray:
        """(M,) True for main-wall points inside lateral ``index``'s hole."""
        origin, axis, _, radius, _ = self.branch_geometry[index]
        v = points_in_world - origin
        u = v @ axis
        return (u > 0) & (np.einsum("ij,ij->i", v, v) - u * u < radius * radius)

    def _hit_extras(
        self,
        world_from_rig: np.ndarray,
        rays_in_rig: np.ndarray,
        rays_world: np.ndarray,
        t: np.ndarray,
        hits: WallHits,
    ) -> WallHits:
        """Standing water in front of the wall, and branch walls seen through laterals' holes."""
        pipe = self.pipe
        o = world_from_rig[:3, 3]
        surface = np.zeros(len(t), np.int8)
        coords = np.full((len(t), 2), np.nan)
        t = t.copy()
        points, normals = hits.points_in_world.copy(), hits.normals_in_world.copy()
        water = pipe.features.water
        if water is not None:
            up = pipe.up()
            rate = rays_world @ up
            with np.errstate(divide="ignore", invalid="ignore"):
                t_w = (float(pipe.water_level()) - o @ up) / rate
            cand = np.flatnonzero((rate < 0) & (t_w > 0) & (t_w < t))
            p_w = o + t_w[cand, None] * rays_world[cand]
            s_w, _ = pipe.sigma_theta(p_w)
            keep = (s_w >= water.axial_from_mm) & (s_w <= water.axial_to_mm)
            idx = cand[keep]
            t[idx], points[idx], normals[idx] = t_w[idx], p_w[keep], up
            surface[idx] = SURFACE_WATER
        for k in range(len(self.branch_geometry)):
            wall_idx = np.flatnonzero(surface == SURFACE_WALL)
            idx = wall_idx[self._in_hole(k, points[wall_idx])]
            if len(idx) == 0:
                continue
            origin, axis, ref, radius, end = self.branch_geometry[k]
            d = rays_world[idx]
            w = o - origin
            d_p = d - np.outer(d @ axis, axis)
            w_p = w - (w @ axis) * axis
            a = np.einsum("ij,ij->i", d_p, d_p)
            b = d_p @ w_p
            c = w_p @ w_p - radius * radius
            t2 = (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / np.maximum(a, 1e-12)
            u = w @ axis + t2 * (d @ axis)
            far = u > end
            # Past the branch's end: the dark opening, on the end's plane.
            t2 = np.where(far, (end - w @ axis) / np.where(far, d @ axis, 1.0), t2)
            y = o + t2[:, None] * d
            v = y - origin
            u = v @ axis
            radial = v - u[:, None] * axis
            rr = np.maximum(np.linalg.norm(radial, axis=1), 1e-12)
            t[idx], points[idx] = t2, y
            normals[idx] = np.where(far[:, None], -axis, -radial / rr[:, None])
            surface[idx] = np.where(far, SURFACE_DARK, k + 1)
            coords[idx, 0] = u
            coords[idx, 1] = np.arctan2(radial @ np.cross(axis, ref), radial @ ref)
        changed = np.flatnonzero(surface != SURFACE_WALL)
        sigma, theta = hits.sigma.copy(), hits.theta.copy()
        if len(changed):
            sigma[changed], theta[changed] = pipe.sigma_theta(points[changed])
        return WallHits(t[:, None] * rays_in_rig, points, sigma, theta, normals, surface, coords)

    def _seen_through_holes(
        self, source_in_world: np.ndarray, points_in_world: np.ndarray, surface: np.ndarray
    ) -> np.ndarray:
        """(M,) 1.0 where the straight path from a light source inside the main pipe to a
        branch wall point (``surface`` 1 + k) leaves through lateral k's hole, else 0.0."""
        diff = points_in_world - source_in_world
        dist = np.linalg.norm(diff, axis=1)
        dirs = diff / np.maximum(dist, 1e-12)[:, None]
        t_main, _ = self.intersect(source_in_world, dirs)
        exit_pts = source_in_world + t_main[:, None] * dirs
        ok = t_main < dist + 1e-6
        for k in range(len(self.branch_geometry)):
            sel = surface == k + 1
            ok[sel] &= self._in_hole(k, exit_pts[sel])
        return ok.astype(np.float64)

    def _albedo(self, hits: WallHits, footprint_mm: np.ndarray) -> np.ndarray:
        """(M, 3) albedo of each hit: main wall texture, water, branch textures, dark ends."""
        if hits.surface is None:
            return self.texture.sample(hits.sigma, hits.theta, footprint_mm)
        out = np.zeros((len(footprint_mm), 3), np.float32)
        wall = hits.surface == SURFACE_WALL
        out[wall] = self.texture.sample(hits.sigma[wall], hits.theta[wall], footprint_mm[wall])
        out[hits.surface == SURFACE_WATER] = WATER_ALBEDO
        for k, tex in enumerate(self.branch_textures):
            sel = hits.surface == k + 1
            if sel.any() and hits.branch_coords is not None:
                uv = hits.branch_coords[sel]
                out[sel] = tex.sample(uv[:, 0], uv[:, 1], footprint_mm[sel])
        return out

    def _laser_extras(
        self, world_from_rig: np.ndarray, hits: WallHits, footprint: np.ndarray, laser_h: np.ndarray
    ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """(albedo, lit, surface) for :meth:`_laser_image` with water or laterals; Nones without."""
        if hits.surface is None:
            return None, None, None
        albedo = self._albedo(hits, footprint)
        lit = (hits.surface >= 0).astype(np.float64)  # water and dark ends send nothing back
        branch = np.flatnonzero((hits.surface > 0) & (np.abs(laser_h) < 30.0))
        if len(branch):
            emitter = apply(world_from_rig, self.laser_origin_in_rig[None])[0]
            lit[branch] = self._seen_through_holes(
                emitter, hits.points_in_world[branch], hits.surface[branch]
            )
        return albedo, lit, hits.surface

    # -- image ------------------------------------------------------------------------
    def hit(self, world_from_rig: np.ndarray, rays_in_rig: np.ndarray) -> WallHits:
        """Cast (M, 3) unit rays from the rig at ``world_from_rig`` onto the true wall."""
        rays_world = rotate(world_from_rig, rays_in_rig)
        origin = world_from_rig[:3, 3]
        t, near_defect = self.intersect(origin, rays_world)
        points_world = origin + t[:, None] * rays_world
        sigma, _, theta, radial, *_ = self.pipe.pipe_coordinates(points_world)
        normals = -radial
        shaped = near_defect if not self.pipe.ovality else np.ones(len(t), bool)
        if shaped.any():
            normals[shaped] = self.wall_normals(points_world[shaped])
        hits = WallHits(t[:, None] * rays_in_rig, points_world, sigma, theta, normals)
        if self.pipe.features.laterals or self.pipe.features.water is not None:
            hits = self._hit_extras(world_from_rig, rays_in_rig, rays_world, t, hits)
        return hits

    def shade(
        self, world_from_rig: np.ndarray, hits: WallHits, footprint_mm: np.ndarray
    ) -> np.ndarray:
        """(M, 3) LED-lit wall radiance (0..1 of full scale) of wall hits.

        Args:
            footprint_mm: (M,) size of each pixel on the wall (mm), for texture filtering.
        """
        cfg = self.config
        albedo = self._albedo(hits, np.minimum(footprint_mm, 50.0))
        led_world = world_from_rig[:3, :3] @ self.led_in_rig + world_from_rig[:3, 3]
        to_led = led_world - hits.points_in_world
        dist = np.linalg.norm(to_led, axis=1)
        cos_i = np.clip(np.einsum("ij,ij->i", hits.normals_in_world, to_led) / dist, 0.0, 1.0)
        irradiance = cfg.exposure * cos_i * (100.0 / dist) ** 2
        if hits.surface is not None and (hits.surface > 0).any():
            branch = np.flatnonzero(hits.surface > 0)
            irradiance[branch] *= self._seen_through_holes(
                led_world, hits.points_in_world[branch], hits.surface[branch]
            )
        return albedo * irradiance[:, None].astype(np.float32)

    @staticmethod
    def footprint(points: np.ndarray, flat_index: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """(M,) pixel footprint on the wall (mm/px) from image differences of hit points."""
        h, w = shape
        full = np.full((h * w, 3), np.nan, np.float32)
        full[flat_index] = points
        grid = full.reshape(h, w, 3)
        gx = np.diff(grid, axis=1, append=np.nan)
        gy = np.diff(grid, axis=0, append=np.nan)
        step = np.fmax(np.linalg.norm(gx, axis=2), np.linalg.norm(gy, axis=2)).ravel()[flat_index]
        return np.where(np.isfinite(step), step, 5.0)

    def render(
        self,
        world_from_rig: np.ndarray,
        seed: int,
        led: bool = True,
        laser: bool = True,
        noise: bool = True,
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Render one 8-bit RGB frame: :meth:`irradiance` then :meth:`expose` (same arguments)."""
        image, truth = self.irradiance(world_from_rig, seed, led=led, laser=laser)
        return self.expose(image, seed, noise=noise), truth

    def irradiance(
        self,
        world_from_rig: np.ndarray,
        seed: int,
        led: bool = True,
        laser: bool = True,
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The image on the sensor (before noise) seen from ``world_from_rig``.

        Args:
            world_from_rig: (4, 4) true pose of the rig (mm).
            seed: speckle seed.
            led: LED illumination on (False: the paper's Fig. 19 laser-only frame).
            laser: laser on.

        Returns:
            image: (H, W, 3) float32 irradiance (1 = full scale before the gain).
            truth: ground truth of the wall pixels: "index" (flat pixel index),
            "points_in_rig" (M, 3) mm, "sigma", "theta", "laser_h" (mm to the plane).
        """
        cfg = self.config
        cam = self.camera
        h, w = cam.height, cam.width
        rng = np.random.default_rng(seed)
        wall = ~self.body
        flat = self.index[wall]
        hits = self.hit(world_from_rig, self.rays_in_rig[wall])
        points_rig = hits.points_in_rig

        # Pixel footprint on the wall (mm/px): distance x pixel angle / cos(incidence).
        rays_world = rotate(world_from_rig, self.rays_in_rig[wall])
        cos_inc = np.abs(np.einsum("ij,ij->i", rays_world, hits.normals_in_world))
        dist = np.linalg.norm(points_rig, axis=1)
        footprint = dist * self.pixel_angle[wall] / np.maximum(cos_inc, 0.1)
        radiance = np.zeros((len(self.index), 3), np.float32)
        if led:
            radiance[wall] = self.shade(world_from_rig, hits, footprint)
            radiance[self.body] = 0.04  # the robot body: dark anodised housing, faintly lit
        radiance *= self.vignette[:, None]
        image = np.zeros((h * w, 3), np.float32)
        image[self.index] = radiance
        image = image.reshape(h, w, 3)
        if cfg.psf_sigma_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), cfg.psf_sigma_px)

        laser_h = points_rig @ self.laser_normal + self.laser_offset
        if laser:
            extras = self._laser_extras(world_from_rig, hits, footprint, laser_h)
            line = None
            if self.pipe.features.water is not None and extras[2] is not None:
                line = self._water_line(world_from_rig, extras[2], laser_h)
            image += self._laser_image(
                points_rig, laser_h, hits.sigma, hits.theta, footprint, wall, rng, *extras,
                water_line=line,
            )

        truth = {
            "index": flat,
            "points_in_rig": points_rig,
            "sigma": hits.sigma,
            "theta": hits.theta,
            "laser_h": laser_h,
        }
        if hits.surface is not None:
            truth["surface"] = hits.surface
        return image, truth

    def _sheet_gradient(
        self, laser_h: np.ndarray, wall: np.ndarray, surface: np.ndarray | None, water_line: WaterLine | None
    ) -> np.ndarray:
        """(M,) |grad h| (mm/px) of the sheet distance ``laser_h`` (M,) across the image at
        the wall-mask pixels ``wall``: central differences; beside another ``surface`` the
        frame's median (:meth:`_grad_at_edges`), but on the water line's pixels the wall's
        own, at their wall part's distance, one-sided from the wall where the water is."""
        h, w = self.camera.height, self.camera.width
        hfull = np.full(h * w, np.nan, np.float64)
        hfull[self.index[wall]] = laser_h
        if water_line is not None:
            hfull[self.index[wall][water_line.index]] = water_line.wall_h
            surface = surface.copy()
            surface[water_line.index] = np.where(water_line.share > 0, SURFACE_WALL, surface[water_line.index])
        himg = hfull.reshape(h, w)
        gy, gx = np.gradient(himg)
        grad = np.hypot(gx, gy).ravel()[self.index[wall]]
        if surface is not None:
            grad = self._grad_at_edges(grad, surface, wall)
        if water_line is not None:
            own = _one_sided_gradient(himg, surface, self.index[wall], (h, w))[water_line.index]
            grad[water_line.index] = np.where(np.isfinite(own), own, grad[water_line.index])
        return grad

    def _water_line(
        self, world_from_rig: np.ndarray, surface: np.ndarray, laser_h: np.ndarray
    ) -> WaterLine | None:
        """The pixels the water line's image crosses near the laser sheet, cast again with
        :data:`WATER_LINE_SUBPIXELS` ^ 2 rays over each one's area (:class:`WaterLine`).

        A pixel beside the water line (a wall pixel with a water neighbour or the reverse)
        sees wall over part of its area only; a sensor integrates the sheet's light over
        that part. Without it each pixel was wall or water by its centre ray (the stripe's
        end up to half a pixel off the true water line, alike in every frame of a run: the
        line's image stays where it is while the robot moves along the pipe). Only pixels
        whose centre lies within :data:`WATER_LINE_NEAR_MM` of the sheet are cast again.
        ``surface`` and ``laser_h`` (M,) of the wall-mask pixels."""
        cam = self.camera
        h, w = cam.height, cam.width
        flat_all = self.index[~self.body]
        full = np.full(h * w, 127, np.int16)
        full[flat_all] = surface
        img = full.reshape(h, w)
        is_wall, is_water = img == SURFACE_WALL, img == SURFACE_WATER
        near_water, near_wall = np.zeros((h, w), bool), np.zeros((h, w), bool)
        for a, b in ((np.s_[:, 1:], np.s_[:, :-1]), (np.s_[1:], np.s_[:-1])):
            near_water[a] |= is_water[b]
            near_water[b] |= is_water[a]
            near_wall[a] |= is_wall[b]
            near_wall[b] |= is_wall[a]
        crossed = ((is_wall & near_water) | (is_water & near_wall)).ravel()[flat_all]
        sel = np.flatnonzero(crossed & (np.abs(laser_h) < WATER_LINE_NEAR_MM))
        if len(sel) == 0:
            return None
        m = WATER_LINE_SUBPIXELS
        flat = flat_all[sel]
        offs = (np.arange(m) + 0.5) / m - 0.5
        ox, oy = (v.ravel() for v in np.meshgrid(offs, offs))
        px = np.stack([(flat % w)[:, None] + ox[None], (flat // w)[:, None] + oy[None]], axis=2)
        sub = self.hit(world_from_rig, cam.unproject(px.reshape(-1, 2)))
        on_wall = sub.surface == SURFACE_WALL
        share = on_wall.reshape(len(sel), m * m).mean(axis=1)
        count = np.maximum(on_wall.reshape(len(sel), m * m).sum(axis=1), 1)[:, None]
        pts = sub.points_in_rig.reshape(len(sel), m * m, 3) * on_wall.reshape(len(sel), m * m, 1)
        wall_h = np.where(share > 0, pts.sum(axis=1) / count @ self.laser_normal + self.laser_offset, laser_h[sel])
        return WaterLine(sel, share, wall_h, sub, on_wall)

    def _water_line_radiance(
        self, line: WaterLine, grad: np.ndarray, footprint: np.ndarray, g_ref: float
    ) -> np.ndarray:
        """(E,) the sheet's radiance over the area of each of ``line``'s pixels: the mean
        of its sub-rays' (:meth:`_sheet_radiance` at a sub-pixel's span of the sheet
        distance, ``grad`` (E,) / :data:`WATER_LINE_SUBPIXELS`), 0 on the water's."""
        mm = WATER_LINE_SUBPIXELS**2
        sub = line.sub
        lh = sub.points_in_rig @ self.laser_normal + self.laser_offset
        g = np.repeat(np.maximum(grad, 1e-6) / WATER_LINE_SUBPIXELS, mm)
        fp = np.repeat(footprint / WATER_LINE_SUBPIXELS, mm)
        wall = line.on_wall
        albedo = np.zeros((len(lh), 3), np.float32)
        albedo[wall] = self.texture.sample(sub.sigma[wall], sub.theta[wall], fp[wall])
        rad = self._sheet_radiance(
            sub.points_in_rig, lh, g, (sub.sigma, sub.theta, fp), albedo, wall.astype(np.float64), g_ref
        )
        return rad.reshape(-1, mm).mean(axis=1)

    def _grad_at_edges(self, grad: np.ndarray, surface: np.ndarray, wall: np.ndarray) -> np.ndarray:
        """``grad`` with pixels beside another surface (or the body) set to the median."""
        h, w = self.camera.height, self.camera.width
        full = np.full(h * w, 127, np.int16)
        full[self.index[wall]] = surface
        img = full.reshape(h, w)
        edge = np.zeros((h, w), bool)
        edge[:, 1:] |= img[:, 1:] != img[:, :-1]
        edge[:, :-1] |= img[:, 1:] != img[:, :-1]
        edge[1:] |= img[1:] != img[:-1]
        edge[:-1] |= img[1:] != img[:-1]
        at = edge.ravel()[self.index[wall]]
        out = grad.copy()
        out[at] = float(np.nanmedian(grad))
        return out

    def expose(self, image: np.ndarray, seed: int, noise: bool = True) -> np.ndarray:
        """The sensor: gain, shot and read noise, 8-bit quantisation of an irradiance image.

        A robot standing still sees the same irradiance (the laser speckle too: same
        geometry); only this sensor noise differs between its frames.
        """
        cfg = self.config
        rng = np.random.default_rng([seed, 1])
        dn = np.clip(image, 0.0, None) * np.float32(255.0 * self.gain)
        if noise:
            # Sensor: shot noise (Poisson, Gaussian approximation) and read noise.
            shot_dn = np.sqrt(dn * np.float32(255.0 / cfg.full_well_e))
            dn = dn + shot_dn * rng.standard_normal(image.shape, dtype=np.float32)
            dn = dn + np.float32(cfg.read_noise_dn) * rng.standard_normal(
                image.shape, dtype=np.float32
            )
        return np.clip(np.round(dn), 0, 255).astype(np.uint8)  # 8-bit quantisation, saturation

    def _laser_image(
        self,
        points_rig: np.ndarray,
        laser_h: np.ndarray,
        sigma: np.ndarray,
        theta: np.ndarray,
        footprint: np.ndarray,
        wall: np.ndarray,
        rng: np.random.Generator,
        albedo_all: np.ndarray | None = None,
        lit: np.ndarray | None = None,
        surface: np.ndarray | None = None,
        water_line: WaterLine | None = None,
    ) -> np.ndarray:
        """The laser line: the sheet's radiance on the wall, then the optics' blur.

        ``albedo_all`` (M, 3) replaces the main texture's albedo of every wall pixel and
        ``lit`` (M,) scales the sheet's power reaching each (0: under water, a branch's
        dark end, a branch wall the hole hides from the emitter); None: the main wall.
        Pixels next to another ``surface`` (M,) straddle a jump in depth: their gradient
        is not the sheet's across the pixel, so they take the frame's median; the pixels
        ``water_line`` crosses (:meth:`_water_line`) take their wall's and the sheet's
        light over their area (:meth:`_water_line_radiance`).

        Each pixel sees the wall point on its ray at distance ``h`` (mm) from the sheet's
        centre plane; the sheet's radiance there is Gaussian in ``h`` (sigma
        ``laser_sheet_sigma_mm``). Integrating over the pixel's area, which spans about
        ``g`` mm of ``h`` (g: the gradient of ``h`` across the image, mm/px), widens that
        Gaussian by ``g^2 / 12`` and lowers its peak alike, so a sheet thinner than a pixel
        neither aliases nor disappears. The image of that radiance is then blurred by the
        point spread function (an image convolution, exact for a curved, unevenly
        magnified line) and carries laser speckle. The radiance does not depend on ``g``:
        a pixel sees radiance, however much wall it covers. An earlier model drew the
        blurred line per pixel with a peak of power / (sqrt(2 pi) sigma_px), which made
        the brightness follow each pixel's ``g``; measured on bench_metrology's scenes at
        800x600 (noise-free frames, seeds 100-102), its ring came out 0.007-0.013 px
        inside the true one, this model's 0.004-0.006 px, and with true poses the
        analysed diameter moved from -0.048 to -0.024 mm (4 seeds).
        """
        cfg = self.config
        cam = self.camera
        h, w = cam.height, cam.width
        grad = self._sheet_gradient(laser_h, wall, surface, water_line)
        dist = laser_h
        if water_line is not None:
            dist = laser_h.copy()
            dist[water_line.index] = water_line.wall_h
        near = np.isfinite(grad) & (np.abs(dist) < 8.0 * cfg.laser_sheet_sigma_mm + 8.0 * grad)
        sel = np.flatnonzero(near)
        out = np.zeros((h * w, 3), np.float32)
        if len(sel) == 0:
            return out.reshape(h, w, 3)
        flat = self.index[wall][sel]  # flat image index of each selected pixel
        radiance = self._sheet_radiance(
            points_rig[sel], laser_h[sel], np.maximum(grad[sel], 1e-6),
            (sigma[sel], theta[sel], footprint[sel]),
            None if albedo_all is None else albedo_all[sel],
            None if lit is None else lit[sel],
        )
        if water_line is not None:
            at = np.full(len(laser_h), -1)
            at[sel] = np.arange(len(sel))
            k = at[water_line.index]
            use = k >= 0
            radiance[k[use]] = self._water_line_radiance(
                water_line.subset(use), grad[water_line.index[use]], footprint[water_line.index[use]],
                self._g_ref(grad[sel]),
            )
        value = self._blur_and_speckle(radiance, flat, rng)
        chan = CHANNEL_INDEX.get(self.rig.laser.channel)
        if chan is None:
            out[flat] = value[:, None]
        else:
            out[flat] = (cfg.laser_crosstalk * value)[:, None]
            out[flat, chan] = value
        return out.reshape(h, w, 3)

    def _sheet_radiance(
        self,
        points_rig: np.ndarray,
        laser_h: np.ndarray,
        g: np.ndarray,
        wall_coords: tuple[np.ndarray, np.ndarray, np.ndarray],
        albedo: np.ndarray | None,
        lit: np.ndarray | None,
        g_ref: float | None = None,
    ) -> np.ndarray:
        """The sheet's radiance (K,) at K wall pixels near it (see :meth:`_laser_image`).

        ``points_rig`` (K, 3) mm, ``laser_h`` (K,) distance from the sheet's centre plane
        (mm), ``g`` (K,) its gradient across the image (mm/px), ``wall_coords`` (sigma,
        theta, footprint) for the texture, ``albedo`` (K, 3) replacing it, ``lit`` (K,)
        the power's scale.
        """
        cfg = self.config
        sheet = cfg.laser_sheet_sigma_mm
        sheet_in_pixel_mm = np.sqrt(sheet**2 + g**2 / 12.0)
        # Power per unit length of the line: sheet fan spreads as 1/D; Lambert on the wall.
        to_emitter = self.laser_origin_in_rig - points_rig
        dist_e = np.linalg.norm(to_emitter, axis=1)
        if albedo is None:
            albedo = self.texture.sample(*wall_coords)
        chan = CHANNEL_INDEX.get(self.rig.laser.channel)
        refl = albedo[:, chan] if chan is not None else albedo.mean(axis=1)
        line = cfg.laser_power * (100.0 / dist_e) * np.clip(refl / 0.5, 0.2, 2.0) * 0.5
        if lit is not None:
            line = line * lit
        # laser_power is the line integral across the stripe (image value x px) at the
        # frame's median footprint: peak radiance = line / (sqrt(2 pi) sheet / g_ref).
        g_ref = self._g_ref(g) if g_ref is None else g_ref
        peak = line * g_ref / (math.sqrt(2 * math.pi) * sheet)
        return peak * (sheet / sheet_in_pixel_mm) * np.exp(-0.5 * (laser_h / sheet_in_pixel_mm) ** 2)

    @staticmethod
    def _g_ref(g: np.ndarray) -> float:
        """The frame's reference sheet gradient (mm/px): the median over its sheet pixels."""
        return float(np.median(g))

    def _blur_and_speckle(
        self, radiance: np.ndarray, flat: np.ndarray, rng: np.random.Generator
    ) -> np.ndarray:
        """The image values (K,) at flat pixel indices ``flat`` of ``radiance`` (K,) after
        the point spread function and laser speckle."""
        cfg = self.config
        h, w = self.camera.height, self.camera.width
        img = np.zeros(h * w, np.float32)
        img[flat] = radiance
        img = img.reshape(h, w)
        if cfg.psf_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), cfg.psf_sigma_px)
        value = img.ravel()[flat]
        if cfg.speckle_contrast > 0:
            # Speckle forms on the sensor (grains of about a pixel): it multiplies the image.
            k = 1.0 / cfg.speckle_contrast**2
            speckle = rng.gamma(k, 1.0 / k, size=len(flat)).astype(np.float32)
            field = np.ones(h * w, np.float32)
            field[flat] = speckle
            field = cv2.GaussianBlur(field.reshape(h, w), (0, 0), 0.6).ravel()
            value = value * field[flat]
        return value

"""Ray-cast rendering of the four-projector rig (Embree through embreex, called directly).

Image formation for projector k, phase step n of a sequence with period P (projector px):

    I = albedo * (ambient + E_k * cos(theta_k) * (d_ref / d_k)^2 * lit_k * pattern(u_k))
    pattern(u) = (A + B cos(2 pi u / P + 2 pi n / N)) ** gamma_projector

where u_k is the projector column hit by the surface point (the phase axis of every projector),
theta_k the angle between the surface normal and the direction to the projector, d_k the
distance to the projector centre and lit_k is 1 iff the point is inside the projector frustum,
faces it and nothing blocks the segment to its centre (exact shadows from occlusion rays).

Anti-aliasing averages each pixel over a grid of sub-pixel rays (``supersample`` per pixel and
axis, see :class:`SampleGrid`) whose centre samples also give the ground truth. As the pattern is a
Fourier series in the phase, each pixel's integral reduces to a few per-pixel sums (of
albedo * irradiance * cos(h phi) and * sin(h phi)), from which every phase step is an exact
linear combination: 148 images cost little more than one. Defocus (Gaussian blur of the optical
image), sensor noise (Poisson-Gaussian, heteroscedastic Gaussian approximation) and saturation
are applied in that order at the output resolution. Ground truth (depth, lit and footprint
masks, projector coordinates) comes from the ray through each pixel centre and is never blended
across edges.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import embreex.mesh_construction as emc
import embreex.rtcore_scene as ers
import numpy as np

from odmv.io.manifest import FringeSpec, fringe_name, uniform_name
from odmv.rig import Projector, Rig
from odmv.sim.scenes import Scene


@dataclass(frozen=True)
class RenderConfig:
    """Optical and sensor settings. Intensities are relative: 1.0 is the sensor's full scale."""

    supersample: int = 2  # sub-pixel sampling per axis (area-averaged, see SampleGrid)
    ambient: float = 0.05  # uniform ambient irradiance
    projector_irradiance: float = 0.9  # E_k at the reference distance, normal incidence
    fringe_offset: float = 0.5  # A
    fringe_amplitude: float = 0.5  # B
    projector_gamma: float = 1.0  # 1 = linear projector; e.g. 2.2 adds harmonics (phase error)
    defocus_sigma_px: float = 0.0  # Gaussian blur of the optical image, output pixels; 0 = off
    full_well_e: float = 20000.0  # electrons at full scale (photon noise); 0 = no photon noise
    read_noise: float = 0.002  # read-noise std in full-scale units; 0 = off
    saturation: float = 1.0  # clip level
    shadow_epsilon_mm: float = 1e-3  # shadow-ray origin offset along the normal

    @property
    def noisy(self) -> bool:
        return self.full_well_e > 0 or self.read_noise > 0


class RayCaster:
    """One Embree scene plus float64 per-face planes for exact hit points."""

    def __init__(self, scene: Scene):
        tris = scene.triangles
        self._embree = ers.EmbreeScene()
        emc.TriangleMesh(self._embree, tris.astype(np.float32))
        n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        self.normals = n / np.linalg.norm(n, axis=1, keepdims=True)
        self.normals32 = self.normals.astype(np.float32)
        self.offsets = (self.normals * tris[:, 0]).sum(1)
        self.albedo = scene.albedo

    def intersect(self, origins: np.ndarray, dirs: np.ndarray):
        """First hits of rays (R x 3 float32 origins and unit directions).

        Returns float32 points (from Embree's hit distance), unit normals facing the ray
        origin, albedo, hit triangle ids (-1: none).
        """
        res = self._embree.run(origins, dirs, output=1)
        prim = res["primID"]
        hit = prim >= 0
        p = np.where(hit, prim, 0)
        n = self.normals32[p]
        pts = origins + np.where(hit, res["tfar"], 0)[:, None] * dirs
        flip = np.einsum("ij,ij->i", n, dirs) > 0
        n[flip] *= -1
        return pts, n, np.where(hit, self.albedo[p], 0).astype(np.float32), prim

    def exact_points(self, origins: np.ndarray, dirs: np.ndarray, prim: np.ndarray):
        """Hit points in float64, intersecting each ray with its hit triangle's plane."""
        n = self.normals[prim]
        o, d = origins.astype(np.float64), dirs.astype(np.float64)
        t = (self.offsets[prim] - np.einsum("ij,ij->i", n, o)) / np.einsum("ij,ij->i", n, d)
        return o + t[:, None] * d

    def lit_by(
        self,
        pts: np.ndarray,
        normals: np.ndarray,
        proj: Projector,
        ref_mm: float,
        shadow_origins: np.ndarray,
    ):
        """Per point: footprint (inside the projector frustum), lit mask (in the footprint,
        facing the projector and unshadowed), projector column u, and the geometric irradiance
        factor cos(theta) * (ref / distance)^2 (0 where unlit).

        ``shadow_origins`` are the points nudged off their surface along the normal (float32).
        """
        dt = pts.dtype
        cam = pts @ proj.R.T.astype(dt) + proj.t.astype(dt)
        z = cam[:, 2]
        inv_z = 1 / np.where(z > 0, z, 1)
        # Python floats: NumPy float64 scalars would promote the float32 arrays
        fx, fy, cx, cy = (float(proj.K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
        u = (fx * cam[:, 0]) * inv_z + cx
        v = (fy * cam[:, 1]) * inv_z + cy
        inside = (z > 0) & (u >= 0) & (u < proj.width_px) & (v >= 0) & (v < proj.height_px)
        to_p = proj.center.astype(dt) - pts
        dist2 = np.einsum("ij,ij->i", to_p, to_p)
        cos_dist = np.einsum("ij,ij->i", normals, to_p)  # cos(theta) * distance
        lit = inside & (cos_dist > 0)
        # Shadow rays, for candidates only, along the unnormalized point-to-projector vector:
        # t = 1 reaches the projector centre (shifted by the origins' ~1 um nudge); stopping at
        # 1 - 1e-6 skips nothing real.
        idx = np.flatnonzero(lit)
        far = np.full(len(idx), 1 - 1e-6, np.float32)
        d32 = to_p[idx].astype(np.float32, copy=False)
        hits = self._embree.run(shadow_origins[idx], d32, dists=far, query="OCCLUDED")
        lit[idx[hits != -1]] = False
        geom = np.where(lit, cos_dist * (ref_mm**2) / (dist2 * np.sqrt(dist2)), 0)
        return inside, lit, u, geom.astype(dt, copy=False)


GLOSS_EXPONENT = 60.0  # Blinn-Phong exponent of the gloss shift's specular lobe: a narrow highlight
TEXTURE_CELL_MM = (0.9, 1.4)  # the texture shift's printed marks: a grid (x, y) on the parts


def texture_factor(points: np.ndarray, on_part: np.ndarray, contrast: float) -> np.ndarray:
    """Albedo factor (float32) of the printed marks: 1 - ``contrast`` on a mark of a part, 1
    elsewhere. The marks are the cells of a grid in world x, y (TEXTURE_CELL_MM) whose index
    sum is a multiple of three: sharp-edged blocks like labels and silkscreen."""
    i = np.floor(points[:, 0] / TEXTURE_CELL_MM[0]).astype(np.int64)
    j = np.floor(points[:, 1] / TEXTURE_CELL_MM[1]).astype(np.int64)
    mark = on_part & ((i + j) % 3 == 0)
    return np.where(mark, np.float32(1 - contrast), np.float32(1)).astype(np.float32)


def specular(
    points: np.ndarray,
    normals: np.ndarray,
    lit: np.ndarray,
    projector_centre: np.ndarray,
    camera_centre: np.ndarray,
    ref_mm: float,
) -> np.ndarray:
    """Blinn-Phong lobe (n . h)^GLOSS_EXPONENT of a projector seen from the camera, with the
    projector's fall-off (ref / distance)^2, on lit points; float32."""
    dt = points.dtype
    to_p = projector_centre.astype(dt) - points
    dist2 = np.einsum("ij,ij->i", to_p, to_p)
    to_c = camera_centre.astype(dt) - points
    half = to_p / np.sqrt(dist2)[:, None] + to_c / np.linalg.norm(to_c, axis=1, keepdims=True)
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    n_h = np.clip(np.einsum("ij,ij->i", normals, half), 0, 1)
    lobe = n_h**GLOSS_EXPONENT * (ref_mm**2 / dist2)
    return np.where(lit, lobe, 0).astype(np.float32)


def _pattern_harmonics(cfg: RenderConfig, n_terms: int = 12) -> np.ndarray:
    """Cosine-series coefficients a_h of (A + B cos phi)^gamma (exact for gamma = 1)."""
    if cfg.projector_gamma == 1.0:
        return np.array([cfg.fringe_offset, cfg.fringe_amplitude])
    phi = np.linspace(0, 2 * np.pi, 1024, endpoint=False)
    vals = np.clip(cfg.fringe_offset + cfg.fringe_amplitude * np.cos(phi), 0, None)
    spec = np.fft.rfft(vals**cfg.projector_gamma) / len(phi)
    a = spec.real[:n_terms] * 2
    a[0] /= 2
    return a


def _gaussian_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian blur over the last two axes with reflected borders."""
    r = max(1, int(math.ceil(3 * sigma)))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    for axis in (-1, -2):
        pad = [(0, 0)] * img.ndim
        pad[axis] = (r, r)
        padded = np.pad(img, pad, mode="reflect")
        n = img.shape[axis]
        img = sum(w * np.take(padded, np.arange(i, i + n), axis=axis) for i, w in enumerate(k))
    return img


@dataclass
class Rendered:
    """What one scene render produces (arrays are H x W unless noted)."""

    depth_mm: np.ndarray  # float32 camera-axis z of the pixel-centre surface point
    lit: dict[str, np.ndarray]  # bool per view
    footprint: dict[str, np.ndarray]  # bool per view: inside that projector's frustum
    projector_coord: dict[str, np.ndarray]  # float32 projector px, NaN where unlit
    fringes: dict[str, np.ndarray]  # file name (see odmv.io.manifest) -> float32 image


@dataclass(frozen=True)
class SampleGrid:
    """Camera rays on a regular sub-pixel grid that contains every pixel centre.

    Odd ``ss``: ss x ss samples per pixel at (k + 1/2) / ss, equally weighted (midpoint rule).
    Even ``ss``: samples every 1/ss px including pixel borders, shared by neighbours, with
    trapezoid weights (1/2, 1, ..., 1, 1/2) / ss per axis. Either way each pixel's value is its
    area average, and sample ``ss // 2`` along each axis is the pixel-centre ray, which gives
    the ground truth without extra rays.
    """

    origins: np.ndarray  # (rows * cols) x 3 float32
    dirs: np.ndarray
    rows: int
    cols: int
    ss: int
    weights: np.ndarray  # 1D quadrature weights over one pixel, summing to 1
    centre: np.ndarray  # flat indices of the pixel-centre samples, row-major (H * W)

    def pixel_mean(self, x: np.ndarray) -> np.ndarray:
        """(..., rows * cols) samples -> (..., H, W) area averages."""
        x = x.reshape(*x.shape[:-1], self.rows, self.cols)
        n, s = len(self.weights), self.ss
        h, w = (self.rows - n) // s + 1, (self.cols - n) // s + 1
        x = sum(wk * x[..., k : k + s * (h - 1) + 1 : s, :] for k, wk in enumerate(self.weights))
        return sum(wk * x[..., k : k + s * (w - 1) + 1 : s] for k, wk in enumerate(self.weights))


@functools.lru_cache(maxsize=4)
def sample_grid(rig: Rig, height_px: int, width_px: int, ss: int) -> SampleGrid:
    """Cached: the rays depend on the rig and the resolution only."""
    cam = rig.camera_at(width_px, height_px)
    if ss % 2:
        weights = np.full(ss, 1 / ss, np.float32)
        ys = (np.arange(ss * height_px) + 0.5) / ss
        xs = (np.arange(ss * width_px) + 0.5) / ss
    else:
        weights = np.full(ss + 1, 1 / ss, np.float32)
        weights[[0, -1]] /= 2
        ys = np.arange(ss * height_px + 1) / ss
        xs = np.arange(ss * width_px + 1) / ss
    uu, vv = np.meshgrid(xs, ys)
    origin, dirs = cam.pixel_rays(np.stack([uu, vv], -1).reshape(-1, 2))
    origins = np.broadcast_to(origin.astype(np.float32), dirs.shape).copy()
    dirs = dirs.astype(np.float32)
    origins.flags.writeable = dirs.flags.writeable = False
    ci = np.arange(height_px) * ss + ss // 2
    cj = np.arange(width_px) * ss + ss // 2
    centre = (ci[:, None] * len(xs) + cj[None, :]).ravel()
    return SampleGrid(origins, dirs, len(ys), len(xs), ss, weights, centre)


def render_scene(
    scene: Scene,
    rig: Rig,
    height_px: int,
    width_px: int,
    fringe: FringeSpec,
    views: tuple[str, ...],
    cfg: RenderConfig,
    rng: np.random.Generator,
    images: str = "full",
    texture: float = 0.0,
    gloss: float = 0.0,
    dead_view: str | None = None,
) -> Rendered:
    """Render ground truth and fringe images of ``scene``. ``images='training'`` renders only
    the (train_frequency, train_step) image per view. The surface and failure shifts
    (odmv.sim.shifts): ``texture`` (contrast of printed marks on the parts), ``gloss`` (the
    specular lobe's peak, in units of the projector's irradiance) and ``dead_view`` (a projector
    that gives no light); the ground truth does not change with them."""
    cam = rig.camera_at(width_px, height_px)
    projectors = rig.projectors()
    ref = rig.projector.distance_mm
    caster = RayCaster(scene)
    H, W, ss = height_px, width_px, cfg.supersample

    grid = sample_grid(rig, H, W, ss)
    # float32 keeps projector columns to ~1e-4 px for image formation and lit tests
    pts, nrm, albedo, prim = caster.intersect(grid.origins, grid.dirs)
    if (prim < 0).any():
        raise ValueError(
            f"{(prim < 0).sum()} camera rays hit nothing; the ground plane must fill the view"
        )
    if texture:
        albedo = albedo * texture_factor(pts, prim >= 2, texture)  # faces 0, 1: the ground
    # ground truth from the pixel-centre samples, hit points refined in float64
    c = grid.centre
    exact = caster.exact_points(grid.origins[c], grid.dirs[c], prim[c])
    depth = cam.depth(exact).reshape(H, W).astype(np.float32)
    shadow_origins = pts + np.float32(cfg.shadow_epsilon_mm) * nrm
    u_all, geom_all, spec_all, lit_gt, foot_gt, coord_gt = {}, {}, {}, {}, {}, {}
    for v in views:
        inside, lit, u_all[v], geom_all[v] = caster.lit_by(
            pts, nrm, projectors[v], ref, shadow_origins
        )
        if gloss:
            spec_all[v] = np.float32(gloss) * specular(
                pts, nrm, lit, projectors[v].center, cam.center, ref
            )
        lit_gt[v] = lit[c].reshape(H, W)
        foot_gt[v] = inside[c].reshape(H, W)
        u_exact = projectors[v].project(exact)[:, 0]
        coord = np.where(lit[c], u_exact, np.nan)
        coord_gt[v] = coord.reshape(H, W).astype(np.float32)

    harm = _pattern_harmonics(cfg)
    if images == "training":
        freqs = [fringe.resolve_frequency(fringe.train_frequency)]
        steps = [fringe.train_step]
    else:
        freqs, steps = list(range(len(fringe.periods_px))), list(range(fringe.steps))

    pixel_mean = grid.pixel_mean

    base = pixel_mean(albedo * np.float32(cfg.ambient))
    if cfg.defocus_sigma_px > 0:
        base = _gaussian_blur(base, cfg.defocus_sigma_px)
    hs = np.arange(len(harm))
    deltas = 2 * np.pi * np.asarray(steps)[:, None] / fringe.steps
    w_cos = (harm * np.cos(hs * deltas)).astype(np.float32)  # steps x harmonics
    w_sin = (harm * np.sin(hs * deltas)).astype(np.float32)
    fringes = {}
    for v in views:
        u, geom = u_all.pop(v), geom_all.pop(v)
        g = albedo * (np.float32(cfg.projector_irradiance) * geom)
        if v in spec_all:  # highlights are the light's colour, not the surface's
            g = g + np.float32(cfg.projector_irradiance) * spec_all.pop(v)
        if v == dead_view:
            g = np.zeros_like(g)
        for fi in freqs:
            phi = (2 * np.pi / fringe.periods_px[fi]) * u
            c1, s1 = np.cos(phi), np.sin(phi)
            sums_c, sums_s = [g], [np.zeros_like(g)]
            ch, sh = c1, s1
            for _ in hs[1:]:  # g * cos/sin(h phi) by the angle-addition recurrence
                sums_c.append(g * ch)
                sums_s.append(g * sh)
                ch, sh = ch * c1 - sh * s1, sh * c1 + ch * s1
            C, S = pixel_mean(np.stack(sums_c)), pixel_mean(np.stack(sums_s))
            if cfg.defocus_sigma_px > 0:
                C, S = (
                    _gaussian_blur(C, cfg.defocus_sigma_px),
                    _gaussian_blur(S, cfg.defocus_sigma_px),
                )
            stack = np.einsum("nh,hyx->nyx", w_cos, C) - np.einsum("nh,hyx->nyx", w_sin, S)
            stack = _sensor(stack + base, cfg, rng)
            for n, img in zip(steps, stack, strict=True):
                fringes[fringe_name(v, fi, n)] = img
        if images == "full" and fringe.uniform:
            white = np.float32((cfg.fringe_offset + cfg.fringe_amplitude) ** cfg.projector_gamma)
            G = pixel_mean(g)
            if cfg.defocus_sigma_px > 0:
                G = _gaussian_blur(G, cfg.defocus_sigma_px)
            fringes[uniform_name(v)] = _sensor(white * G + base, cfg, rng)
    return Rendered(depth, lit_gt, foot_gt, coord_gt, fringes)


def _sensor(signal: np.ndarray, cfg: RenderConfig, rng: np.random.Generator) -> np.ndarray:
    """Poisson-Gaussian noise (variance = signal * scale / full_well + read^2), then clipping."""
    out = signal.astype(np.float32)
    if cfg.noisy:
        var = cfg.read_noise**2 + (
            np.clip(out, 0, None) * cfg.saturation / cfg.full_well_e if cfg.full_well_e > 0 else 0
        )
        out = out + np.sqrt(var).astype(np.float32) * rng.standard_normal(out.shape, np.float32)
    return np.clip(out, 0, cfg.saturation)

"""Ray-cast rendering of the four-projector rig (Embree through embreex, called directly).

Image formation for projector k, phase step n of a sequence with period P (projector px):

    I = albedo * (ambient + E_k * cos(theta_k) * (d_ref / d_k)^2 * lit_k * pattern(u_k))
    pattern(u) = (A + B cos(2 pi u / P + 2 pi n / N)) ** gamma_projector

where u_k is the projector column hit by the surface point (the phase axis of every projector),
theta_k the angle between the surface normal and the direction to the projector, d_k the
distance to the projector centre and lit_k is 1 iff the point is inside the projector frustum,
faces it and nothing blocks the segment to its centre (exact shadows from occlusion rays).

Anti-aliasing integrates each pixel over ss x ss sub-pixel rays. Because the pattern is a
Fourier series in the phase, each pixel's integral reduces to a few per-pixel sums (of
albedo * irradiance * cos(h phi) and * sin(h phi)), from which every phase step is an exact
linear combination: 148 images cost little more than one. Defocus (Gaussian blur of the optical
image), sensor noise (Poisson-Gaussian, heteroscedastic Gaussian approximation) and saturation
are applied in that order at the output resolution. Ground truth (depth, lit masks, projector
coordinates) comes from the ray through each pixel centre and is never blended across edges.
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

    supersample: int = 2  # sub-pixel rays per axis (area-averaged)
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

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, exact: bool):
        """First hits of rays (R x 3 float32 origins and unit directions).

        ``exact``: refine hit points in float64 on the hit triangle's plane (ground truth);
        otherwise points are float32 from Embree's hit distance (image formation). Returns
        points, unit normals facing the ray origin, albedo and a hit mask.
        """
        res = self._embree.run(origins, dirs, output=1)
        prim = res["primID"]
        hit = prim >= 0
        p = np.where(hit, prim, 0)
        if exact:
            n = self.normals[p]
            o, d = origins.astype(np.float64), dirs.astype(np.float64)
            t = (self.offsets[p] - np.einsum("ij,ij->i", n, o)) / np.einsum("ij,ij->i", n, d)
        else:
            n = self.normals32[p]
            o, d, t = origins, dirs, np.where(hit, res["tfar"], 0)
        pts = o + t[:, None] * d
        flip = np.einsum("ij,ij->i", n, d) > 0
        n[flip] *= -1
        return pts, n, np.where(hit, self.albedo[p], 0), hit

    def lit_by(
        self,
        pts: np.ndarray,
        normals: np.ndarray,
        proj: Projector,
        ref_mm: float,
        shadow_origins: np.ndarray,
    ):
        """Per point: lit mask (frustum, facing and unshadowed), projector column u, and the
        geometric irradiance factor cos(theta) * (ref / distance)^2 (0 where unlit).

        ``shadow_origins`` are the points nudged off their surface along the normal (float32).
        """
        dt = pts.dtype
        cam = pts @ proj.R.T.astype(dt) + proj.t.astype(dt)
        z = cam[:, 2]
        inv_z = 1 / np.where(z > 0, z, 1)
        u = (proj.K[0, 0] * cam[:, 0]) * inv_z + proj.K[0, 2]
        v = (proj.K[1, 1] * cam[:, 1]) * inv_z + proj.K[1, 2]
        inside = (z > 0) & (u >= 0) & (u < proj.width_px) & (v >= 0) & (v < proj.height_px)
        to_p = proj.center.astype(dt) - pts
        dist2 = np.einsum("ij,ij->i", to_p, to_p)
        cos_dist = np.einsum("ij,ij->i", normals, to_p)  # cos(theta) * distance
        lit = inside & (cos_dist > 0)
        # Shadow rays with unnormalized directions: t = 1 is the projector centre; stopping at
        # 1 - 1e-6 (~0.2 um short) skips nothing real. Zero length where already unlit.
        to_c = proj.center.astype(np.float32) - shadow_origins
        far = np.where(lit, np.float32(1 - 1e-6), np.float32(0))
        lit &= self._embree.run(shadow_origins, to_c, dists=far, query="OCCLUDED") == -1
        geom = np.where(lit, cos_dist * (ref_mm**2) / (dist2 * np.sqrt(dist2)), 0)
        return lit, u, geom.astype(dt, copy=False)


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
    projector_coord: dict[str, np.ndarray]  # float32 projector px, NaN where unlit
    fringes: dict[str, np.ndarray]  # file name (see odmv.io.manifest) -> float32 image


@functools.lru_cache(maxsize=4)
def camera_rays(rig: Rig, height_px: int, width_px: int, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and unit directions (float32) for ss x ss sub-pixel samples per pixel, ordered
    (row, column, sample); ss = 1 gives the pixel-centre rays. Cached: they depend on the rig only.
    """
    cam = rig.camera_at(width_px, height_px)
    offs = (np.arange(ss) + 0.5) / ss
    jj, ii = np.meshgrid(np.arange(width_px), np.arange(height_px))
    sy, sx = np.meshgrid(offs, offs, indexing="ij")
    uv = np.stack([jj[..., None] + sx.ravel(), ii[..., None] + sy.ravel()], -1)
    origin, dirs = cam.pixel_rays(uv.reshape(-1, 2))
    origins = np.broadcast_to(origin.astype(np.float32), dirs.shape).copy()
    dirs = dirs.astype(np.float32)
    origins.flags.writeable = dirs.flags.writeable = False
    return origins, dirs


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
) -> Rendered:
    """Render ground truth and fringe images of ``scene``. ``images='training'`` renders only
    the (train_frequency, train_step) image per view."""
    cam = rig.camera_at(width_px, height_px)
    projectors = rig.projectors()
    ref = rig.projector.distance_mm
    caster = RayCaster(scene)
    H, W, ss = height_px, width_px, cfg.supersample

    # ground truth from the pixel-centre rays
    eps = cfg.shadow_epsilon_mm
    pts, nrm, _, hit = caster.intersect(*camera_rays(rig, H, W, 1), exact=True)
    if not hit.all():
        raise ValueError(
            f"{(~hit).sum()} camera rays hit nothing; the ground plane must fill the view"
        )
    depth = cam.depth(pts).reshape(H, W).astype(np.float32)
    # lit tests and projector columns in float32 (~1e-4 px), depth above in float64
    pts32, nrm32 = pts.astype(np.float32), nrm.astype(np.float32)
    shadow_origins = pts32 + np.float32(eps) * nrm32
    lit_gt, coord_gt = {}, {}
    for v in views:
        lit, u, _ = caster.lit_by(pts32, nrm32, projectors[v], ref, shadow_origins)
        lit_gt[v] = lit.reshape(H, W)
        coord_gt[v] = np.where(lit, u, np.nan).reshape(H, W).astype(np.float32)

    # sub-pixel rays: per-pixel sums from which every phase step follows linearly
    # float32 keeps projector coordinates to ~1e-4 px here and halves the memory traffic
    pts, nrm, albedo, _ = caster.intersect(*camera_rays(rig, H, W, ss), exact=False)
    albedo = albedo.astype(np.float32)
    shadow_origins = pts + np.float32(eps) * nrm
    harm = _pattern_harmonics(cfg)
    if images == "training":
        freqs = [fringe.resolve_frequency(fringe.train_frequency)]
        steps = [fringe.train_step]
    else:
        freqs, steps = list(range(len(fringe.periods_px))), list(range(fringe.steps))

    def pixel_mean(x):  # (..., H*W*ss*ss) -> (..., H, W), summing strided sample slices
        x = x.reshape(*x.shape[:-1], H * W, ss * ss)
        return (sum(x[..., i] for i in range(ss * ss)) / (ss * ss)).reshape(*x.shape[:-2], H, W)

    base = pixel_mean(albedo * np.float32(cfg.ambient))
    if cfg.defocus_sigma_px > 0:
        base = _gaussian_blur(base, cfg.defocus_sigma_px)
    hs = np.arange(len(harm))
    deltas = 2 * np.pi * np.asarray(steps)[:, None] / fringe.steps
    w_cos = (harm * np.cos(hs * deltas)).astype(np.float32)  # steps x harmonics
    w_sin = (harm * np.sin(hs * deltas)).astype(np.float32)
    fringes = {}
    for v in views:
        _, u, geom = caster.lit_by(pts, nrm, projectors[v], ref, shadow_origins)
        g = albedo * (np.float32(cfg.projector_irradiance) * geom)
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
    return Rendered(depth, lit_gt, coord_gt, fringes)


def _sensor(signal: np.ndarray, cfg: RenderConfig, rng: np.random.Generator) -> np.ndarray:
    """Poisson-Gaussian noise (variance = signal * scale / full_well + read^2), then clipping."""
    out = signal.astype(np.float32)
    if cfg.noisy:
        var = cfg.read_noise**2 + (
            np.clip(out, 0, None) * cfg.saturation / cfg.full_well_e if cfg.full_well_e > 0 else 0
        )
        out = out + np.sqrt(var).astype(np.float32) * rng.standard_normal(out.shape, np.float32)
    return np.clip(out, 0, cfg.saturation)

"""A metric, richly textured synthetic seafloor (pure numpy, seeded).

World frame (metres): a right-handed frame with **z up**, the mean seafloor at z = 0 and the
scene centred on the origin: x ∈ [−size_x/2, size_x/2], y ∈ [−size_y/2, size_y/2]. The floor is a
height field z = h(x, y) triangulated on a regular grid.

Texture mapping is planar: ``uv = ((x − x_min) / size_x, (y − y_min) / size_y)`` and texel
(row r, column c) of the (Ht, Wt, 3) texture covers u ∈ [c/Wt, (c+1)/Wt], v ∈ [r/Ht, (r+1)/Ht]
(its centre is at x = x_min + (c + 0.5) size_x / Wt, y = y_min + (r + 0.5) size_y / Ht).
Texture values are linear RGB albedo in [0, 1].
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

#: Linear-RGB albedos of the seafloor materials (before the water's own colour is applied).
SEDIMENT_PALETTE: tuple[tuple[float, float, float], ...] = (
    (0.42, 0.46, 0.36),  # pale sand
    (0.26, 0.34, 0.28),  # greenish silt
    (0.30, 0.30, 0.26),  # grey mud
    (0.18, 0.30, 0.30),  # blue-green algal film
)
PEBBLE_PALETTE: tuple[tuple[float, float, float], ...] = (
    (0.55, 0.55, 0.48),
    (0.12, 0.16, 0.14),
    (0.38, 0.30, 0.22),
    (0.22, 0.38, 0.40),
    (0.65, 0.68, 0.62),
    (0.30, 0.42, 0.24),
)
ROCK_RGB = (0.24, 0.26, 0.27)
#: Albedo range of pale clutter (near-white shell and mineral fragments).
PALE_ALBEDO = (0.6, 0.9)


@dataclass(frozen=True)
class SceneOptions:
    """Size and roughness of the synthetic seafloor."""

    size_m: tuple[float, float] = (8.0, 8.0)  # extent along x and y, metres
    resolution_m: float = 0.02  # grid spacing of the height field (2 triangles per cell)
    relief_m: float = 0.4  # peak-to-peak height of the fractal terrain; boulders add ~0.6×
    n_boulders: int = 7
    texture_px: int = 4096  # texels along the longer side
    n_pebbles: int = 30000  # painted pebbles at texture_px = 4096 (scaled with texel count)
    #: pale clutter (mineral speckle, shell hash): patches per square metre, 0 = none; drawn
    #: from their own random stream, so the rest of the scene is the same with or without them
    pale_patches_per_m2: float = 0.0
    pale_patch_diameter_m: tuple[float, float] = (0.008, 0.04)  # log-uniform
    seed: int = 0


@dataclass(frozen=True)
class Scene:
    """A textured triangle mesh in metric world coordinates (z up)."""

    vertices: F64  # (V, 3) metres
    triangles: NDArray[np.int32]  # (F, 3) vertex indices, counter-clockwise seen from +z
    uv: F64  # (V, 2) texture coordinates in [0, 1]
    texture: F32  # (Ht, Wt, 3) linear RGB albedo
    normals: F64  # (V, 3) unit vertex normals

    @property
    def bounds(self) -> tuple[F64, F64]:
        """(min xyz, max xyz) of the vertices, metres."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    @property
    def texel_size_m(self) -> float:
        """Mean texel footprint in metres along x (planar mapping)."""
        lo, hi = self.bounds
        return float((hi[0] - lo[0]) / self.texture.shape[1])


@dataclass(frozen=True)
class _Boulder:
    center_xy: F64  # (2,)
    radii: F64  # (2,) semi-axes, metres
    angle: float  # radians
    height: float  # metres above the local terrain


def fractal_noise(rng: np.random.Generator, shape: tuple[int, int], min_cells: int,
                  max_cells: int, roughness: float = 0.6) -> F32:
    """(H, W) zero-mean noise: octaves of bicubic-upsampled random grids, unit std.

    Octave k has 2^k·min_cells cells along the longer side and amplitude roughness^k.
    """
    h, w = shape
    out = np.zeros(shape, dtype=np.float32)
    cells, amp = min_cells, 1.0
    while cells <= max_cells:
        ch = max(2, round(cells * h / max(h, w)))
        cw = max(2, round(cells * w / max(h, w)))
        grid = rng.standard_normal((ch, cw)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        cells, amp = cells * 2, amp * roughness
    out -= out.mean()
    std = float(out.std())
    return out / std if std > 0 else out


def _make_boulders(rng: np.random.Generator, options: SceneOptions) -> list[_Boulder]:
    """Random boulders placed away from the scene border."""
    sx, sy = options.size_m
    out = []
    for _ in range(options.n_boulders):
        r = rng.uniform(0.15, 0.45)
        out.append(_Boulder(
            center_xy=np.array([rng.uniform(-0.4, 0.4) * sx, rng.uniform(-0.4, 0.4) * sy]),
            radii=np.array([r, r * rng.uniform(0.6, 1.0)]),
            angle=float(rng.uniform(0, np.pi)),
            height=float(options.relief_m * rng.uniform(0.5, 1.0) * r / 0.3),
        ))
    return out


def _boulder_field(boulders: list[_Boulder], xs: F64, ys: F64) -> tuple[F64, F64]:
    """Boulder height above terrain and a 0..1 rock mask (each (ny, nx)) on the grid xs × ys.

    ``xs`` (nx,) and ``ys`` (ny,) are increasing world coordinates; each boulder touches only
    the grid cells inside its bounding box.
    """
    height = np.zeros((len(ys), len(xs)))
    mask = np.zeros_like(height)
    for b in boulders:
        r = float(b.radii.max())
        i0, i1 = np.searchsorted(ys, b.center_xy[1] - r), np.searchsorted(ys, b.center_xy[1] + r)
        j0, j1 = np.searchsorted(xs, b.center_xy[0] - r), np.searchsorted(xs, b.center_xy[0] + r)
        if i0 >= i1 or j0 >= j1:
            continue
        dx = (xs[j0:j1] - b.center_xy[0])[None, :]
        dy = (ys[i0:i1] - b.center_xy[1])[:, None]
        c, s = np.cos(b.angle), np.sin(b.angle)
        u = (c * dx + s * dy) / b.radii[0]
        v = (-s * dx + c * dy) / b.radii[1]
        q = np.clip(1.0 - (u * u + v * v), 0.0, None)
        box = (slice(i0, i1), slice(j0, j1))
        height[box] = np.maximum(height[box], b.height * q**0.7)
        mask[box] = np.maximum(mask[box], np.clip(q * 8.0, 0.0, 1.0))
    return height, mask


def _height_field(rng: np.random.Generator, options: SceneOptions, x: F64, y: F64,
                  boulders: list[_Boulder]) -> F64:
    """Terrain heights (metres) on the grid: fractal relief + sand ripples + boulders."""
    ny, nx = x.shape
    n_cells = max(4, round(max(options.size_m) / 0.1))  # finest octave ~10 cm
    terrain = fractal_noise(rng, (ny, nx), 2, n_cells, roughness=0.5).astype(np.float64)
    p2p = float(terrain.max() - terrain.min())
    terrain *= options.relief_m / p2p if p2p > 0 else 0.0
    terrain -= terrain.mean()
    ripple_dir = rng.uniform(0, np.pi)
    phase = x * np.cos(ripple_dir) + y * np.sin(ripple_dir)
    envelope = 0.5 + 0.5 * fractal_noise(rng, (ny, nx), 2, 4).astype(np.float64)
    ripples = 0.012 * np.sin(2 * np.pi * phase / 0.35) * np.clip(envelope, 0, 1)
    rock, _ = _boulder_field(boulders, x[0], y[:, 0])
    return terrain + ripples + rock


def _grid_triangles(nx: int, ny: int) -> NDArray[np.int32]:
    """(2·(nx−1)(ny−1), 3) triangles of a row-major nx × ny vertex grid, CCW from +z."""
    idx = np.arange(nx * ny, dtype=np.int32).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def vertex_normals(vertices: F64, triangles: NDArray[np.integer]) -> F64:
    """(V, 3) area-weighted unit vertex normals."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    fn = np.cross(b - a, c - a)  # length = 2 × area
    out = np.zeros_like(vertices)
    for k in range(3):
        for ax in range(3):
            out[:, ax] += np.bincount(triangles[:, k], weights=fn[:, ax], minlength=len(vertices))
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.asarray(np.divide(out, norm, out=np.zeros_like(out), where=norm > 0))


def _texel_centres(options: SceneOptions, shape: tuple[int, int]) -> tuple[F64, F64]:
    """World x (Wt,) and y (Ht,) of the texel centres."""
    ht, wt = shape
    sx, sy = options.size_m
    return (-sx / 2 + (np.arange(wt) + 0.5) * sx / wt, -sy / 2 + (np.arange(ht) + 0.5) * sy / ht)


def _paint_pebbles(rng: np.random.Generator, tex: F32, n: int) -> None:
    """Draw n pebbles (filled ellipses with a dark shadow rim) into the texture, in place."""
    ht, wt = tex.shape[:2]
    scale = max(ht, wt) / 4096.0
    radii = np.clip(1.5 * (1.0 - rng.random(n)) ** (-1.0 / 1.6), 1.5, 40.0) * max(scale, 0.35)
    centres = rng.random((n, 2)) * [wt, ht]
    colours = np.asarray(PEBBLE_PALETTE)[rng.integers(0, len(PEBBLE_PALETTE), n)]
    colours = colours * rng.uniform(0.5, 1.4, (n, 1))
    aspect = rng.uniform(0.45, 1.0, n)
    angles = rng.uniform(0.0, 180.0, n)
    for i in range(n):
        cx, cy = int(round(centres[i, 0])), int(round(centres[i, 1]))
        ax = (max(1, int(round(radii[i]))), max(1, int(round(radii[i] * aspect[i]))))
        rim = (ax[0] + 1 + ax[0] // 6, ax[1] + 1 + ax[1] // 6)
        shadow = tuple(float(v) for v in 0.35 * tex[min(cy, ht - 1), min(cx, wt - 1)])
        cv2.ellipse(tex, (cx + 1, cy + 1), rim, angles[i], 0, 360, shadow, -1)
        cv2.ellipse(tex, (cx, cy), ax, angles[i], 0, 360, tuple(float(v) for v in colours[i]), -1)


def _paint_speckles(rng: np.random.Generator, tex: F32, n: int) -> None:
    """Scatter single-texel bright and dark speckles (shell fragments, grains), in place."""
    ht, wt = tex.shape[:2]
    rows, cols = rng.integers(0, ht, n), rng.integers(0, wt, n)
    tex[rows, cols] *= rng.choice([0.3, 1.8], n)[:, None].astype(np.float32)


def _paint_pale_patches(rng: np.random.Generator, tex: F32, options: SceneOptions) -> None:
    """Scatter small pale patches (shell hash, mineral speckle) into the texture, in place.

    ``options.pale_patches_per_m2`` patches over the scene, diameters log-uniform in
    ``options.pale_patch_diameter_m``, elongated ellipses of a slightly warm or cool white
    (albedo in ``PALE_ALBEDO``), placed to a quarter texel (cv2's fixed-point ``shift``); the
    renderer's mip-mapping filters their edges.
    """
    sx, sy = options.size_m
    n = int(round(options.pale_patches_per_m2 * sx * sy))
    if n <= 0:
        return
    ht, wt = tex.shape[:2]
    texels_per_m = wt / sx
    lo, hi = np.log(options.pale_patch_diameter_m)
    diam_px = np.exp(rng.uniform(lo, hi, n)) * texels_per_m
    centres = rng.random((n, 2)) * [wt, ht]
    aspect = rng.uniform(0.4, 1.0, n)
    angles = rng.uniform(0.0, 180.0, n)
    level = rng.uniform(*PALE_ALBEDO, n)
    tint = rng.uniform(-0.05, 0.05, n)
    sub = 4  # cv2 fixed-point shift of 2 bits: quarter-texel centres and axes
    for i in range(n):
        rgb = (level[i] * (1 + tint[i]), level[i], level[i] * (1 - tint[i]))
        axes = (max(1, int(round(sub * diam_px[i] / 2))),
                max(1, int(round(sub * aspect[i] * diam_px[i] / 2))))
        centre = (int(round(sub * centres[i, 0])), int(round(sub * centres[i, 1])))
        cv2.ellipse(tex, centre, axes, angles[i], 0, 360, rgb, -1, cv2.LINE_8, 2)


def _sediment(rng: np.random.Generator, shape: tuple[int, int], n_cells: int) -> F32:
    """(H, W, 3) smooth blend of the sediment palette (patches from 0.25 m to a few metres)."""
    palette = np.asarray(SEDIMENT_PALETTE, dtype=np.float32)
    weights = np.stack([np.exp(1.5 * fractal_noise(rng, shape, 2, n_cells)) for _ in palette])
    weights /= weights.sum(axis=0)
    return np.asarray(np.einsum("khw,kc->hwc", weights, palette), dtype=np.float32)


def _grain(rng: np.random.Generator, shape: tuple[int, int]) -> F32:
    """(H, W) sand grain: blurred random impulses at three scales (many small blobs), unit std."""
    out = np.zeros(shape, dtype=np.float32)
    for sigma, density in ((1.0, 0.06), (2.0, 0.02), (3.5, 0.008)):
        n = int(density * shape[0] * shape[1])
        imp = np.zeros(shape, dtype=np.float32)
        imp[rng.integers(0, shape[0], n), rng.integers(0, shape[1], n)] = rng.standard_normal(n)
        layer = cv2.GaussianBlur(imp, (0, 0), sigma)
        out += layer / max(float(layer.std()), 1e-12)
    return out / max(float(out.std()), 1e-12)


def make_texture(rng: np.random.Generator, options: SceneOptions,
                 boulders: list[_Boulder]) -> F32:
    """(Ht, Wt, 3) linear-RGB albedo rich in detail from the metre to the texel scale."""
    sx, sy = options.size_m
    wt = options.texture_px if sx >= sy else max(2, round(options.texture_px * sx / sy))
    ht = options.texture_px if sy >= sx else max(2, round(options.texture_px * sy / sx))
    n_cells_m = max(1, int(round(max(sx, sy))))  # about one cell per metre
    low = (max(2, ht // 8), max(2, wt // 8))  # low-frequency fields are made small, then upsampled
    tex = cv2.resize(_sediment(rng, low, 4 * n_cells_m), (wt, ht), interpolation=cv2.INTER_LINEAR)
    _paint_pebbles(rng, tex, int(options.n_pebbles * ht * wt / 4096**2))
    xs, ys = _texel_centres(options, (ht, wt))
    _, rock = _boulder_field(boulders, xs, ys)
    rows, cols = np.nonzero(rock.any(axis=1))[0], np.nonzero(rock.any(axis=0))[0]
    if len(rows):
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        m = rock[box][:, :, None].astype(np.float32)
        grain = fractal_noise(rng, m.shape[:2], 32, max(m.shape[:2]) // 4, 0.9)
        rock_tex = np.asarray(ROCK_RGB, np.float32) * (1.0 + 0.3 * grain)[:, :, None]
        tex[box] = tex[box] * (1.0 - m) + rock_tex * m
    detail = fractal_noise(rng, (ht, wt), 2 * n_cells_m, max(ht, wt) // 4, 0.8)
    detail *= 0.25
    detail += 0.3 * _grain(rng, (ht, wt))
    np.clip(detail, -1.0, 1.0, out=detail)
    tex *= (1.0 + detail + 0.5 * detail * detail)[:, :, None]  # ≈ exp(detail), cheaper
    _paint_speckles(rng, tex, ht * wt // 60)
    if options.pale_patches_per_m2 > 0:  # own stream: the draws above are unchanged
        _paint_pale_patches(np.random.default_rng([options.seed, 0x9A1E]), tex, options)
    np.clip(tex, 0.01, 0.95, out=tex)
    return tex


def make_scene(options: SceneOptions) -> Scene:
    """A rough, textured seafloor in metres (world z up, mean floor at z = 0)."""
    if options.resolution_m <= 0 or min(options.size_m) <= 0:
        raise ValueError("size_m and resolution_m must be positive")
    rng = np.random.default_rng(options.seed)
    sx, sy = options.size_m
    nx = int(round(sx / options.resolution_m)) + 1
    ny = int(round(sy / options.resolution_m)) + 1
    xs, ys = np.linspace(-sx / 2, sx / 2, nx), np.linspace(-sy / 2, sy / 2, ny)
    x, y = np.meshgrid(xs, ys)
    boulders = _make_boulders(rng, options)
    z = _height_field(rng, options, x, y, boulders)
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    triangles = _grid_triangles(nx, ny)
    uv = np.column_stack([(x.ravel() + sx / 2) / sx, (y.ravel() + sy / 2) / sy])
    texture = make_texture(rng, options, boulders)
    logger.debug("scene: %d vertices, %d triangles, texture %s", len(vertices), len(triangles),
                 texture.shape)
    return Scene(vertices=vertices, triangles=triangles, uv=uv, texture=texture,
                 normals=vertex_normals(vertices, triangles))


def make_plane_scene(size_m: tuple[float, float], texture: F32, z: float = 0.0) -> Scene:
    """A flat textured rectangle z = ``z`` centred on the origin (two triangles)."""
    sx, sy = size_m
    vertices = np.array([[-sx / 2, -sy / 2, z], [sx / 2, -sy / 2, z],
                         [-sx / 2, sy / 2, z], [sx / 2, sy / 2, z]], dtype=np.float64)
    triangles = _grid_triangles(2, 2)
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    return Scene(vertices=vertices, triangles=triangles, uv=uv,
                 texture=np.asarray(texture, dtype=np.float32),
                 normals=np.tile([0.0, 0.0, 1.0], (4, 1)))

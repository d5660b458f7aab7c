"""Steps of a frame that place things relative to the spots: clutter, snow, glints, hot
spots, laser-lit particles, and the spots themselves (used by :func:`.conditions.render_frame`).

Counts are given per 1920×1080 image and scaled with the image area; distances in pixels at
1920 px width are scaled with the image width (``scale``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.synthetic.underwater import beams as beams_mod
from sfm_laserscale.synthetic.underwater import optics, particles, spectra, water
from sfm_laserscale.synthetic.underwater.layout import Layout
from sfm_laserscale.synthetic.underwater.optics import CameraModel
from sfm_laserscale.synthetic.underwater.seafloor import Lamp
from sfm_laserscale.synthetic.underwater.surface import intersect, point_m

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
#: reference image area for counts (1920 x 1080)
REF_AREA = 1920.0 * 1080.0
#: pale clutter and snow keep this far (px at 1920 wide) from true spot centres
SPOT_CLEARANCE_PX = 10.0
#: laser-coloured specks keep this far (px at 1920 wide) from every beam's image line
SPECK_BEAM_CLEARANCE_PX = 40.0


@dataclass(frozen=True)
class Context:
    """What placement needs to know: camera, layout, true spots, beam image lines."""

    cam: CameraModel
    layout: Layout
    truths: list[tuple[float, float]]  # visible spots of lasers that are on
    near_lines: list[F64]  # each beam's image from 0.5 m to its hit (where it glows)
    far_lines: list[F64]  # each beam's image from 0.3 to 12 m (keep-away zone)

    @property
    def scale(self) -> float:
        """Image width / 1920."""
        return self.cam.width / 1920.0

    @property
    def area_factor(self) -> float:
        """Image area / (1920 x 1080)."""
        return self.cam.width * self.cam.height / REF_AREA


def make_context(cam: CameraModel, lay: Layout) -> Context:
    """Truths and beam lines of a layout."""
    truths = [tuple(map(float, lay.hits[b.name].truth_px)) for b in lay.beams
              if lay.on[b.name] and b.name in lay.hits]
    near, far = [], []
    for b in lay.beams:
        hit = lay.hits.get(b.name)
        end = hit.range_m if hit is not None else 12.0
        line = beams_mod.beam_polyline_px(b, cam, 0.5, max(end, 0.6))
        if len(line) > 1:
            near.append(line)
        line = beams_mod.beam_polyline_px(b, cam, 0.3, 12.0)
        if len(line) > 1:
            far.append(line)
    return Context(cam, lay, truths, near, far)  # type: ignore[arg-type]


def _count(rng: np.random.Generator, per_ref: tuple[int, int], ctx: Context, cap: int) -> int:
    return min(int(rng.integers(per_ref[0], per_ref[1] + 1) * ctx.area_factor), cap)


def clutter_discs(rng: np.random.Generator, ctx: Context, pale: bool, specks: bool,
                  speck_channels: tuple[int, ...]) -> tuple[list[particles.Disc],
                                                            dict[str, object]]:
    """Albedo patches: 200-600 pale patches (per 1920×1080) away from the spots, and 2-6
    laser-coloured specks away from every beam line."""
    discs: list[particles.Disc] = []
    meta: dict[str, object] = {}
    w, h = ctx.cam.width, ctx.cam.height
    if pale:
        n = _count(rng, (200, 600), ctx, 3500)
        xy = particles.random_positions(
            rng, n, w, h, lambda p: particles.distance_to_points(p, ctx.truths)
            > SPOT_CLEARANCE_PX * ctx.scale)
        pale_discs = particles.pale_clutter(rng, xy)
        discs += pale_discs
        meta["pale_clutter_count"] = len(pale_discs)
        meta["pale_clutter_sample"] = [[d.x, d.y, 2 * d.a_px] for d in pale_discs[:40]]
    if specks:
        n = int(rng.integers(2, 7))
        xy = particles.random_positions(
            rng, n, w, h, lambda p: (particles.distance_to_polylines(p, ctx.far_lines)
                                     > SPECK_BEAM_CLEARANCE_PX * ctx.scale)
            & (particles.distance_to_points(p, ctx.truths) > 60.0 * ctx.scale))
        channels = [speck_channels[int(rng.integers(len(speck_channels)))] for _ in xy]
        sp = [particles.coloured_specks(rng, p[None, :], ch)[0]
              for p, ch in zip(xy, channels, strict=True)]
        discs += sp
        meta["laser_specks"] = [[d.x, d.y, 2 * d.a_px, *d.rgb] for d in sp]
    return discs, meta


def hot_lamps(rng: np.random.Generator, ctx: Context) -> tuple[tuple[Lamp, ...], list[F64]]:
    """1-2 narrow lamps (cone sigma 3-7°) each aimed at a floor point 1.8-3 lobe sigmas from
    a true spot, so that the spot sits on the bright flank of the hot spot, not inside its
    clipped centre (anywhere when no laser is on). Returns the lamps and their aim pixels."""
    cam, sf = ctx.cam, ctx.layout.seafloor
    lamps, aims = [], []
    for _ in range(int(rng.integers(1, 3))):
        sigma = math.radians(rng.uniform(3.0, 7.0))
        lobe_px = sigma * cam.focal_px
        if ctx.truths:
            base = np.asarray(ctx.truths[int(rng.integers(len(ctx.truths)))])
            ang = rng.uniform(0, 2 * math.pi)
            aim = base + rng.uniform(1.8, 3.0) * lobe_px * np.array([math.cos(ang),
                                                                      math.sin(ang)])
        else:
            aim = np.array([rng.uniform(0.2, 0.8) * cam.width, rng.uniform(0.2, 0.8)
                            * cam.height])
        ray = optics.unproject_px(aim[None, :], cam)
        _, s, t, ok = intersect(sf, np.zeros(3), ray / np.linalg.norm(ray))
        if not ok[0]:
            continue
        target = point_m(sf, s, t)[0]
        pos = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.4, -0.1), 0.0])
        axis = (target - pos) / np.linalg.norm(target - pos)
        lamps.append(Lamp(position_m=pos, axis=axis, sigma_rad=sigma, intensity=1.0))
        aims.append(aim)
    return tuple(lamps), aims


def snow_discs(rng: np.random.Generator, ctx: Context, wat: water.WaterType
               ) -> list[particles.Disc]:
    """40-160 marine-snow particles (per 1920×1080); 20 % placed within 25 px of a beam's
    image line (a few of them next to the spot itself: overlapping its halo)."""
    n = _count(rng, (40, 160), ctx, 900)
    n_line = int(round(0.2 * n))
    xy = particles.random_positions(rng, n - n_line, ctx.cam.width, ctx.cam.height)
    near = particles.points_near_polylines(rng, n_line, ctx.near_lines, 25.0 * ctx.scale)
    if ctx.truths and n_line:
        k = max(1, n_line // 5)
        for i in range(k):
            base = np.asarray(ctx.truths[int(rng.integers(len(ctx.truths)))])
            ang = rng.uniform(0, 2 * math.pi)
            near[i] = base + rng.uniform(12.0, 40.0) * ctx.scale * np.array(
                [math.cos(ang), math.sin(ang)])
    xy = np.concatenate([xy, near]) if len(near) else xy
    paths, trans = water.transmission_table(wat)
    lamp = spectra.integrate_rgb(spectra.white_led_spectrum())
    colour = lamp / lamp.max() * np.array([np.interp(2.0, paths, trans[:, c]) for c in range(3)])
    discs = particles.marine_snow(rng, xy, colour / colour.max())
    return [d for d in discs if particles.distance_to_points(
        np.array([[d.x, d.y]]), ctx.truths)[0] > d.a_px + 4.0 * ctx.scale]


def glint_discs(rng: np.random.Generator, ctx: Context, wat: water.WaterType
                ) -> list[particles.Disc]:
    """10-40 specular glints (per 1920×1080), 30 % within 5-30 px of a beam line; all at
    least 12 px from the true spots."""
    n = _count(rng, (10, 40), ctx, 250)
    n_line = int(round(0.3 * n))
    xy = particles.random_positions(rng, n - n_line, ctx.cam.width, ctx.cam.height)
    near = particles.points_near_polylines(rng, n_line, ctx.near_lines, 30.0 * ctx.scale)
    xy = np.concatenate([xy, near]) if len(near) else xy
    keep = particles.distance_to_points(xy, ctx.truths) > 12.0 * ctx.scale
    paths, trans = water.transmission_table(wat)
    lamp = spectra.integrate_rgb(spectra.white_led_spectrum())
    dist = ctx.layout.seafloor.distance_m
    colour = lamp * np.array([np.interp(2 * dist, paths, trans[:, c]) for c in range(3)])
    return particles.glints(rng, xy[keep], colour / colour.max())


def laser_lit_discs(rng: np.random.Generator, ctx: Context) -> list[particles.Disc]:
    """1-2 particles inside beams 0.3-1.2 m from the rig, lit by the laser: defocused discs
    (thin-lens blur, aperture 6 mm, focused on the floor; diameter 8-40 px at 1920 wide) of
    the laser's colour, peak 0.1-0.6x white, on the beam's image line far from its spot."""
    out = []
    cam, lay = ctx.cam, ctx.layout
    on = [b for b in lay.beams if lay.on[b.name]]
    for _ in range(int(rng.integers(1, 3)) if on else 0):
        beam = on[int(rng.integers(len(on)))]
        a = rng.uniform(0.3, 1.2)
        p = beam.origin_m + a * beam.direction
        xy = optics.project_px(p[None, :], cam)[0]
        if not (20 <= xy[0] <= cam.width - 20 and 20 <= xy[1] <= cam.height - 20):
            continue
        if particles.distance_to_points(xy[None, :], ctx.truths)[0] < 40.0 * ctx.scale:
            continue
        diam = cam.focal_px * 0.006 * abs(1.0 / p[2] - 1.0 / lay.seafloor.distance_m)
        diam = float(np.clip(diam, 8.0 * ctx.scale, 40.0 * ctx.scale))
        rgb = np.asarray(spectra.laser_rgb(beam.wavelength_nm)) * rng.uniform(0.1, 0.6)
        out.append(particles.Disc(float(xy[0]), float(xy[1]), diam / 2, diam / 2, 0.0,
                                  (float(rgb[0]), float(rgb[1]), float(rgb[2])), 0.2))
    return out

"""Named benchmark conditions and :func:`render_frame`: one underwater laser-scaler photograph.

A frame is made in this order (every random draw from the ``numpy.random.Generator`` given):

1. camera (:func:`.optics.random_camera`), laser wavelength and water type of the condition;
2. geometry (:func:`.layout.sample_layout`): seafloor, rig, beams, true spot centres;
3. the lit seafloor (:func:`.seafloor.render_seafloor`) with pale clutter and laser-coloured
   specks painted into its albedo, two vehicle lamps (and narrow hot-spot lamps);
4. camera settings, auto-exposure on the median output green (:func:`.sensor.auto_exposure`),
   hot-spot strength, the water's forward scatter over the scene (a fraction
   ``1 - exp(-b_s r)`` of the light spread by the halo kernel);
5. additive light in exposed units: marine snow, laser-lit particles, glints;
6. the laser spots (:func:`.beams.render_spot`, scaled to their peak/white) and the beams'
   glow in the water (:func:`.beams.glow_line`), both rendered with the optical PSF;
7. the camera (:func:`.sensor.capture`): lens (the spots are added after its PSF), Bayer
   sensor, noise, processing, JPEG.

The table of conditions is :data:`CONDITIONS` (name -> :class:`Condition`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.synthetic.underwater import beams as beams_mod
from sfm_laserscale.synthetic.underwater import (
    compose,
    layout,
    optics,
    particles,
    sensor,
    spectra,
    texture,
    water,
)
from sfm_laserscale.synthetic.underwater.seafloor import Lamp, render_seafloor

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
Range = tuple[float, float]
#: a spot whose background (exposed scene light around it) is at least this (x white) in every
#: channel where the laser gives at least MIN_VISIBLE_CROSSTALK of its response is in a
#: clipped region: not visible, its truth is None
CLIPPED_BACKGROUND = 0.95
MIN_VISIBLE_CROSSTALK = 0.05


@dataclass(frozen=True)
class Condition:
    """How the frames of one benchmark condition are made (ranges are sampled uniformly
    per frame, peaks log-uniformly per spot)."""

    name: str
    description: str
    wavelengths_nm: tuple[float, ...] = (532.0,)
    waters: tuple[str, ...] = ("neutral",)
    peak_over_white: Range = (1.5, 8.0)
    geometry: layout.GeometrySpec = field(default_factory=layout.GeometrySpec)
    exposure_green: Range = (0.35, 0.55)  # median output green, 0-1
    pale_clutter: bool = False
    laser_specks: bool = False
    marine_snow: bool = False
    laser_lit_particles: bool = False
    hotspots: bool = False
    glints: bool = False
    jpeg_quality: tuple[int, int] = (80, 95)
    noise_gain: Range = (1.0, 2.0)  # ISO gain: the full well is divided by it
    sharpen: Range = (0.0, 0.3)
    motion_blur_px: Range | None = None
    defocus_radius_px: Range | None = None
    speckle_contrast: Range = (0.1, 0.35)
    lasers_on: bool = True
    beam_glow: bool = True  # the beams' in-water glow lines (physics: always there, faint
    #                         in clear water); False removes them


def _conditions() -> dict[str, Condition]:
    g = layout.GeometrySpec
    rows = [
        Condition("clipped_cores", "green 532 nm beams, peaks 5-50x white: clipped white "
                  "cores, green halo, speckle, neutral water", peak_over_white=(5.0, 50.0)),
        Condition("green_water", "green beams in green-cyan coastal water (median G 60-80 %), "
                  "peaks 0.5-5x white, 1.5-4.5 m", waters=("green_coastal",),
                  peak_over_white=(0.5, 5.0), exposure_green=(0.6, 0.8),
                  geometry=g(distance_m=(1.5, 4.5))),
        Condition("pale_clutter", "green beams, neutral water, hundreds of pale specks 2-10 px "
                  "and a few green organisms away from the beams", pale_clutter=True,
                  laser_specks=True, peak_over_white=(1.5, 20.0)),
        Condition("camera_output", "green beams; Bayer, high-ISO noise, sharpening, JPEG q "
                  "70-80 4:2:0", jpeg_quality=(70, 80), noise_gain=(3.0, 8.0),
                  sharpen=(0.3, 0.8), peak_over_white=(1.5, 20.0)),
        Condition("green_all", "clipped cores and faint spots in green-cyan water with pale "
                  "clutter, green organisms, JPEG 70-95", waters=("green_coastal",),
                  peak_over_white=(0.5, 50.0), exposure_green=(0.6, 0.8), pale_clutter=True,
                  laser_specks=True, jpeg_quality=(70, 95), noise_gain=(1.0, 4.0),
                  sharpen=(0.0, 0.6), geometry=g(distance_m=(1.5, 4.5))),
        Condition("red_blue_water", "red 638 nm beams in clear blue oceanic water",
                  wavelengths_nm=(638.0,), waters=("blue_oceanic",),
                  peak_over_white=(1.0, 20.0)),
        Condition("blue_beams", "blue 450 nm beams, neutral or blue water",
                  wavelengths_nm=(450.0,), waters=("neutral", "blue_oceanic"),
                  peak_over_white=(1.0, 20.0)),
        Condition("turbid_brown", "green or red beams in turbid brown water: strong "
                  "forward-scatter halos and beam glow, low contrast, 1.5-3 m",
                  wavelengths_nm=(532.0, 638.0), waters=("turbid_brown",),
                  peak_over_white=(1.0, 20.0), geometry=g(distance_m=(1.5, 3.0))),
        Condition("marine_snow", "green beams with marine snow, some on the beam lines, and "
                  "particles lit by the beams", marine_snow=True, laser_lit_particles=True,
                  peak_over_white=(1.5, 20.0)),
        Condition("strobe_hotspots", "green beams with lamp hot spots and specular glints, "
                  "some near the beam lines", hotspots=True, glints=True,
                  peak_over_white=(1.5, 20.0)),
        Condition("faint_far", "far spots (5-9 m) with peaks 0.3-1x white in green-cyan water",
                  waters=("green_coastal",), peak_over_white=(0.3, 1.0),
                  exposure_green=(0.6, 0.8), geometry=g(distance_m=(5.0, 9.0),
                                                        tilt_deg=(0.0, 25.0))),
        Condition("old_motion_blur", "green or red beams, motion blur 4-12 px",
                  wavelengths_nm=(532.0, 638.0), motion_blur_px=(4.0, 12.0)),
        Condition("old_defocus", "green or red beams, defocused frame (disc radius 2.5-6 px): "
                  "wide soft spots", wavelengths_nm=(532.0, 638.0),
                  defocus_radius_px=(2.5, 6.0), peak_over_white=(1.0, 4.0)),
        Condition("old_border", "green or red beams, spots 2-12 px from the image border, "
                  "partly cut", wavelengths_nm=(532.0, 638.0), geometry=g(at_border=True)),
        Condition("old_missing", "green or red beams, 1-2 of the 4 lasers switched off",
                  wavelengths_nm=(532.0, 638.0), geometry=g(lasers_off=(1, 2))),
        Condition("no_lasers", "no laser on: pale clutter, red and green organisms, glints, "
                  "marine snow (every reported spot is false)", lasers_on=False,
                  pale_clutter=True, laser_specks=True, glints=True, marine_snow=True),
        Condition("red_clean", "red 638 nm beams, mild cast, peaks 1.5-4x white (the old easy "
                  "case)", wavelengths_nm=(638.0,), peak_over_white=(1.5, 4.0)),
    ]
    return {c.name: c for c in rows}


#: the named benchmark conditions
CONDITIONS: dict[str, Condition] = _conditions()


@dataclass(frozen=True)
class Frame:
    """One rendered photograph and everything known about it.

    ``truth`` maps laser name -> true spot centre (x, y) in COLMAP pixels, or None when the
    spot is not in the image (laser off, or no spot) or cannot be seen (its background is
    clipped in every channel the laser shows in: inside a lamp hot spot or behind a bright
    particle; ``CLIPPED_BACKGROUND``).
    ``rig_toml`` is the rig as given to the detector (true beams + calibration error);
    ``camera_spec`` the COLMAP OPENCV camera. ``image_laser_free_rgb`` (with
    ``render_frame(..., laser_free=True)``): the same photograph, same noise, without the
    lasers' spots and glow.

    ``image_scene_rgb`` (with ``render_frame(..., scene_reference=True)``): the seafloor as a
    laser-free view of it would record it, pixel-aligned with this one: the same lit seafloor
    and camera, without the lasers, the lamp hot spots, the seafloor's forward-scatter veil
    and the particles of the water column (marine snow, glints: they do not stay in place
    between photographs), with its own noise draws and JPEG.
    """

    image_rgb: U8
    camera_spec: str
    rig_toml: str
    truth: dict[str, tuple[float, float] | None]
    meta: dict[str, Any]
    image_laser_free_rgb: U8 | None = None
    image_scene_rgb: U8 | None = None


def _log_uniform(rng: np.random.Generator, lo_hi: Range) -> float:
    return float(math.exp(rng.uniform(math.log(lo_hi[0]), math.log(lo_hi[1]))))


def vehicle_lamps(rng: np.random.Generator) -> tuple[Lamp, ...]:
    """Two broad-beam lamps 0.35-0.6 m left and right of the camera, slightly above it, aimed
    forward and 0-12° outwards (and 0-8° down); Gaussian cones of sigma 35-55°."""
    out = []
    for side in (-1.0, 1.0):
        pos = np.array([side * rng.uniform(0.35, 0.6), rng.uniform(-0.3, -0.1), 0.0])
        out_ang, down_ang = math.radians(rng.uniform(0.0, 12.0)), math.radians(rng.uniform(0, 8))
        aim = np.array([side * math.tan(out_ang), math.tan(down_ang), 1.0])
        out.append(Lamp(position_m=pos, axis=aim / np.linalg.norm(aim),
                        sigma_rad=math.radians(rng.uniform(35.0, 55.0)),
                        intensity=float(rng.uniform(0.8, 1.2))))
    return tuple(out)


def sensor_settings(rng: np.random.Generator, cond: Condition) -> sensor.SensorSettings:
    """Camera settings of a frame of this condition (PSF, noise, white balance for the lamps,
    colour matrix, JPEG quality, blur, glare, chromatic aberration, tone, sharpening)."""
    lamp = spectra.integrate_rgb(spectra.white_led_spectrum())
    gains = lamp[1] / lamp
    beta = rng.uniform(0.6, 1.0)
    ccm = np.eye(3) + beta * (np.asarray(sensor.BASE_CCM) - np.eye(3))
    gain_iso = rng.uniform(*cond.noise_gain)
    return sensor.SensorSettings(
        psf_sigma_px=float(rng.uniform(0.4, 0.8)),
        full_well_e=float(rng.uniform(6000.0, 12000.0) / gain_iso),
        read_noise_e=float(rng.uniform(2.0, 5.0)),
        wb_gains=(float(gains[0]), float(gains[1]), float(gains[2])),
        ccm=tuple((float(r[0]), float(r[1]), float(r[2])) for r in ccm),
        jpeg_quality=int(rng.integers(cond.jpeg_quality[0], cond.jpeg_quality[1] + 1)),
        motion_px=float(rng.uniform(*cond.motion_blur_px)) if cond.motion_blur_px else 0.0,
        motion_angle_rad=float(rng.uniform(0.0, math.pi)),
        defocus_radius_px=(float(rng.uniform(*cond.defocus_radius_px))
                           if cond.defocus_radius_px else 0.0),
        glare_fraction=float(rng.uniform(0.003, 0.015)),
        ca_red=float(rng.uniform(-1.5e-4, 1.5e-4)), ca_blue=float(rng.uniform(-1.5e-4, 1.5e-4)),
        tone=float(rng.uniform(0.0, 0.25)), sharpen=float(rng.uniform(*cond.sharpen)))


def _partial_awb(s: sensor.SensorSettings, radiance: F32, rng: np.random.Generator
                 ) -> sensor.SensorSettings:
    """Move the lamp white balance 0-35 % of the way (in log gain) to grey-world, as a
    camera's auto white balance partly does under water."""
    mean = radiance[::8, ::8].reshape(-1, 3).mean(axis=0).astype(np.float64)
    grey = mean[1] / np.maximum(mean, 1e-12)
    alpha = rng.uniform(0.0, 0.35)
    lamp = np.asarray(s.wb_gains)
    gains = lamp * (grey / lamp) ** alpha
    gains = gains / gains[1]
    return sensor.SensorSettings(**{**s.__dict__, "wb_gains": tuple(float(g) for g in gains)})


def scene_forward_scatter(radiance: F32, wat: water.WaterType, distance_m: float,
                          focal_px: float) -> float:
    """In place: spread the fraction 1 - exp(-b_s r) of the scene light by the halo kernel
    (the water's small-angle scattering on the way to the camera); returns the fraction."""
    frac = -math.expm1(-float(wat.small_angle_scattering_per_m(550.0)[0]) * distance_m)
    sig = wat.halo_sigma_rad * focal_px
    wide = sensor.wide_blur(radiance, sig, ((beams_mod.HALO_INNER_SHARE, 1.0),
                                            (1.0 - beams_mod.HALO_INNER_SHARE,
                                             beams_mod.HALO_OUTER_FACTOR)))
    cv2.addWeighted(radiance, 1.0 - frac, wide, frac, 0.0, dst=radiance)
    return frac


def _background_at(radiance: F32, x: float, y: float, channel: int) -> float:
    """Median exposed scene light (no laser) in the 5x5 pixels around (x, y), one channel."""
    i, j = int(y), int(x)
    win = radiance[max(i - 2, 0): i + 3, max(j - 2, 0): j + 3, channel]
    return float(np.median(win)) if win.size else 0.0


def _ca_of_dominant(ca: tuple[tuple[float, float], tuple[float, float]],
                    wavelength_nm: float) -> float:
    """Chromatic displacement (px) of the laser's dominant channel (0 for green: G is the
    reference)."""
    dom = spectra.dominant_channel(wavelength_nm)
    return float(np.hypot(*ca[0])) if dom == 0 else float(np.hypot(*ca[1])) if dom == 2 else 0.0


def spot_crops(cond: Condition, cam: optics.CameraModel, lay: layout.Layout,
               wat: water.WaterType, albedo_at: beams_mod.AlbedoFn,
               settings: sensor.SensorSettings, rng: np.random.Generator
               ) -> tuple[list[sensor.Crop], dict[str, dict[str, float]]]:
    """Every switched-on laser's spot and glow as light crops in exposed units (the optical
    PSF included), and per-spot metadata."""
    meta: dict[str, dict[str, float]] = {}
    crops: list[sensor.Crop] = []
    for beam in lay.beams:
        hit = lay.hits.get(beam.name)
        if not lay.on[beam.name] or hit is None:
            continue
        opts = beams_mod.SpotOptions(
            peak_over_white=_log_uniform(rng, cond.peak_over_white),
            speckle_contrast=float(rng.uniform(*cond.speckle_contrast)),
            speckle_grain_px=float(rng.uniform(1.0, 2.0)),
            psf_sigma_px=settings.psf_sigma_px)
        spot = beams_mod.render_spot(beam, hit, cam, lay.seafloor, albedo_at, wat, opts, rng)
        ca = sensor.chromatic_shift_px(float(hit.truth_px[0]), float(hit.truth_px[1]),
                                       settings, cam.cx, cam.cy)
        crops.append((spot.x0, spot.y0,
                      sensor.shift_channels(spot.light, ca) * np.float32(spot.scale)))
        glow = (beams_mod.glow_line(beam, hit, cam, wat, settings.psf_sigma_px)
                if cond.beam_glow else None)
        glow_peak = 0.0
        if glow is not None:
            crops.append((glow[0], glow[1], glow[2] * np.float32(spot.scale)))
            glow_peak = float(glow[2].max()) * spot.scale
        meta[beam.name] = {
            **spot.meta, "truth_x": float(hit.truth_px[0]), "truth_y": float(hit.truth_px[1]),
            "range_m": hit.range_m, "camera_distance_m": hit.camera_distance_m,
            "incidence_deg": hit.incidence_deg, "wavelength_nm": beam.wavelength_nm,
            "waist_mm": beam.waist_m * 1e3, "divergence_mrad": beam.divergence_rad * 1e3,
            "speckle_contrast": opts.speckle_contrast, "speckle_grain_px": opts.speckle_grain_px,
            "glow_peak_over_white": glow_peak,
            "ca_shift_dominant_px": _ca_of_dominant(ca, beam.wavelength_nm)}
    return crops, meta


@dataclass
class _Work:
    """Intermediate state of one frame."""

    cond: Condition
    cam: optics.CameraModel
    wavelength: float
    wat: water.WaterType
    lay: layout.Layout
    ctx: compose.Context
    discs: list[particles.Disc]
    meta: dict[str, Any]


def _plan(condition_name: str, width: int, height: int, rng: np.random.Generator) -> _Work:
    """Camera, laser wavelength, water, geometry, clutter patches (steps 1-2)."""
    cond = CONDITIONS[condition_name]
    cam = optics.random_camera(rng, width, height)
    wavelength = float(cond.wavelengths_nm[int(rng.integers(len(cond.wavelengths_nm)))])
    wat = water.WATER_TYPES[cond.waters[int(rng.integers(len(cond.waters)))]]
    lay = layout.sample_layout(rng, cam, cond.geometry, wavelength)
    if not cond.lasers_on:
        lay = layout.Layout(lay.seafloor, lay.tilt_deg, lay.beams,
                            {n: False for n in lay.on}, lay.hits)
    ctx = compose.make_context(cam, lay)
    speck_channels = (spectra.dominant_channel(wavelength),) if cond.lasers_on else (0, 1)
    discs, meta = compose.clutter_discs(rng, ctx, cond.pale_clutter, cond.laser_specks,
                                        speck_channels)
    return _Work(cond, cam, wavelength, wat, lay, ctx, discs, meta)


def _exposed_scene(work: _Work, rng: np.random.Generator, keep_seafloor: bool = False
                   ) -> tuple[F32, sensor.SensorSettings, beams_mod.AlbedoFn, F32 | None]:
    """The lit seafloor, camera settings, auto-exposure, hot spots, forward scatter and the
    additive light of particles and glints (steps 3-5), in exposed raw units; with
    ``keep_seafloor`` also a copy of the exposed seafloor alone (before hot spots, veil and
    particles), else None."""
    cond, cam, lay = work.cond, work.cam, work.lay
    hot, hot_aims = compose.hot_lamps(rng, work.ctx) if cond.hotspots else ((), [])
    look = texture.random_look(rng)
    bank = texture.make_noise_bank(rng)
    discs = work.discs
    scene = render_seafloor(cam, lay.seafloor, look, bank, vehicle_lamps(rng), hot, work.wat,
                            lambda alb: particles.paint_albedo_patches(alb, discs))
    settings = _partial_awb(sensor_settings(rng, cond), scene.radiance, rng)
    target = float(rng.uniform(*cond.exposure_green))
    exposure = sensor.auto_exposure(scene.radiance, settings, target)
    radiance = scene.radiance
    radiance *= np.float32(exposure)
    seafloor = radiance.copy() if keep_seafloor else None
    hot_peak = 0.0
    if scene.hotspot is not None:  # lobe + seabed at the lobe's centre: 0.9-1.3x white
        hot_peak = float(rng.uniform(0.9, 1.3))
        lobe = float(np.percentile(scene.hotspot[::4, ::4, 1], 99.5)) * exposure
        base = float(np.median(radiance[::4, ::4, 1]))
        radiance += scene.hotspot * np.float32(
            exposure * max(hot_peak - base, 0.1) / max(lobe, 1e-30))
    fs = scene_forward_scatter(radiance, work.wat, lay.seafloor.distance_m, cam.focal_px)
    snow = compose.snow_discs(rng, work.ctx, work.wat) if cond.marine_snow else []
    glints = compose.glint_discs(rng, work.ctx, work.wat) if cond.glints else []
    lit = (compose.laser_lit_discs(rng, work.ctx)
           if cond.laser_lit_particles and cond.lasers_on else [])
    extra = snow + glints + lit
    particles.add_discs(radiance, extra)
    work.discs = discs + extra
    work.meta.update({
        "exposure": exposure, "exposure_target_green": target,
        "scene_forward_scatter_fraction": fs, "hotspot_peak_over_white": hot_peak,
        "hotspot_aims_px": [list(map(float, a)) for a in hot_aims],
        "marine_snow_count": len(snow), "glint_count": len(glints),
        "laser_lit_particles": [[d.x, d.y, 2 * d.a_px, max(d.rgb)] for d in lit]})
    return (radiance, settings, beams_mod.albedo_function(bank, look, scene.linear_below_m),
            seafloor)


def _visibility(work: _Work, radiance: F32, spot_meta: dict[str, dict[str, float]]
                ) -> dict[str, tuple[float, float] | None]:
    """Truth per laser: None when off, or when its spot's background clips in every channel
    the laser shows in (see ``CLIPPED_BACKGROUND``); also the nearest distractor."""
    laser = np.asarray(spectra.laser_rgb(work.wavelength))
    dominant = spectra.dominant_channel(work.wavelength)
    points = [(d.x, d.y) for d in work.discs] + [tuple(a) for a in
                                                 work.meta.get("hotspot_aims_px", [])]
    truth: dict[str, tuple[float, float] | None] = {}
    for beam in work.lay.beams:
        m = spot_meta.get(beam.name)
        if m is None:
            truth[beam.name] = None
            continue
        bg = [_background_at(radiance, m["truth_x"], m["truth_y"], c) for c in range(3)]
        m["background_over_white"] = bg[dominant]
        m["visible_background_over_white"] = min(
            b for b, r in zip(bg, laser, strict=True) if r >= MIN_VISIBLE_CROSSTALK)
        m["nearest_distractor_px"] = float(particles.distance_to_points(
            np.array([[m["truth_x"], m["truth_y"]]]), points)[0])
        visible = m["visible_background_over_white"] < CLIPPED_BACKGROUND
        truth[beam.name] = (m["truth_x"], m["truth_y"]) if visible else None
    return truth


def render_frame(condition_name: str, width: int, height: int,
                 rng: np.random.Generator, laser_free: bool = False,
                 laser_free_jpeg: bool = True, scene_reference: bool = False) -> Frame:
    """Render one photograph of the named condition at this size (see the module docstring).

    Everything is drawn from ``rng``: the same generator state gives the same frame.
    ``laser_free``: also capture it without the lasers' light (same noise draws), and give each
    spot's ``visible_levels`` (:func:`visible_levels`) in ``meta["spots"]``;
    ``laser_free_jpeg`` False leaves that capture unencoded (the camera's 8-bit output before
    JPEG), so the frame minus it holds the lasers' light with the frame's own compression only.
    ``scene_reference``: also capture the seafloor alone (``Frame.image_scene_rgb``) with noise
    drawn from a stream of its own (``rng`` draws what it would without it: the frame is the
    same).
    """
    work = _plan(condition_name, width, height, rng)
    radiance, settings, albedo_at, seafloor = _exposed_scene(work, rng, scene_reference)
    crops, spot_meta = spot_crops(work.cond, work.cam, work.lay, work.wat, albedo_at, settings, rng)
    truth = _visibility(work, radiance, spot_meta)
    dark_settings = settings if laser_free_jpeg else replace(settings, jpeg=False)
    dark = (sensor.capture(radiance.copy(), dark_settings, _same_draws(rng), ())
            if laser_free else None)
    scene = (None if seafloor is None
             else sensor.capture(seafloor, settings, _other_draws(rng), ()))
    del seafloor
    image = sensor.capture(radiance, settings, rng, crops)
    del radiance
    if dark is not None:
        for m in spot_meta.values():
            m["visible_levels"] = visible_levels(image, dark, m["truth_x"], m["truth_y"])
    rig = layout.rig_toml(work.lay.beams, spectra.color_name(work.wavelength), rng)
    lay, wat = work.lay, work.wat
    meta: dict[str, Any] = {
        "condition": work.cond.name, "description": work.cond.description,
        "water": wat.name, "wavelength_nm": work.wavelength,
        "color": spectra.color_name(work.wavelength),
        "lasers_on": {n: bool(v) for n, v in lay.on.items()},
        "distance_m": lay.seafloor.distance_m, "tilt_deg": lay.tilt_deg, **work.meta,
        "jpeg_quality": settings.jpeg_quality, "psf_sigma_px": settings.psf_sigma_px,
        "full_well_e": settings.full_well_e, "read_noise_e": settings.read_noise_e,
        "wb_gains": list(settings.wb_gains), "motion_px": settings.motion_px,
        "defocus_radius_px": settings.defocus_radius_px, "sharpen": settings.sharpen,
        "ca_red": settings.ca_red, "ca_blue": settings.ca_blue, "spots": spot_meta,
        "median_output_rgb": [float(np.median(image[::4, ::4, c])) for c in range(3)],
        "water_optics": water.describe(wat),
    }
    return Frame(image_rgb=image, camera_spec=optics.colmap_camera_spec(work.cam),
                 rig_toml=rig, truth=truth, meta=meta, image_laser_free_rgb=dark,
                 image_scene_rgb=scene)


def _same_draws(rng: np.random.Generator) -> np.random.Generator:
    """A generator that will draw what ``rng`` draws next (``rng`` itself untouched)."""
    bit = type(rng.bit_generator)()
    bit.state = rng.bit_generator.state
    return np.random.Generator(bit)


def _other_draws(rng: np.random.Generator) -> np.random.Generator:
    """A generator independent of ``rng`` (its state jumped far ahead; ``rng`` untouched)."""
    bit = _same_draws(rng).bit_generator
    return np.random.Generator(bit.jumped())  # type: ignore[attr-defined]  # PCG64, Philox


def visible_levels(image: U8, laser_free: U8, x: float, y: float, radius: int = 3) -> float:
    """How much a spot changes the photograph: the largest difference (8-bit levels, any
    channel) between the image and its laser-free capture within ``radius`` px of (x, y)
    (COLMAP pixels). The scene's texture varies by 2-10 levels between neighbouring pixels."""
    col, row = int(math.floor(x)), int(math.floor(y))
    win = (slice(max(0, row - radius), row + radius + 1),
           slice(max(0, col - radius), col + radius + 1))
    diff = np.abs(image[win].astype(np.int16) - laser_free[win].astype(np.int16))
    return float(diff.max()) if diff.size else 0.0

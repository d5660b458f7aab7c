"""How far each true spot of the physical benchmark stands out from the scene's own blobs, and
whether the detector found it.

Usage::

    python scripts/bench_separability.py [--per-condition 20] [--size 1920x1080]
        [--conditions green_all,strobe_hotspots,...] [--seed 0] [--workers 2]
        [--json records.json]

Every frame of ``sfm_laserscale.synthetic.underwater`` (the same generator states as
``bench_detection_physical.py --sizes WxH``) is rendered with its capture without the lasers
(``render_frame(..., laser_free=True)``: the same noise draws, the camera's JPEG too): that
capture is the scene a detector must tell the spots from. Each true spot is measured on five
signals of the sRGB-decoded image: red, green, blue, their sum (brightness) and the laser's
colour excess (its own channel minus the mean of the other two: a green laser's spot in
green-cyan water and a pale speck there differ in it only as much as their colours do). On
each, a matched filter at the spot's scale (a difference of Gaussians, σ the spot's image σ
and 3σ: :func:`bench_centre_floor.image_sigma_px`) is read at the spot (its largest value
within 1 px of the truth). The scene's competition is every local maximum (3 × 3) of the same
filter on the laser-free capture in two regions:

- *the band at the spot's range*: within the detector's beam band (``default_band_px``) of
  the beam's image (the rig as given to the detector) between ranges e^±0.1 of the spot's:
  where a spot at the other spots' range may lie;
- *the floor's window*: within the floor search's radius (``default_floor_radius_px``) of the
  spot: where the floor through three other spots puts it;
- *the whole band*: within the beam band of the beam's image between the detector's
  ``min_range_m`` and ``max_range_m``: where a spot must be found with no other spot to go by.

A spot's strength on a signal is the smaller of the filter on the photograph and on its light
alone (the photograph minus the laser-free capture), both read where the photograph's is
largest within 1 px of the truth: a spot that adds nothing to a bump of the scene under it is
not made strong by that bump. A spot is *separable* in a region when on at least one signal
no maximum of the scene there is as strong as the spot. A spot that is not separable in the
band can be told from the scene there only by its shape; one that is not separable even in
the floor's window, not by any strength or colour at all. The best of five signals, chosen
knowing the truth, flatters a detector that must choose its signal beforehand; the second
table counts, per signal, the spots separable in the band at their range on that signal
alone. The detector (default options) runs on every frame, so each row also says how many of
the spots it missed are separable. This is a measurement of the generator's photographs, not
a bound: shape (round, compact) is left out of the five signals.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from bench_centre_floor import Job, image_sigma_px, render_job, run_all
from bench_detection_physical import score_frame
from numpy.typing import NDArray
from scipy import ndimage

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.detection import DetectionOptions, beam_polyline_px, detect_spots
from sfm_laserscale.detection.beams import default_band_px, distance_to_polyline
from sfm_laserscale.detection.floor import default_floor_radius_px
from sfm_laserscale.model import Camera
from sfm_laserscale.rig import Laser, rig_from_dict
from sfm_laserscale.synthetic.underwater import Frame
from sfm_laserscale.synthetic.underwater.sensor import srgb_decode

F64 = NDArray[np.float64]
#: the band's stretch: ranges within this (natural log) of the spot's
RANGE_LN = 0.1
#: the five signals, in the order of :func:`signals`
SIGNALS = ("red", "green", "blue", "brightness", "colour excess")
#: the background scale of the matched filter, in spot σ
BACKGROUND_SIGMAS = 3.0


@dataclass(frozen=True)
class SpotSeparation:
    """One true spot: whether it is separable in each region (on at least one signal, no
    maximum of the scene there as strong), the number of the scene's maxima as strong on the
    signal with the fewest in the band at its range, that signal, and whether the detector
    found it."""

    condition: str
    index: int
    laser: str
    found: bool
    whole_separable: bool
    band_separable: bool
    window_separable: bool
    band_rivals: int
    best_signal: str
    #: per signal (SIGNALS): the scene's maxima as strong in the whole band, the band at its
    #: range and the floor's window
    rivals_by_signal: tuple[tuple[int, int, int], ...]


def signals(rgb8: NDArray[np.uint8], channel: int) -> F64:
    """(5, H, W) linear red, green, blue, brightness (their sum) and the colour excess of a
    laser brightest in ``channel`` (its channel minus the mean of the other two)."""
    lin = srgb_decode(rgb8 / 255.0)
    others = [k for k in range(3) if k != channel]
    excess = lin[..., channel] - 0.5 * (lin[..., others[0]] + lin[..., others[1]])
    return np.stack([lin[..., 0], lin[..., 1], lin[..., 2], lin.sum(axis=2), excess])


def matched(plane: F64, sigma_px: float) -> F64:
    """A difference of Gaussians at a spot's scale: σ and BACKGROUND_SIGMAS σ."""
    return np.asarray(ndimage.gaussian_filter(plane, sigma_px)
                      - ndimage.gaussian_filter(plane, BACKGROUND_SIGMAS * sigma_px))


def band_mask(shape: tuple[int, int], corner: tuple[int, int], segment_px: F64,
              band_px: float, chunk: int = 4096) -> NDArray[np.bool_]:
    """Pixels of a crop (``corner``: its (x0, y0) in the image) within ``band_px`` of the
    polyline ``segment_px`` (N, 2; COLMAP px). Only pixels that near the chord from its first
    to its last point, widened by the polyline's largest distance from it, are measured,
    ``chunk`` at a time."""
    gy, gx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64) + 0.5
    xy = np.column_stack([gx.ravel() + corner[0], gy.ravel() + corner[1]])
    chord = segment_px[[0, -1]]
    bend = float(distance_to_polyline(segment_px, chord).max())
    todo = np.flatnonzero(distance_to_polyline(xy, chord) <= band_px + bend)
    inside = np.zeros(len(xy), dtype=bool)
    for i in range(0, len(todo), chunk):
        idx = todo[i:i + chunk]
        inside[idx] = distance_to_polyline(xy[idx], segment_px) <= band_px
    return inside.reshape(shape)


def beam_stretch(camera: Camera, laser: Laser, near_m: float, far_m: float, steps: int = 64
                 ) -> F64:
    """(K, 2) pixels of a beam's image between ranges ``near_m`` and ``far_m``, near end
    first (:func:`~sfm_laserscale.detection.beam_polyline_px`), those in the image only."""
    if laser.origin is None or laser.direction is None:
        raise ValueError(f"laser {laser.name} is not calibrated")
    px = beam_polyline_px(camera, laser, near_m, far_m, steps)[::-1]
    inside = ((px[:, 0] >= 0) & (px[:, 0] <= camera.width) & (px[:, 1] >= 0)
              & (px[:, 1] <= camera.height))
    return px[inside]


def rivals(free: F64, region: NDArray[np.bool_], level: float) -> int:
    """Local maxima (3 × 3) of ``free`` inside ``region`` at least ``level``."""
    peaks = (free == ndimage.maximum_filter(free, size=3)) & region & (free >= level)
    return int(peaks.sum())


def _crop(camera: Camera, whole: F64, truth: tuple[float, float], reach: float
          ) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) of the image holding the beam's image ``whole`` (N, 2) and the spot
    with ``reach`` px around them; None when the spot lies within ``reach`` of the crop's
    edge (the image's) or the beam is not in the image."""
    if len(whole) < 2:
        return None
    x0, y0 = (max(0, int(math.floor(min(whole[:, k].min(), truth[k]) - reach))) for k in (0, 1))
    x1 = min(camera.width, int(math.ceil(max(whole[:, 0].max(), truth[0]) + reach)))
    y1 = min(camera.height, int(math.ceil(max(whole[:, 1].max(), truth[1]) + reach)))
    if not (x0 + reach <= truth[0] <= x1 - reach and y0 + reach <= truth[1] <= y1 - reach):
        return None
    return x0, y0, x1, y1


def separate_spot(frame: Frame, camera: Camera, laser: Laser, truth: tuple[float, float],
                  channel: int
                  ) -> tuple[bool, bool, bool, int, str, tuple[tuple[int, int, int], ...]] | None:
    """(separable in the whole band, in the band at its range, in the floor's window; rivals
    on the best signal in the band at its range, that signal; rivals per signal and region)
    of one spot; None when the band at its range leaves the image."""
    meta = frame.meta["spots"][laser.name]
    sigma = image_sigma_px(frame.meta, float(meta["sigma_major_px"]))
    range_m = float(meta["range_m"])
    options = DetectionOptions()
    at_range = beam_stretch(camera, laser, range_m * math.exp(-RANGE_LN),
                            range_m * math.exp(RANGE_LN))
    whole = beam_stretch(camera, laser, options.min_range_m, options.max_range_m, 256)
    band = default_band_px(camera.width, camera.height)
    box = _crop(camera, whole, truth, band + BACKGROUND_SIGMAS * 4 * sigma + 4)
    if len(at_range) < 2 or box is None:
        return None
    x0, y0, x1, y1 = box
    free_rgb = frame.image_laser_free_rgb
    if free_rgb is None:
        raise ValueError("the frame has no laser-free capture")
    lit = signals(frame.image_rgb[y0:y1, x0:x1], channel)
    free = signals(free_rgb[y0:y1, x0:x1], channel)
    gy, gx = np.mgrid[0:y1 - y0, 0:x1 - x0].astype(np.float64) + 0.5
    dist = np.hypot(gx + x0 - truth[0], gy + y0 - truth[1])
    regions = (band_mask(dist.shape, (x0, y0), whole, band),
               band_mask(dist.shape, (x0, y0), at_range, band),
               dist <= default_floor_radius_px(camera.width, camera.height))
    near = dist <= 1.0
    counts: list[tuple[int, int, int]] = []  # per signal: rivals in each region
    for k in range(len(SIGNALS)):
        seen, scene = matched(lit[k], sigma), matched(free[k], sigma)
        at = np.unravel_index(np.argmax(np.where(near, seen, -np.inf)), seen.shape)
        level = min(float(seen[at]), float(seen[at] - scene[at]))  # and its light alone
        whole_n, band_n, window_n = (rivals(scene, region, level) for region in regions)
        counts.append((whole_n, band_n, window_n))
    best = min(range(len(SIGNALS)), key=lambda k: (counts[k][1], counts[k][0]))
    whole_ok, band_ok, window_ok = (min(c[r] for c in counts) == 0 for r in range(3))
    return whole_ok, band_ok, window_ok, counts[best][1], SIGNALS[best], tuple(counts)


def run_job(job: Job) -> list[dict[str, Any]]:
    """Every true spot's :class:`SpotSeparation` of one frame (as dicts); found as the
    benchmark scores it (``bench_detection_physical.score_frame``)."""
    frame, _ = render_job(job, laser_free_jpeg=True)
    camera = parse_camera(frame.camera_spec)
    rig = rig_from_dict(tomllib.loads(frame.rig_toml))
    found = {f["laser"] for f in score_frame(frame, detect_spots(frame.image_rgb, camera, rig,
                                                                  DetectionOptions()))["found"]}
    out = []
    for laser in rig.lasers:
        truth = frame.truth.get(laser.name)
        if truth is None:
            continue
        rgb = np.asarray(laser.expected_rgb or (1.0, 1.0, 1.0))
        sep = separate_spot(frame, camera, laser, (float(truth[0]), float(truth[1])),
                            int(np.argmax(rgb)))
        if sep is not None:
            out.append(asdict(SpotSeparation(job.condition, job.index, laser.name,
                                             laser.name in found, *sep)))
    return out


def summary_rows(records: Sequence[dict[str, Any]]) -> list[tuple[Any, ...]]:
    """Per condition: (condition, spots, separable in the whole band, in the band at its range,
    in the floor's window, missed, and the same three counts for the missed spots)."""
    keys = ("whole_separable", "band_separable", "window_separable")
    rows = []
    for cond in dict.fromkeys(r["condition"] for r in records):
        rs = [r for r in records if r["condition"] == cond]
        missed = [r for r in rs if not r["found"]]
        rows.append((cond, len(rs), *(sum(r[k] for r in rs) for k in keys), len(missed),
                     *(sum(r[k] for r in missed) for k in keys)))
    return rows


def signal_rows(records: Sequence[dict[str, Any]]) -> list[tuple[Any, ...]]:
    """Per condition: (condition, spots, then per signal the spots separable in the band at
    their range on that signal alone)."""
    rows = []
    for cond in dict.fromkeys(r["condition"] for r in records):
        rs = [r for r in records if r["condition"] == cond]
        rows.append((cond, len(rs), *(sum(r["rivals_by_signal"][k][1] == 0 for r in rs)
                                      for k in range(len(SIGNALS)))))
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    ran = run_all(argv, __doc__.split("\n\n")[0], run_job, records=True)
    if ran is None:
        return 2
    args, _, results = ran
    records = [r for frame in results for r in frame]
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(records, fh)
    print("| condition | spots | separable: whole band / band at its range / floor's window | "
          "missed | missed and separable: whole band / at its range / window |")
    print("|---|---|---|---|---|")
    for cond, n, wh, band, win, missed, m_wh, m_band, m_win in summary_rows(records):
        print(f"| {cond} | {n} | {wh} / {band} / {win} | {missed} | {m_wh} / {m_band} / {m_win} |")
    print()
    print("| condition | spots | separable in the band at its range on: "
          + " / ".join(SIGNALS) + " |")
    print("|---|---|---|")
    for cond, n, *per_signal in signal_rows(records):
        print(f"| {cond} | {n} | {' / '.join(str(v) for v in per_signal)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

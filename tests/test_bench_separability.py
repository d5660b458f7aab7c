"""``scripts/bench_separability.py``: regions, rivals and one spot against placed scene blobs."""

from __future__ import annotations

import numpy as np
import pytest

from sfm_laserscale.commands.detect import parse_camera
from sfm_laserscale.rig import rig_from_dict
from sfm_laserscale.synthetic.underwater import Frame
from tests.script_loader import load_script

floor = load_script("bench_centre_floor")  # imported by bench_separability
load_script("bench_detection_physical")  # imported by bench_separability
sep = load_script("bench_separability")

#: f 1000 px, principal point (960, 540); a beam 0.1 m right of the camera along its axis is
#: imaged on the row y = 540 at x = 960 + 100 / r (r its range, m)
CAMERA = "PINHOLE 1920 1080 1000 1000 960 540"
RIG = {"laser": [{"name": "L1", "origin": [0.1, 0.0, 0.0], "direction": [0.0, 0.0, 1.0],
                  "color": "green"}]}


def _blob(image: np.ndarray, x: float, y: float, amplitude: float, sigma: float = 1.0) -> None:
    """In place: a Gaussian blob in the green channel (COLMAP pixel centres at +0.5), drawn
    out to 8 σ."""
    r = int(8 * sigma)
    col, row = int(x), int(y)
    gy, gx = np.mgrid[row - r:row + r + 1, col - r:col + r + 1] + 0.5
    blob = amplitude * np.exp(-0.5 * ((gx - x) ** 2 + (gy - y) ** 2) / sigma ** 2)
    patch = image[row - r:row + r + 1, col - r:col + r + 1, 1]
    patch[:] = np.clip(patch + blob, 0, 255)


def _frame(rival_x: float | None, rival_amplitude: float = 150.0) -> Frame:
    """A flat grey frame with the spot of a beam at 2 m (x = 1010) and, on its laser-free
    capture, one scene blob on the beam's line at ``rival_x``."""
    lit = np.full((1080, 1920, 3), 60.0)
    free = lit.copy()
    _blob(lit, 1010.0, 540.0, 100.0)
    if rival_x is not None:
        _blob(lit, rival_x, 540.0, rival_amplitude)
        _blob(free, rival_x, 540.0, rival_amplitude)
    meta = {"spots": {"L1": {"sigma_major_px": 1.0, "range_m": 2.0}}}
    return Frame(lit.astype(np.uint8), CAMERA, "", {"L1": (1010.0, 540.0)}, meta,
                 free.astype(np.uint8))


@pytest.mark.parametrize(("rival_x", "expected"), [
    (None, (True, True, True)),
    (1040.0, (False, True, True)),  # at 1.25 m: in the band, not at the spot's range
    (1014.0, (False, False, True)),  # at 1.92 m, 4 px away: beyond the floor's 3.1 px
    (1012.5, (False, False, False)),  # 2.5 px away
])
def test_a_spot_is_separable_where_no_scene_blob_is_as_strong(
        rival_x: float | None, expected: tuple[bool, bool, bool]) -> None:
    laser = rig_from_dict(RIG).lasers[0]
    got = sep.separate_spot(_frame(rival_x), parse_camera(CAMERA), laser, (1010.0, 540.0), 1)
    assert got is not None
    assert got[:3] == expected
    assert got[4] in sep.SIGNALS


def test_a_weaker_scene_blob_is_no_rival() -> None:
    laser = rig_from_dict(RIG).lasers[0]
    got = sep.separate_spot(_frame(1014.0, 40.0), parse_camera(CAMERA), laser, (1010.0, 540.0),
                            1)
    assert got is not None
    assert got[:4] == (True, True, True, 0)


def test_the_beam_stretch_lies_on_the_beam_image() -> None:
    laser = rig_from_dict(RIG).lasers[0]
    px = sep.beam_stretch(parse_camera(CAMERA), laser, 1.8, 2.2, steps=5)
    assert px[:, 1] == pytest.approx(540.0)
    assert px[0, 0] == pytest.approx(960 + 100 / 1.8)
    assert px[-1, 0] == pytest.approx(960 + 100 / 2.2)


def test_rivals_are_local_maxima_in_the_region_at_least_as_strong() -> None:
    plane = np.zeros((20, 20))
    plane[5, 5], plane[15, 15] = 1.0, 0.5
    everywhere = np.ones_like(plane, dtype=bool)
    assert sep.rivals(plane, everywhere, 0.6) == 1
    assert sep.rivals(plane, everywhere, 0.4) == 2
    assert sep.rivals(plane, ~(np.arange(20)[:, None] < 10) & everywhere, 0.4) == 1


def test_the_band_mask_holds_pixels_near_the_polyline() -> None:
    mask = sep.band_mask((20, 40), (100, 200), np.array([[110.0, 210.0], [130.0, 210.0]]), 2.0)
    assert mask[11, 20]  # pixel centre (120.5, 211.5): 1.5 px from the line
    assert not mask[13, 20]  # 3.5 px
    assert not mask[10, 35]  # (135.5, 210.5): 5.5 px beyond its end


def test_summary_counts_the_missed_spots_apart() -> None:
    rec = {"condition": "c", "whole_separable": False, "band_separable": True,
           "window_separable": True}
    rows = sep.summary_rows([rec | {"found": True}, rec | {"found": False},
                             rec | {"found": False, "window_separable": False}])
    assert rows == [("c", 3, 0, 3, 2, 2, 0, 2, 1)]


def test_a_spot_adding_nothing_is_not_made_strong_by_the_scene_under_it() -> None:
    frame = _frame(None)
    frame.image_laser_free_rgb[...] = frame.image_rgb  # the "spot" is the scene's own blob
    laser = rig_from_dict(RIG).lasers[0]
    got = sep.separate_spot(frame, parse_camera(CAMERA), laser, (1010.0, 540.0), 1)
    assert got is not None
    assert got[:3] == (False, False, False)


def test_the_signal_table_counts_each_signal_alone() -> None:
    recs = [{"condition": "c", "rivals_by_signal": [[0, 0, 0], [3, 1, 0], [0, 0, 0], [1, 0, 0],
                                                    [2, 2, 1]]},
            {"condition": "c", "rivals_by_signal": [[0, 1, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0],
                                                    [0, 0, 0]]}]
    assert sep.signal_rows(recs) == [("c", 2, 1, 1, 2, 2, 1)]


def test_only_a_script_that_keeps_records_takes_json(capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    assert floor.parse_args(["--json", "out.json"], "d", records=True).json == "out.json"
    with pytest.raises(SystemExit):
        floor.parse_args(["--json", "out.json"], "d")
    assert sep.main(["--conditions", "nope", "--per-condition", "1"]) == 2
    assert "nope" in capsys.readouterr().err

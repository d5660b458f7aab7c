"""Rig file parsing: strict keys, beam geometry checks, origins moved onto z = 0."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sfm_laserscale.errors import InputError
from sfm_laserscale.rig import load_rig, rig_from_dict, rig_to_toml

GOOD = """
name = "test rig"
[[laser]]
name = "L1"
origin = [0.1, 0.0, 0.0]
direction = [0.0, 0.0, 2.0]
color = "red"
[[laser]]
name = "L2"
origin = [-0.1, 0.0, 0.0]
direction = [0.0, 0.0, 1.0]
[[pair]]
lasers = ["L1", "L2"]
separation = 0.2
"""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def test_good_rig_normalises_direction(tmp_path: Path) -> None:
    rig = load_rig(_write(tmp_path, GOOD))
    assert rig.names == ["L1", "L2"]
    np.testing.assert_allclose(rig.laser("L1").direction, [0, 0, 1])
    assert rig.pairs[0].separation == pytest.approx(0.2)
    assert rig.has_fcm


def test_origin_moved_along_beam_onto_laser_plane() -> None:
    d = np.array([0.1, 0.0, 1.0])
    rig = rig_from_dict({"laser": [{"name": "A", "origin": [0.2, 0.0, 0.5], "direction": list(d)}]})
    o = rig.laser("A").origin
    assert o is not None and o[2] == pytest.approx(0.0)
    np.testing.assert_allclose(o, [0.2 - 0.05, 0.0, 0.0])


def test_round_trip_through_toml(tmp_path: Path) -> None:
    rig = load_rig(_write(tmp_path, GOOD))
    again = load_rig(_write(tmp_path, rig_to_toml(rig)))
    for a, b in zip(again.lasers, rig.lasers, strict=True):
        assert (a.name, a.color) == (b.name, b.color)
        np.testing.assert_allclose(a.origin, b.origin, atol=1e-12)
        np.testing.assert_allclose(a.direction, b.direction, atol=1e-12)
    assert again.pairs == rig.pairs


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (GOOD + "\nfoo = 1\n", "unknown key"),
        (GOOD.replace('color = "red"', 'colour = "red"'), "unknown key"),
        (GOOD.replace("[0.0, 0.0, 2.0]", "[0.0, 0.0, 0.0]"), "zero vector"),
        (GOOD.replace("[0.1, 0.0, 0.0]", "[0.0, 0.0, 0.0]"), "camera centre"),
        (GOOD.replace("[0.0, 0.0, 2.0]", "[1.0, 0.0, 0.0]"), "parallel to the laser plane"),
        (GOOD.replace("separation = 0.2", ""), "no 'separation'"),
        (GOOD.replace('lasers = ["L1", "L2"]', 'lasers = ["L1", "L9"]'), "unknown laser 'L9'"),
        (GOOD.replace('"red"', '"purple"'), "color"),
        (GOOD.replace("separation = 0.2", "separation = -1"), "positive"),
        ("name = 'x'\n", "no [[laser]]"),
        ("not toml [", "not valid TOML"),
    ],
)
def test_bad_rigs_raise_input_error_naming_the_file(
    tmp_path: Path, text: str, message: str
) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(InputError) as err:
        load_rig(path)
    assert message in str(err.value)
    assert str(path) in str(err.value)


def test_missing_rig_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        load_rig(tmp_path / "nope.toml")


@pytest.mark.parametrize(
    ("value", "channel", "label"),
    [
        ('"green"', "green", "green"),
        ('"Blue"', "blue", "blue"),
        ("532", "green", "532 nm"),
        ('"532 nm"', "green", "532 nm"),
        ("450", "blue", "450 nm"),
        ("638.5", "red", "638.5 nm"),
        ("[0.1, 1.0, 0.2]", "green", "[0.1, 1, 0.2]"),
        ("[255, 40, 10]", "red", "[255, 40, 10]"),
    ],
)
def test_laser_colour_as_name_wavelength_or_triplet_round_trips(
    tmp_path: Path, value: str, channel: str, label: str
) -> None:
    """A colour may be a name, a wavelength (nm) or an RGB triplet: the laser's channel is the
    one it is brightest in, its label what the file said, and the TOML written reads back the
    same."""
    rig = load_rig(_write(tmp_path, GOOD.replace('color = "red"', f"color = {value}")))
    las = rig.laser("L1")
    assert (las.color, las.color_label) == (channel, label)
    rgb = las.expected_rgb
    assert rgb is not None and max(rgb) == pytest.approx(1.0)
    assert ("red", "green", "blue")[int(np.argmax(rgb))] == channel
    again = load_rig(_write(tmp_path, rig_to_toml(rig))).laser("L1")
    assert (again.color, again.color_label, again.expected_rgb) == (channel, label, rgb)


def test_wavelength_response_follows_the_sensor_bands() -> None:
    from sfm_laserscale.laser_color import rgb_from_wavelength

    g = rgb_from_wavelength(532.0)
    assert g[1] == 1.0 and 0.0 < g[0] < 0.2 and 0.0 < g[2] < 0.3  # crosstalk, green dominant
    r = rgb_from_wavelength(650.0)
    assert r[0] == 1.0 and r[1] < 0.2
    b = rgb_from_wavelength(450.0)
    assert b[2] == 1.0 and b[0] < 0.1


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("300", "380-780 nm"),
        ('"900 nm"', "380-780 nm"),
        ("[1, 2]", "3 numbers"),
        ("[0, 0, 0]", "not all 0"),
        ("[-1, 1, 0]", ">= 0"),
        ('"teal"', "wavelength in nm"),
        ("true", "wavelength in nm"),
    ],
)
def test_bad_laser_colours_name_the_laser(tmp_path: Path, value: str, message: str) -> None:
    path = _write(tmp_path, GOOD.replace('color = "red"', f"color = {value}"))
    with pytest.raises(InputError) as err:
        load_rig(path)
    assert message in str(err.value) and "'L1'" in str(err.value)

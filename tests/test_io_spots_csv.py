"""Spots CSV reading/writing (sfm_laserscale.io.spots_csv)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.spots_csv import read_spots_csv, write_spots_csv
from sfm_laserscale.model import Spot

LASERS = ["L1", "L2", "L3"]
IMAGES = ["01.jpg", "sub/02.jpg", "a/03.jpg", "b/03.jpg"]


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "spots.csv"
    path.write_text(text)
    return path


def test_round_trip_is_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    x, y = rng.uniform(0, 4000, 2).tolist()
    # numpy scalars, as a detector may produce them, must be written as plain floats
    third, y32 = np.float64(1.0) / 3, np.float32(2.7)
    spots = {
        "01.jpg": [Spot("L1", x, y, score=float(rng.random()), sigma_px=0.1 + float(rng.random())),
                   Spot("L2", 0.1 + 0.2, 1e-300, score=1.0, sigma_px=0.3, source="manual")],
        "img, with comma \"quoted\".jpg": [Spot("L3", third, y32,  # type: ignore[arg-type]
                                                source="detected")],
    }
    path = tmp_path / "out.csv"
    write_spots_csv(path, spots)
    assert path.read_text().splitlines()[0] == "image,laser,x,y,score,sigma_px,source"
    back = read_spots_csv(path, None, LASERS)
    assert back == {k: [Spot(s.laser, float(s.x), float(s.y), s.score, s.sigma_px, s.source)
                        for s in v] for k, v in spots.items()}
    assert list(back) == list(spots)


def test_minimal_file_defaults_and_header_normalisation(tmp_path: Path) -> None:
    path = _write(tmp_path, "\ufeff Image , LASER,X ,y\n01.jpg,L1,10.5,20.25\n\n"
                            "# comment line\nsub/02.jpg,L2,1,2\n01.jpg,L2,3,4\n")
    spots = read_spots_csv(path, IMAGES, LASERS)
    assert spots == {
        "01.jpg": [Spot("L1", 10.5, 20.25, 1.0, 0.3, "manual"), Spot("L2", 3.0, 4.0, 1.0, 0.3,
                                                                     "manual")],
        "sub/02.jpg": [Spot("L2", 1.0, 2.0, 1.0, 0.3, "manual")],
    }


def test_optional_columns(tmp_path: Path) -> None:
    path = _write(tmp_path, "image,laser,x,y,score,sigma_px\n01.jpg,L1,1,2,0.5,0.8\n"
                            "01.jpg,L2,1,2,,\n")
    spots = read_spots_csv(path, IMAGES, LASERS)["01.jpg"]
    assert spots == [Spot("L1", 1.0, 2.0, 0.5, 0.8, "manual"), Spot("L2", 1.0, 2.0, 1.0, 0.3,
                                                                    "manual")]


def test_image_matching_by_basename(tmp_path: Path) -> None:
    path = _write(tmp_path, "image,laser,x,y\n/data/run1/01.jpg,L1,1,2\n02.jpg,L1,1,2\n"
                            "C:\\pics\\02.jpg,L2,1,2\n")
    spots = read_spots_csv(path, IMAGES, LASERS)
    assert sorted(spots) == ["01.jpg", "sub/02.jpg"]
    assert [s.laser for s in spots["sub/02.jpg"]] == ["L1", "L2"]
    exact = _write(tmp_path, "image,laser,x,y\na/03.jpg,L1,1,2\n")
    assert list(read_spots_csv(exact, IMAGES, LASERS)) == ["a/03.jpg"]


ERRORS = {
    "missing column": ("image,laser,x\n01.jpg,L1,1\n", "line 1: missing column"),
    "unknown column": ("image,laser,x,y,colour\n01.jpg,L1,1,2,red\n", "line 1: unknown column"),
    "repeated column": ("image,laser,x,y,X\n01.jpg,L1,1,2,3\n", "line 1: a column appears twice"),
    "non-numeric x": ("image,laser,x,y\n01.jpg,L1,1,2\n01.jpg,L2,abc,2\n", "line 3: x is not"),
    "nan y": ("image,laser,x,y\n01.jpg,L1,1,nan\n", "line 2: y is not finite"),
    "inf x": ("image,laser,x,y\n01.jpg,L1,-inf,1\n", "line 2: x is not finite"),
    "empty x": ("image,laser,x,y\n01.jpg,L1,,1\n", "line 2: x is not a number"),
    "unknown image": ("image,laser,x,y\n09.jpg,L1,1,2\n", "line 2: image '09.jpg' is not"),
    "ambiguous image": ("image,laser,x,y\n03.jpg,L1,1,2\n", "line 2: image '03.jpg' is ambig"),
    "unknown laser": ("image,laser,x,y\n01.jpg,L9,1,2\n", "line 2: laser 'L9' is not in"),
    "duplicate": ("image,laser,x,y\n01.jpg,L1,1,2\n/x/01.jpg,L1,3,4\n",
                  "line 3: image '01.jpg' laser 'L1' already given on line 2"),
    "too few fields": ("image,laser,x,y\n01.jpg,L1,1\n", "line 2: 3 fields"),
    "too many fields": ("image,laser,x,y\n01.jpg,L1,1,2,3\n", "line 2: 5 fields"),
    "bad score": ("image,laser,x,y,score\n01.jpg,L1,1,2,1.5\n", "line 2: score must be"),
    "bad sigma": ("image,laser,x,y,sigma_px\n01.jpg,L1,1,2,0\n", "line 2: sigma_px must be"),
    "bad source": ("image,laser,x,y,source\n01.jpg,L1,1,2,guess\n", "line 2: source must be"),
    "empty file": ("", "empty spots file"),
    "header only blank": ("\n\n", "empty spots file"),
    "empty image": ("image,laser,x,y\n ,L1,1,2\n", "line 2: empty image name"),
}


@pytest.mark.parametrize("case", sorted(ERRORS))
def test_errors_name_file_and_line(tmp_path: Path, case: str) -> None:
    text, message = ERRORS[case]
    path = _write(tmp_path, text)
    with pytest.raises(InputError) as err:
        read_spots_csv(path, IMAGES, LASERS)
    assert err.value.path == str(path)
    assert message in err.value.problem


def test_missing_and_binary_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        read_spots_csv(tmp_path / "nope.csv", None, LASERS)
    path = tmp_path / "bin.csv"
    path.write_bytes(b"image,laser,x,y\n\xff\xfe\x00,L1,1,2\n")
    with pytest.raises(InputError, match="UTF-8"):
        read_spots_csv(path, None, LASERS)


def test_no_image_names_keeps_entries_as_written(tmp_path: Path) -> None:
    path = _write(tmp_path, "image,laser,x,y\n/abs/09.jpg,L1,1,2\n")
    assert list(read_spots_csv(path, None, LASERS)) == ["/abs/09.jpg"]


def test_malformed_csv(tmp_path: Path) -> None:
    path = _write(tmp_path, "image,laser,x,y\n" + "a" * 200_000 + ",L1,1,2\n")  # > csv limit
    with pytest.raises(InputError, match="bad CSV"):
        read_spots_csv(path, None, LASERS)

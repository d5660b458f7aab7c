"""The CLI contract (docs/OUTPUTS.md) through click's CliRunner: exit codes 0/1/2 and the
outputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner, Result

from sfm_laserscale.cli import main
from sfm_laserscale.io.transforms import read_matrix_4x4

OUTPUTS = ["report.json", "report.html", "estimates.csv", "spots.csv", "transform.sim3",
           "transform_4x4.txt", "scaled/model/images.bin", "scaled/model/points3D.bin",
           "scaled/mesh.ply"]


def _args(ds: Any, out: Path, **over: Any) -> list[str]:
    """scale arguments for the data set; ``over`` replaces options (None drops one)."""
    lasers = over.pop("--laser-images-list", [ds.laser_images_dir])
    opts = {"--model": ds.model_dir, "--mesh": ds.mesh_path, "--rig": ds.rig_path,
            "--database": ds.database_path, "--out": out, **over}
    args = ["scale"]
    for k, v in opts.items():
        if v is not None:
            args += [k, str(v)]
    return args + ["--laser-images", *map(str, lasers)]


def _run(args: list[str]) -> Result:
    return CliRunner().invoke(main, args, catch_exceptions=False)


@pytest.fixture(scope="module")
def good_run(small_dataset: Any, tmp_path_factory: pytest.TempPathFactory) -> tuple[Result, Path]:
    out = tmp_path_factory.mktemp("cli") / "run"
    return _run(_args(small_dataset, out) + ["--quiet"]), out


def test_scale_succeeds_and_writes_every_output(good_run: tuple[Result, Path],
                                                small_dataset: Any) -> None:
    result, out = good_run
    assert result.exit_code == 0, result.stderr
    for rel in OUTPUTS:
        assert (out / rel).is_file(), rel
    assert list((out / "overlays").glob("*.jpg"))
    report = json.loads((out / "report.json").read_text())
    s = report["scale"]
    assert s["method"] == "fcm"
    err = abs(s["value"] - small_dataset.true_scale) / small_dataset.true_scale
    assert err < 0.01, f"scale error {err:.3%}"
    assert s["ci95"][0] <= s["value"] <= s["ci95"][1]
    assert s["inverse"] == pytest.approx(1 / s["value"])
    for key in ("version", "methods", "images", "checks", "timings_s"):
        assert key in report
    im = report["images"][0]
    for key in ("name", "registered", "reason", "num_matches", "num_inliers", "reproj_error_px",
                "cam_from_world", "spots", "estimates"):
        assert key in im
    assert "scale =" in result.stdout


def test_transform_files_hold_the_scale(good_run: tuple[Result, Path]) -> None:
    _, out = good_run
    s = json.loads((out / "report.json").read_text())["scale"]["value"]
    sim3 = [float(x) for x in (out / "transform.sim3").read_text().split()]
    assert sim3 == pytest.approx([s, 1, 0, 0, 0, 0, 0, 0])
    m = read_matrix_4x4(out / "transform_4x4.txt")
    assert m[0][0] == pytest.approx(s) and m[3][3] == 1.0 and m[0][3] == 0.0


def test_greedy_laser_images_takes_several_files(small_dataset: Any, tmp_path: Path) -> None:
    files = sorted(small_dataset.laser_images_dir.glob("*.png"))[:2]
    result = _run(_args(small_dataset, tmp_path / "o", **{"--laser-images-list": files})
                  + ["--quiet", "--method", "pcm"])
    assert result.exit_code == 0, result.stderr
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert [im["name"] for im in report["images"]] == [f.name for f in files]
    assert report["scale"]["method"] == "pcm"


def test_no_spots_anywhere_exits_1_with_reasons(small_dataset: Any, tmp_path: Path) -> None:
    # Reference images hold no laser spots: the run works, but nothing can be estimated.
    refs = sorted(small_dataset.images_dir.glob("*.png"))[:2]
    out = tmp_path / "o"
    result = _run(_args(small_dataset, out, **{"--laser-images-list": refs}) + ["--quiet"])
    assert result.exit_code == 1
    report = json.loads((out / "report.json").read_text())
    assert report["scale"]["value"] is None
    assert all(im["reason"] for im in report["images"])
    assert not (out / "scaled").exists()


def test_non_empty_out_refused_without_overwrite(small_dataset: Any, tmp_path: Path) -> None:
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    result = _run(_args(small_dataset, out))
    assert result.exit_code == 2
    assert "not empty" in result.stderr and (out / "keep.txt").exists()


def _bad(args: list[str], out: Path, must_name: str) -> None:
    result = _run(args)
    assert result.exit_code == 2, (result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert must_name in lines[0]
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.name}.partial-*"))


def _copy_model(ds: Any, tmp: Path) -> Path:
    dst = tmp / "model"
    shutil.copytree(ds.model_dir, dst)
    return dst


def test_bad_missing_model(small_dataset: Any, tmp_path: Path) -> None:
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--model": tmp_path / "nope"}), out, "nope")


def test_bad_model_folder_lacking_files(small_dataset: Any, tmp_path: Path) -> None:
    model = _copy_model(small_dataset, tmp_path)
    (model / "points3D.bin").unlink()
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--model": model}), out, "points3D")


def test_bad_corrupt_binary_model(small_dataset: Any, tmp_path: Path) -> None:
    model = _copy_model(small_dataset, tmp_path)
    data = (model / "images.bin").read_bytes()
    (model / "images.bin").write_bytes(data[: len(data) // 2])
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--model": model}), out, "images.bin")


@pytest.mark.parametrize("kind", ["missing", "empty", "corrupt", "no_triangles"])
def test_bad_mesh(small_dataset: Any, tmp_path: Path, kind: str) -> None:
    mesh = tmp_path / "mesh.ply"
    if kind == "empty":
        mesh.write_bytes(b"")
    elif kind == "corrupt":
        mesh.write_bytes(small_dataset.mesh_path.read_bytes()[:5000])
    elif kind == "no_triangles":
        mesh.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                        "property float y\n"
                        "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--mesh": mesh}), out, "mesh.ply")


BASE_LASER = '[[laser]]\nname = "L1"\norigin = [0.1, 0, 0]\ndirection = [0, 0, 1]\n'
RIG_CASES = {
    "unknown_key": BASE_LASER + "colour = 1\n",
    "zero_direction": BASE_LASER.replace("[0, 0, 1]", "[0, 0, 0]"),
    "origin_at_centre": BASE_LASER.replace("[0.1, 0, 0]", "[0, 0, 0]"),
    "parallel_to_plane": BASE_LASER.replace("[0, 0, 1]", "[1, 0, 0]"),
}


@pytest.mark.parametrize("case", sorted(RIG_CASES))
def test_bad_rig(small_dataset: Any, tmp_path: Path, case: str) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG_CASES[case])
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--rig": rig}), out, "rig.toml")


@pytest.mark.parametrize(
    "pair", ['lasers = ["L1", "L2"]', 'lasers = ["L1", "L9"]\nseparation = 0.1'])
def test_bad_rig_pairs(small_dataset: Any, tmp_path: Path, pair: str) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(small_dataset.rig_path.read_text().split("[[pair]]")[0] + "[[pair]]\n" + pair)
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--rig": rig}), out, "rig.toml")


def test_bad_no_readable_laser_image(small_dataset: Any, tmp_path: Path) -> None:
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--laser-images-list": [junk]}), out, "junk.png")


def test_bad_laser_image_size(small_dataset: Any, tmp_path: Path) -> None:
    import cv2
    src = sorted(small_dataset.laser_images_dir.glob("*.png"))[0]
    img = cv2.imread(str(src))
    small = tmp_path / "half.png"
    cv2.imwrite(str(small), cv2.resize(img, None, fx=0.5, fy=0.5))
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--laser-images-list": [small]}), out, "half.png")


@pytest.mark.parametrize("row", ["nope.png,L1,10,10", "{img},L9,10,10", "{img},L1,ten,10"])
def test_bad_spots_csv(small_dataset: Any, tmp_path: Path, row: str) -> None:
    img = sorted(small_dataset.laser_images_dir.glob("*.png"))[0].name
    spots = tmp_path / "spots.csv"
    spots.write_text("image,laser,x,y\n" + row.format(img=img) + "\n")
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--spots": spots}), out, "spots.csv")


def test_bad_out_not_writable(small_dataset: Any, tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    out = blocker / "o"  # a folder inside a regular file cannot be created
    result = _run(_args(small_dataset, out))
    assert result.exit_code == 2
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_debug_shows_traceback(small_dataset: Any, tmp_path: Path) -> None:
    args = _args(small_dataset, tmp_path / "o", **{"--model": tmp_path / "nope"})
    result = CliRunner().invoke(main, ["--debug", *args])
    assert result.exit_code != 0 and result.exception is not None


def test_no_descriptors_source_is_bad_usage(small_dataset: Any, tmp_path: Path) -> None:
    out = tmp_path / "o"
    _bad(_args(small_dataset, out, **{"--database": None}), out, "--database")


def test_usage_error_exits_2() -> None:
    result = CliRunner().invoke(main, ["scale", "--model", "x"])
    assert result.exit_code == 2

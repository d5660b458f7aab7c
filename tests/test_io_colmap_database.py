"""COLMAP database features: fixture (old schema), pycolmap 4.2 schema, WAL, never writing."""

from __future__ import annotations

import hashlib
import shutil
import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.colmap import read_colmap_model
from sfm_laserscale.io.colmap_database import open_database_features, read_database_features

FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures"
MAUPERTUIS = FIXTURES / "maupertuis_colmap"
DB = MAUPERTUIS / "colmap.db"
NUM_KEYPOINTS = {"00.jpg": 6424, "01.jpg": 5920, "02.jpg": 5576, "03.jpg": 6090}


def _folder_state(folder: Path) -> dict[str, tuple[str, int]]:
    """File name -> (sha256, mtime_ns) of every file in a folder."""
    return {p.name: (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(folder.iterdir()) if p.is_file()}


def _copy_db(dst_dir: Path) -> Path:
    """Copy of the fixture database with its -wal and -shm files, writable."""
    dst_dir.mkdir(parents=True, exist_ok=True)
    for suffix in ("", "-wal", "-shm"):
        shutil.copyfile(MAUPERTUIS / f"colmap.db{suffix}", dst_dir / f"colmap.db{suffix}")
    return dst_dir / "colmap.db"


def _raises_naming(path_part: str, *args, **kwargs) -> InputError:  # type: ignore[no-untyped-def]
    with pytest.raises(InputError) as info:
        read_database_features(*args, **kwargs)
    assert path_part in str(info.value) and "\n" not in str(info.value), str(info.value)
    return info.value


def test_lazy_features_read_one_image_per_access_and_index_alike() -> None:
    """The mapping the pipeline indexes from reads an image's rows on each access (nothing
    kept between accesses) and gives the same features, hence the same descriptor index,
    as reading the whole database."""
    from sfm_laserscale.io.colmap import read_colmap_model
    from sfm_laserscale.registration.index import build_descriptor_index
    from sfm_laserscale.registration.options import IndexOptions

    whole = read_database_features(DB)
    before = _folder_state(MAUPERTUIS)
    with open_database_features(DB) as lazy:
        assert list(lazy) == list(whole) and len(lazy) == len(whole)
        first, again = lazy["02.jpg"], lazy["02.jpg"]
        assert first.descriptors is not again.descriptors  # read again, not cached
        np.testing.assert_array_equal(first.descriptors, whole["02.jpg"].descriptors)
        np.testing.assert_array_equal(first.xy_px, whole["02.jpg"].xy_px)
        with pytest.raises(KeyError):
            lazy["not-there.jpg"]
        model = read_colmap_model(MAUPERTUIS / "reconstruction")
        for opts in (IndexOptions(), IndexOptions(exact=False, ivf_lists=40)):
            a = build_descriptor_index(model, lazy, opts)
            b = build_descriptor_index(model, whole, opts)
            np.testing.assert_array_equal(a.point_rows, b.point_rows)
            np.testing.assert_array_equal(a.descriptors, b.descriptors)
            assert (a.method, a.ivf_lists) == (b.method, b.ivf_lists)
    assert _folder_state(MAUPERTUIS) == before
    with pytest.raises(InputError, match="not in the database"), \
            open_database_features(DB, ["nope.jpg"]):
        pass


def test_fixture_features_and_untouched_fixture() -> None:
    before = _folder_state(MAUPERTUIS)
    feats = read_database_features(DB)
    assert _folder_state(MAUPERTUIS) == before  # not even the -shm is written
    assert {n: len(f.xy_px) for n, f in feats.items()} == NUM_KEYPOINTS
    for f in feats.values():
        assert f.xy_px.dtype == np.float64 and f.xy_px.shape[1] == 2
        assert f.descriptors.dtype == np.uint8 and f.descriptors.shape == (len(f.xy_px), 128)
        assert np.all(f.xy_px > 0) and np.all(f.xy_px < [1919, 1079])
        # SIFT descriptors are L2-normalised then scaled to uint8 (norm ~ 512)
        assert 400 < np.median(np.linalg.norm(f.descriptors.astype(float), axis=1)) < 600
    subset = read_database_features(str(DB), ["02.jpg"])
    assert list(subset) == ["02.jpg"]
    np.testing.assert_array_equal(subset["02.jpg"].descriptors, feats["02.jpg"].descriptors)


def test_fixture_keypoints_are_model_points2d() -> None:
    """Keypoint i of the database is points2D[i] of the COLMAP model, same pixel convention.

    The model is text with 6 significant digits (e.g. ``1664.13``), so the bound is half a
    unit of the 6th digit (0.005 px above 1000 px) plus float32 rounding of the keypoints;
    below 100 px that is under 1e-3 px.
    """
    model = read_colmap_model(MAUPERTUIS / "reconstruction")
    feats = read_database_features(DB)
    for im in model.images.values():
        kp = feats[im.name].xy_px
        assert len(kp) == len(im.xy_px)
        diff = np.abs(kp - im.xy_px)
        digits = np.floor(np.log10(np.maximum(np.abs(im.xy_px), 1e-300)))
        bound = 0.5 * 10.0 ** (digits - 5) + 1.5e-4
        assert np.all(diff <= bound)
        small = np.abs(im.xy_px) < 100
        assert np.all(diff[small] < 1e-3)


def test_copy_in_writable_folder_gains_no_files(tmp_path: Path) -> None:
    db = _copy_db(tmp_path / "db")
    before = _folder_state(db.parent)
    assert len(read_database_features(db)) == 4
    assert _folder_state(db.parent) == before


def test_pending_wal_is_seen_without_writing(tmp_path: Path) -> None:
    """A WAL with uncheckpointed rows (COLMAP still running or killed): rows are read from a
    private copy, the user's files stay as they are."""
    db = _copy_db(tmp_path / "db")
    writer = sqlite3.connect(db)
    try:
        assert writer.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        writer.execute("PRAGMA wal_autocheckpoint=0")
        new_kp = np.array([[10.25, 20.5, 1, 0, 0, 1], [30.75, 40.0, 1, 0, 0, 1]], "<f4")
        writer.execute("UPDATE keypoints SET rows=2, cols=6, data=? WHERE image_id=1",
                       (new_kp.tobytes(),))
        writer.execute("UPDATE descriptors SET rows=2, cols=128, data=? WHERE image_id=1",
                       (bytes(range(256)),))
        writer.commit()
        assert (tmp_path / "db" / "colmap.db-wal").stat().st_size > 0
        before = _folder_state(db.parent)
        feats = read_database_features(db, ["00.jpg", "01.jpg"])
        assert _folder_state(db.parent) == before
    finally:
        writer.close()
    np.testing.assert_array_equal(feats["00.jpg"].xy_px, new_kp[:, :2].astype(np.float64))
    np.testing.assert_array_equal(feats["00.jpg"].descriptors.ravel(), np.arange(256))
    assert len(feats["01.jpg"].xy_px) == NUM_KEYPOINTS["01.jpg"]


def test_pycolmap_4_2_database(tmp_path: Path) -> None:
    """The current schema (rigs/frames tables, descriptors.type) written by pycolmap 4.2."""
    rng = np.random.default_rng(5)
    path = tmp_path / "new.db"
    written = {}
    with pycolmap.Database.open(str(path)) as db:
        cam = db.write_camera(pycolmap.Camera.create_from_model_name(0, "SIMPLE_RADIAL", 1e3,
                                                                     640, 480))
        for k, cols in enumerate((2, 4, 6)):
            name = f"sub/im{k}.jpg"
            image_id = db.write_image(pycolmap.Image(name=name, camera_id=cam))
            kp = rng.uniform(0, 600, (20 + k, cols)).astype(np.float32)
            desc = rng.integers(0, 256, (20 + k, 128), dtype=np.uint8)
            db.write_keypoints(image_id, kp)
            db.write_descriptors(image_id, pycolmap.FeatureDescriptors(
                pycolmap.FeatureExtractorType.SIFT, desc))
            written[name] = (kp, desc)
        db.write_image(pycolmap.Image(name="nofeatures.jpg", camera_id=cam))
    # closed here: an unclosed connection keeps -wal/-shm beside the file until the garbage
    # collector closes it, which then races with the folder's snapshots below
    with closing(sqlite3.connect(path)) as con:
        tables = {r[0] for r in con.execute(
            "SELECT name FROM sqlite_master WHERE type='table'")}
    assert {"rigs", "frames"} <= tables
    before = _folder_state(tmp_path)
    feats = read_database_features(path)
    assert _folder_state(tmp_path) == before
    assert set(feats) == set(written)  # the image without features is left out
    for name, (kp, desc) in written.items():
        np.testing.assert_array_equal(feats[name].xy_px, kp[:, :2].astype(np.float64))
        np.testing.assert_array_equal(feats[name].descriptors, desc)
    err = _raises_naming("new.db", path, ["nofeatures.jpg"])
    assert "no keypoints" in str(err)


def test_non_sift_descriptors_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "aliked.db"
    with pycolmap.Database.open(str(path)) as db:
        cam = db.write_camera(pycolmap.Camera.create_from_model_name(0, "PINHOLE", 1e3, 64, 48))
        image_id = db.write_image(pycolmap.Image(name="a.jpg", camera_id=cam))
        db.write_keypoints(image_id, np.ones((3, 2), np.float32))
        db.write_descriptors(image_id, pycolmap.FeatureDescriptors(
            pycolmap.FeatureExtractorType.ALIKED_N32, np.ones((3, 128), np.uint8)))
    assert "not SIFT" in str(_raises_naming("aliked.db", path))


def test_missing_not_sqlite_and_wrong_files(tmp_path: Path) -> None:
    assert "not found" in str(_raises_naming("nothere.db", tmp_path / "nothere.db"))
    assert "not a file" in str(_raises_naming(str(tmp_path), tmp_path))
    text = tmp_path / "model.txt"
    text.write_text("# this is not a database\n")
    assert "not a SQLite" in str(_raises_naming("model.txt", text))
    (tmp_path / "empty.db").write_bytes(b"")
    _raises_naming("empty.db", tmp_path / "empty.db")
    other = tmp_path / "other.db"
    with sqlite3.connect(other) as con:
        con.execute("CREATE TABLE images (image_id INTEGER, name TEXT)")
    con.close()
    err = _raises_naming("other.db", other)
    assert "keypoints" in str(err) and "descriptors" in str(err)
    corrupt = tmp_path / "corrupt.db"
    corrupt.write_bytes(DB.read_bytes()[:5000])
    _raises_naming("corrupt.db", corrupt)


def test_unknown_image_and_corrupt_blobs(tmp_path: Path) -> None:
    db = _copy_db(tmp_path / "db")
    err = _raises_naming("colmap.db", db, ["00.jpg", "missing.jpg"])
    assert "missing.jpg" in str(err)
    with sqlite3.connect(db) as con:
        con.execute("UPDATE keypoints SET cols=5 WHERE image_id=2")
    con.close()
    assert "01.jpg" in str(_raises_naming("colmap.db", db, ["01.jpg"]))
    with sqlite3.connect(db) as con:
        con.execute("UPDATE keypoints SET cols=6 WHERE image_id=2")
        con.execute("UPDATE descriptors SET rows=rows-1 WHERE image_id=3")
    con.close()
    assert len(read_database_features(db, ["01.jpg"])["01.jpg"].xy_px) == 5920
    assert "02.jpg" in str(_raises_naming("colmap.db", db, ["02.jpg"]))

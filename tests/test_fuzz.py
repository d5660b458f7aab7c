"""Fuzzed inputs through the CLI: truncated, bit-flipped and overwritten meshes (PLY binary and
ASCII, OBJ), COLMAP models (binary and text), OpenMVG sfm_data.json and COLMAP databases.
Every case must exit 0/1 (accepted) or 2 with one clear line naming the file — never 3 (a
crash), a traceback or a hang — and huge declared counts must not allocate gigabytes.

Seeded: the same cases every run. ``scale`` cases run the real loading stage (every reader and
check of a scale run) and stop right after it, so an accepted case costs no registration.
"""

from __future__ import annotations

import shutil
import signal
import struct
import subprocess
import sys
import tracemalloc
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner, Result

from sfm_laserscale.cli import main
from sfm_laserscale.commands import scale as scale_command

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO.parent / "shared" / "fixtures"
CASE_TIMEOUT_S = 20


class Accepted(BaseException):
    """Raised after a successful loading stage (BaseException: not mapped to an exit code)."""


class Hang(BaseException):
    """A case ran longer than CASE_TIMEOUT_S."""


@contextmanager
def time_limit(seconds: int) -> Iterator[None]:
    def on_alarm(signum: int, frame: Any) -> None:
        raise Hang(f"case still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


# ---------------------------------------------------------------------------- mutations

def mutate(data: bytes, rng: np.random.Generator, kind: str) -> bytes:
    """One corruption of ``data``: truncate, flip bits, overwrite with 0xFF (huge counts and
    lengths), zero a run, or drop a chunk."""
    n = len(data)
    buf = bytearray(data)
    if kind == "truncate":
        return bytes(buf[: int(rng.integers(0, n))])
    if kind == "bitflip":
        for _ in range(int(rng.integers(1, 9))):
            pos = int(rng.integers(0, n))
            buf[pos] ^= 1 << int(rng.integers(0, 8))
        return bytes(buf)
    pos = int(rng.integers(0, n))
    if kind == "ones":
        buf[pos:pos + 8] = b"\xff" * len(buf[pos:pos + 8])
    elif kind == "zeros":
        buf[pos:pos + 16] = bytes(len(buf[pos:pos + 16]))
    elif kind == "drop":
        del buf[pos:pos + int(rng.integers(1, 256))]
    return bytes(buf)


KINDS = ("truncate", "bitflip", "ones", "zeros", "drop")


def cases(name: str, data: bytes, n: int, seed: int) -> list[tuple[str, bytes]]:
    """``n`` seeded mutations of one file, cycling through the kinds."""
    rng = np.random.default_rng(seed)
    return [(f"{name}:{KINDS[i % len(KINDS)]}#{i}", mutate(data, rng, KINDS[i % len(KINDS)]))
            for i in range(n)]


# ---------------------------------------------------------------------------- checks

#: errors about another input than the corrupted file that are still the right diagnosis
#: (a corrupt database whose keypoints no longer fit the model; a corrupt camera size).
CROSS_FILE_ERRORS = ("keypoints differ from the model's observations",
                     "does not match the model's camera")


def check_result(res: Result | None, accepted: bool, case: str, must_name: str) -> str:
    """'accepted' or 'rejected'; fails on a crash (exit 3), a traceback or an error line that
    names neither the file nor a cross-file mismatch."""
    if accepted:
        return "accepted"
    assert res is not None
    err = res.stderr
    assert "Traceback" not in err and "internal error" not in err, (case, err[-1500:])
    assert res.exit_code in (0, 1, 2), (case, res.exit_code, err[-1500:], res.exception)
    if res.exit_code != 2:
        return "accepted"
    lines = err.strip().splitlines()
    assert len(lines) == 1, (case, err)
    assert lines[0].startswith("sfm-laserscale: error: "), (case, err)
    assert must_name in lines[0] or any(m in lines[0] for m in CROSS_FILE_ERRORS), (case, err)
    return "rejected"


def invoke(args: list[str]) -> tuple[Result | None, bool]:
    """Run the CLI in-process under a time limit; (result, reached the end of loading)."""
    try:
        with time_limit(CASE_TIMEOUT_S):
            return CliRunner().invoke(main, args), False
    except Accepted:
        return None, True


@pytest.fixture()
def stop_after_loading(monkeypatch: pytest.MonkeyPatch) -> None:
    """``scale`` reads and checks every input as usual, then stops (raises Accepted)."""
    real = scale_command.load_inputs

    def load_then_stop(*args: Any, **kwargs: Any) -> Any:
        real(*args, **kwargs)
        raise Accepted

    monkeypatch.setattr(scale_command, "load_inputs", load_then_stop)


def scale_args(ds: Any, out: Path, **over: Path) -> list[str]:
    opts = {"--model": ds.model_dir, "--mesh": ds.mesh_path, "--rig": ds.rig_path,
            "--database": ds.database_path, **over}
    args = ["scale", "--quiet", "--out", str(out)]
    for k, v in opts.items():
        args += [k, str(v)]
    return args + ["--laser-images", str(sorted(ds.laser_images_dir.glob("*.png"))[0])]


Tally = dict[str, int]


def run_file_cases(base: Path, rel: str, variants: list[tuple[str, bytes]], tmp: Path,
                   args_for: Callable[[Path], list[str]], must_name: str | None = None) -> Tally:
    """For each variant: copy ``base`` (file or folder) to tmp, replace ``rel`` inside it with
    the variant, run the CLI on the copy and check the outcome."""
    tally: Tally = {"accepted": 0, "rejected": 0}
    for i, (case, data) in enumerate(variants):
        work = tmp / f"c{i}"
        if base.is_dir():
            shutil.copytree(base, work / base.name)
            target = work / base.name / rel
        else:
            work.mkdir()
            target = work / base.name
        target.write_bytes(data)
        res, accepted = invoke(args_for(work / base.name))
        outcome = check_result(res, accepted, case, must_name or target.name)
        tally[outcome] += 1
        shutil.rmtree(work)
    print(f"{base.name}/{rel}: {tally}")  # shown with pytest -s
    return tally


# ---------------------------------------------------------------------------- small meshes

def _grid_mesh(n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    verts = np.c_[u.ravel(), v.ravel(), 0.1 * np.sin(3 * u.ravel())]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), \
        idx[1:, 1:].ravel()
    faces = np.r_[np.c_[a, b, d], np.c_[a, d, c]]
    return verts, faces


def ply_binary() -> bytes:
    verts, faces = _grid_mesh()
    head = ("ply\nformat binary_little_endian 1.0\ncomment fuzz\n"
            f"element vertex {len(verts)}\nproperty float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\n"
            f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"),
                    ("b", "u1")])
    vrows = np.zeros(len(verts), vdt)
    vrows["x"], vrows["y"], vrows["z"] = verts.T
    vrows["r"] = 200
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    frows = np.zeros(len(faces), fdt)
    frows["n"], frows["i"] = 3, faces
    return head.encode() + vrows.tobytes() + frows.tobytes()


def ply_ascii() -> bytes:
    verts, faces = _grid_mesh(8)
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(verts)}\nproperty double x\n"
            "property double y\nproperty double z\n"
            f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    body = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in verts)
    body += "".join(f"3 {a} {b} {c}\n" for a, b, c in faces)
    return (head + body).encode()


def obj_text() -> bytes:
    verts, faces = _grid_mesh(8)
    lines = ["# fuzz", "mtllib none.mtl", "o grid"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in verts]
    lines += ["vn 0 0 1", "vt 0.5 0.5"]
    lines += [f"f {a + 1}/1/1 {b + 1}/1/1 {c + 1}/1/1" for a, b, c in faces[::2]]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces[1::2]]
    return ("\n".join(lines) + "\n").encode()


MESHES: dict[str, Callable[[], bytes]] = {"mesh_bin.ply": ply_binary,
                                          "mesh_ascii.ply": ply_ascii, "mesh.obj": obj_text}

# ---------------------------------------------------------------------------- tests


@pytest.mark.parametrize("name", sorted(MESHES))
def test_fuzzed_meshes_through_scale(small_dataset: Any, tmp_path: Path, name: str,
                                     stop_after_loading: None) -> None:
    variants = cases(name, MESHES[name](), 30, seed=1)
    src = tmp_path / "src"
    src.mkdir()
    (src / name).write_bytes(MESHES[name]())
    tally = run_file_cases(src / name, "", variants, tmp_path,
                           lambda p: scale_args(small_dataset, tmp_path / "o", **{"--mesh": p}))
    assert tally["rejected"] >= 10, tally  # the corruptions are mostly caught, not ignored
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", sorted(MESHES))
def test_fuzzed_meshes_through_apply(tmp_path: Path, name: str) -> None:
    """The streaming rescaler (apply) on the same corruptions: exit 0 or 2, never 3."""
    src = tmp_path / "src"
    src.mkdir()
    (src / name).write_bytes(MESHES[name]())
    variants = cases(name, MESHES[name](), 15, seed=2)
    tally = run_file_cases(src / name, "", variants, tmp_path, lambda p: [
        "apply", "--quiet", "--scale", "2", "--mesh", str(p), "--out", str(p.parent / "o")])
    assert tally["rejected"] >= 3, tally


BIN_FILES = ("cameras.bin", "images.bin", "points3D.bin")


@pytest.mark.parametrize("rel", BIN_FILES)
def test_fuzzed_colmap_binary_model(small_dataset: Any, tmp_path: Path, rel: str,
                                    stop_after_loading: None) -> None:
    base = small_dataset.model_dir
    n = 20 if rel in ("images.bin", "points3D.bin") else 10
    variants = cases(rel, (base / rel).read_bytes(), n, seed=3)
    tally = run_file_cases(base, rel, variants, tmp_path, lambda p: scale_args(
        small_dataset, tmp_path / "o", **{"--model": p}))
    assert tally["rejected"] >= n // 4, tally


@pytest.mark.parametrize("rel", ["frames.bin", "rigs.bin", "images.bin"])
def test_fuzzed_colmap_binary_model_through_apply(small_dataset: Any, tmp_path: Path,
                                                  rel: str) -> None:
    """apply reads the model and rewrites every file rescaled (frames/rigs included)."""
    base = small_dataset.model_dir
    variants = cases(rel, (base / rel).read_bytes(), 8, seed=10)
    tally = run_file_cases(base, rel, variants, tmp_path, lambda p: [
        "apply", "--quiet", "--scale", "2", "--model", str(p), "--out", str(p.parent / "o")])
    assert tally["rejected"] >= 2, tally


TEXT_FILES = ("cameras.txt", "images.txt", "points3D.txt")


@pytest.mark.parametrize("rel", TEXT_FILES)
def test_fuzzed_colmap_text_model_fixture(fixtures_dir: Path, tmp_path: Path, rel: str) -> None:
    base = fixtures_dir / "maupertuis_colmap" / "reconstruction"
    variants = cases(rel, (base / rel).read_bytes(), 12, seed=4)
    tally = run_file_cases(base, rel, variants, tmp_path, lambda p: [
        "apply", "--quiet", "--scale", "2", "--model", str(p), "--out", str(p.parent / "o")])
    assert tally["rejected"] >= 3, tally


def test_fuzzed_openmvg_sfm_data_fixture(fixtures_dir: Path, tmp_path: Path) -> None:
    base = fixtures_dir / "maupertuis_openmvg" / "sfm_data.json"
    data = base.read_bytes()
    variants = cases("sfm_data.json", data, 30, seed=5)
    # structural edits a bit flip rarely makes: wrong types, missing and renamed keys
    for i, (old, new) in enumerate([(b'"rotation"', b'"rotatio_"'), (b'"X": [', b'"X": ["a", '),
                                    (b'"focal_length"', b'"focal"'), (b'"key": 0', b'"key": -7'),
                                    (b'"value": {', b'"value": [{'), (b'"views"', b'"viewz"'),
                                    (b'"center": [', b'"center": [1e999, ')]):
        variants.append((f"sfm_data.json:edit#{i}", data.replace(old, new, 1)))
    tally = run_file_cases(base, "", variants, tmp_path, lambda p: [
        "apply", "--quiet", "--scale", "2", "--model", str(p), "--out", str(p.parent / "o")])
    assert tally["rejected"] >= 20, tally


def test_fuzzed_colmap_database(small_dataset: Any, tmp_path: Path,
                                stop_after_loading: None) -> None:
    base = small_dataset.database_path
    data = base.read_bytes()
    variants = cases("database.db", data, 24, seed=6)
    # the keypoints/descriptors of the model's images: blobs with lengths that do not match
    for i, flip in enumerate(np.random.default_rng(7).integers(len(data) // 2, len(data), 6)):
        buf = bytearray(data)
        buf[int(flip)] ^= 0x40
        variants.append((f"database.db:blob#{i}", bytes(buf)))
    tally = run_file_cases(base, "", variants, tmp_path, lambda p: scale_args(
        small_dataset, tmp_path / "o", **{"--database": p}))
    assert tally["rejected"] >= 8, tally


def test_fuzzed_fixture_database(fixtures_dir: Path, tmp_path: Path,
                                 stop_after_loading: None) -> None:
    """The real (old-schema) COLMAP database of the fixture, with the fixture's text model."""
    fx = fixtures_dir / "maupertuis_colmap"
    model = tmp_path / "model"
    shutil.copytree(fx / "reconstruction", model)
    laser = fx / "images" / "03.jpg"
    rig = tmp_path / "rig.toml"
    rig.write_text('[[laser]]\nname = "L1"\norigin = [0.1, 0, 0]\ndirection = [0, 0, 1]\n')
    data = (fx / "colmap.db").read_bytes()
    variants = cases("colmap.db", data, 12, seed=8)

    def args(p: Path) -> list[str]:
        return ["scale", "--quiet", "--model", str(model), "--mesh", str(_write_mesh(tmp_path)),
                "--rig", str(rig), "--database", str(p), "--out", str(tmp_path / "o"),
                "--laser-images", str(laser)]

    tally = run_file_cases(fx / "colmap.db", "", variants, tmp_path, args)
    assert tally["rejected"] >= 3, tally


def _write_mesh(folder: Path) -> Path:
    path = folder / "grid.ply"
    if not path.exists():
        path.write_bytes(ply_binary())
    return path


@pytest.mark.parametrize("name,text", [
    ("rig.toml", b"[[laser]]\nname = \"L1\"\norigin = [0.1, 0, 0]\ndirection = [0, 0, 1]\n"),
    ("spots.csv", b"image,laser,x,y\nlaser_000.png,L1,301.3,236.0\n")])
def test_fuzzed_rig_and_spots_files(small_dataset: Any, tmp_path: Path, name: str, text: bytes,
                                    stop_after_loading: None) -> None:
    src = tmp_path / "src"
    src.mkdir()
    (src / name).write_bytes(text)
    option = "--rig" if name == "rig.toml" else "--spots"
    tally = run_file_cases(src / name, "", cases(name, text, 15, seed=9), tmp_path,
                           lambda p: scale_args(small_dataset, tmp_path / "o", **{option: p}))
    assert tally["rejected"] >= 5, tally


# ---------------------------------------------------------------------------- huge counts

def _huge_count_variants(ds: Any) -> list[tuple[str, str, bytes]]:
    """(file, case, bytes): counts near 2^63 or 2^32 in headers of otherwise valid files."""
    model = ds.model_dir
    out = []
    for rel in ("cameras.bin", "images.bin", "points3D.bin"):
        data = (model / rel).read_bytes()
        out.append((rel, f"{rel}:count=2^62", struct.pack("<Q", 2**62) + data[8:]))
        out.append((rel, f"{rel}:count=2^32", struct.pack("<Q", 2**32) + data[8:]))
    img = (model / "images.bin").read_bytes()
    # first image's num_points2D (after id, qvec, tvec, camera id and the name's NUL)
    name_end = img.index(b"\x00", 8 + 4 + 56 + 4)
    out.append(("images.bin", "images.bin:num_points2D=2^60",
                img[:name_end + 1] + struct.pack("<Q", 2**60) + img[name_end + 9:]))
    pts = (model / "points3D.bin").read_bytes()
    at = 8 + 8 + 24 + 3 + 8  # first point's track length
    out.append(("points3D.bin", "points3D.bin:track=2^61",
                pts[:at] + struct.pack("<Q", 2**61) + pts[at + 8:]))
    return out


def test_huge_counts_in_headers_allocate_little(small_dataset: Any, tmp_path: Path) -> None:
    """Truncated files whose headers declare billions of records: rejected at once from the
    file size, with a peak of traced allocations far below the declared size."""
    from sfm_laserscale.errors import InputError
    from sfm_laserscale.io.meshes.mesh import load_mesh
    from sfm_laserscale.io.models import load_model

    variants = _huge_count_variants(small_dataset)
    ply = ply_binary()
    for elem in (b"element vertex 144", b"element face 242"):
        head = elem.split(b" ")[0] + b" " + elem.split(b" ")[1] + b" 4000000000000"
        variants.append(("mesh_bin.ply", f"ply:{elem.decode()}=4e12", ply.replace(elem, head)))
    ascii_ply = ply_ascii().replace(b"element vertex 64", b"element vertex 9000000000000")
    variants.append(("mesh_ascii.ply", "ply-ascii:vertex=9e12", ascii_ply))
    for i, (rel, case, data) in enumerate(variants):
        work = tmp_path / f"h{i}"
        if rel.endswith(".bin"):
            shutil.copytree(small_dataset.model_dir, work)
            (work / rel).write_bytes(data)
            read: Callable[..., Any] = load_model
            arg = work
        else:
            work.mkdir()
            (work / rel).write_bytes(data)
            read, arg = load_mesh, work / rel
        tracemalloc.start()
        try:
            with time_limit(CASE_TIMEOUT_S), pytest.raises(InputError) as info:
                read(arg)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert rel in str(info.value) or rel == "points3D.bin", (case, info.value)
        assert peak < 50e6, (case, peak)


# ---------------------------------------------------------------------------- real processes

def test_fuzzed_inputs_in_real_processes(small_dataset: Any, tmp_path: Path) -> None:
    """A few corrupt inputs through the installed entry point, in a real process with a
    timeout: exit 2, one line on stderr, no traceback, no hang."""
    ds = small_dataset
    rng = np.random.default_rng(11)
    model = tmp_path / "model"
    shutil.copytree(ds.model_dir, model)
    images = (model / "images.bin").read_bytes()
    (model / "images.bin").write_bytes(images[: len(images) // 3])
    mesh = tmp_path / "mesh.ply"
    mesh.write_bytes(ply_binary()[:900])
    sfm = tmp_path / "sfm_data.json"
    sfm.write_bytes(mutate((FIXTURES / "maupertuis_openmvg" / "sfm_data.json").read_bytes(), rng,
                           "truncate"))
    exe = [sys.executable, "-m", "sfm_laserscale.cli"]
    runs = {
        "images.bin": scale_args(ds, tmp_path / "o", **{"--model": model}),
        "mesh.ply": scale_args(ds, tmp_path / "o", **{"--mesh": mesh}),
        "sfm_data.json": ["apply", "--scale", "2", "--model", str(sfm), "--out",
                          str(tmp_path / "o")],
    }
    procs = {name: subprocess.Popen([*exe, *args], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, cwd=tmp_path)
             for name, args in runs.items()}  # in parallel: each pays the imports
    for name, proc in procs.items():
        try:
            _, stderr = proc.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            pytest.fail(f"{name}: still running after 90 s (hang)")
        lines = stderr.strip().splitlines()
        assert proc.returncode == 2, (name, proc.returncode, stderr[-2000:])
        assert len(lines) == 1 and name in lines[0] and "Traceback" not in stderr, (name, stderr)
        assert not (tmp_path / "o").exists()

#!/usr/bin/env python3
"""Speed benchmark of ``sfm-laserscale scale`` (issue #7): per-stage wall time and peak memory.

Synthetic cases of growing size, one axis varied at a time around a base case:
model points 10k / 100k / 1M, mesh triangles 100k / 1M / 10M / 20M, laser images 1 / 6 / 20.
Inputs come from the small demo data set (a real pycolmap SfM model and database, rendered laser
images with spots), padded with ``sfm_laserscale.synthetic.bench_data``. Each case runs
``commands.scale.run`` in its own subprocess (peak RSS from /proc/self/status VmHWM, which
covers C++ allocations), with every stage function wrapped by a timer. The load average is
recorded next to every case (the machine may be shared).

    .venv/bin/python scripts/benchmark.py --quick            # < 3 min subset
    .venv/bin/python scripts/benchmark.py                    # every case (~5 min, ~1.1 GB disk)
    .venv/bin/python scripts/benchmark.py --colmap           # + COLMAP 3.8 registrator side by side
    .venv/bin/python scripts/benchmark.py --markdown out.md --json out.json

Targets checked (issue #7): everything but SIFT on the laser images and mesh read/write under
half the SIFT time; mesh rescale >= 50 % of the throughput of copying the file; peak memory
(above the interpreter + libraries baseline) under 2 × mesh file + model (sparse folder and
database); the 1M-point / 20M-triangle case completes.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

# Stages timed inside the run (name -> (module, attribute)); wrapped in the child process.
WRAPPED = (
    ("model_read", "sfm_laserscale.commands.scale", "load_model"),
    ("mesh_read", "sfm_laserscale.commands.scale", "load_mesh"),
    # the database is read image by image inside the index build (3 passes), counted there
    ("index_build", "sfm_laserscale.commands.scale", "select_index_candidates"),
    ("index_build", "sfm_laserscale.commands.scale", "build_index"),
    ("mesh_crop", "sfm_laserscale.commands.scale", "crop_mesh"),
    ("raycast_build", "sfm_laserscale.raycast", "MeshRaycaster"),
    ("image_read", "sfm_laserscale.commands.scale", "read_rgb"),
    ("detect", "sfm_laserscale.commands.scale", "detect_spots"),
    ("sift", "sfm_laserscale.commands.scale", "extract_sift"),
    ("match", "sfm_laserscale.registration.pose", "match_to_model"),
    ("pose", "sfm_laserscale.registration.pose", "estimate_pose"),
    ("estimate", "sfm_laserscale.commands.scale", "estimate_image"),
    ("fuse", "sfm_laserscale.commands.scale", "fuse_all"),
    ("mesh_check", "sfm_laserscale.commands.scale", "mesh_model_agreement"),
    ("provenance", "sfm_laserscale.commands.scale", "provenance"),
    ("report_build", "sfm_laserscale.commands.scale", "build_report"),
    ("model_write", "sfm_laserscale.report.writer", "write_scaled_colmap_model"),
    ("mesh_write", "sfm_laserscale.report.writer", "write_scaled_mesh"),
    ("overlays", "sfm_laserscale.report.writer", "_write_overlays"),
    ("report_html", "sfm_laserscale.report.writer", "render_html"),
)
METHODS = (("raycast", "cast"),)  # MeshRaycaster methods
# run in a thread beside the stages after registration: timed, not part of the stage sum
# ("provenance" is the main thread's wait for them)
THREADED = (("input_hashes", "sfm_laserscale.provenance", "input_digests"),)
# with worker processes, "sift" is this process's SIFT time: its own extractions and its waits
# for the workers' (the workers' extraction time is in the report's timings)
POOL_METHODS = (("sift", "features"),)  # SiftPool methods
STAGES = ["model_read", "index_build", "mesh_read", "image_read", "detect", "sift",
          "match", "pose", "mesh_crop", "raycast_build", "raycast", "estimate", "fuse",
          "mesh_check", "provenance", "report_build", "model_write", "mesh_write", "overlays",
          "report_html", "other"]
UNAVOIDABLE = ("sift", "mesh_read", "mesh_write")
BASE = {"points": 100_000, "triangles": 1_000_000, "images": 6}
AXES = {"points": (10_000, 100_000, 1_000_000),
        "triangles": (100_000, 1_000_000, 10_000_000, 20_000_000),
        "images": (1, 6, 20)}
QUICK_BASE = {"points": 10_000, "triangles": 100_000, "images": 1}
QUICK_AXES = {"points": (10_000, 100_000), "triangles": (100_000, 1_000_000), "images": (1, 3)}
BIG = {"points": 1_000_000, "triangles": 20_000_000, "images": 6}
WARM = {"points": 10_000, "triangles": 20_000, "images": 1}  # warms the libraries up (IVF)


# --------------------------------------------------------------------------- machine


def _status_bytes(key: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024  # kB
    except OSError:
        pass
    return None


def reset_peak() -> bool:
    """Reset this process's peak RSS (VmHWM) to its current RSS (Linux >= 4.0); False if not."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def rss_bytes() -> int:
    """Current resident set size (0 where /proc is not available)."""
    return _status_bytes("VmRSS") or 0


def maxrss_bytes() -> int:
    """Peak resident set size of this process since it started its program.

    Linux keeps ``ru_maxrss`` across fork + exec, so a child would report its parent's size
    when that was larger; ``VmHWM`` (/proc/self/status) belongs to the new address space.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024  # kB
    except OSError:
        pass
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # KiB on Linux


def loadavg() -> list[float]:
    """1, 5 and 15 minute load averages."""
    return [round(v, 2) for v in os.getloadavg()]


def machine() -> dict[str, Any]:
    """CPU, core count, memory, OS and library versions."""
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    import cv2
    import open3d
    import pycolmap
    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gb": round(mem / 2**30, 1),
            "os": platform.platform(), "python": platform.python_version(),
            "numpy": np.__version__, "pycolmap": pycolmap.__version__,
            "open3d": open3d.__version__, "opencv": cv2.__version__}


# --------------------------------------------------------------------------- data


# the small demo's 640 × 480 camera, a 1920 × 1080 ROV video camera, a 4000 × 3000 still camera
CAMERAS = {"vga": (640, 480), "hd": (1920, 1080), "12mp": (4000, 3000)}


def _suffix(camera: str) -> str:
    return "" if camera == "vga" else f"_{camera}"


def demo_dataset(work: Path, camera: str = "vga") -> Path:
    """The demo data set the cases are made from (made once): the small demo (640 × 480,
    ~15 s) or the full demo scene seen by a 1920 × 1080 (``hd``, 2 min) or 4000 × 3000
    (``12mp``) camera with the demo's horizontal field of view (16 reference and 6 laser
    images)."""
    out = work / f"demo{_suffix(camera)}"
    if (out / "truth.json").is_file():
        return out
    from sfm_laserscale.synthetic.dataset import DemoDataOptions, make_demo_dataset
    if camera == "vga":
        opts = DemoDataOptions(small=True, seed=0, progress=False)
    else:
        width, height = CAMERAS[camera]
        opts = DemoDataOptions(image_size=(width, height), focal_px=900.0 * width / 1024,
                               seed=0, progress=False)
    make_demo_dataset(out, opts, overwrite=True)
    return out


def case_inputs(work: Path, points: int, triangles: int, images: int,
                camera: str = "vga") -> dict[str, Path]:
    """Model (padded), database, mesh and laser image folder of a case (cached in ``work``)."""
    from sfm_laserscale.synthetic.bench_data import (
        pad_model,
        replicate_laser_images,
        write_heightfield_mesh,
    )
    demo = demo_dataset(work, camera)
    sfx = _suffix(camera)
    mdir = work / f"model_{points}{sfx}"
    if not (mdir / "sparse" / "points3D.bin").is_file():
        pad_model(demo / "sparse" / "0", demo / "database.db", mdir, points, seed=1)
    mesh = work / f"mesh_{triangles}{sfx}.ply"
    if not mesh.is_file():
        tmp = mesh.with_suffix(".tmp")
        write_heightfield_mesh(demo / "mesh.ply", demo / "truth.json", tmp, triangles)
        tmp.rename(mesh)
    lasers = work / f"laser_{images}{sfx}"
    if not lasers.is_dir():
        replicate_laser_images(demo / "laser_images", lasers, images)
    return {"model": mdir / "sparse", "database": mdir / "database.db", "mesh": mesh,
            "lasers": lasers, "rig": demo / "rig.toml"}


def scale_inputs(paths: dict[str, Path]) -> Any:
    """The ``ScaleInputs`` of a case's input paths (see ``case_inputs``)."""
    from sfm_laserscale.run_types import ScaleInputs
    return ScaleInputs(model=paths["model"], mesh=paths["mesh"], laser_images=(paths["lasers"],),
                       rig=paths["rig"], database=paths["database"])


def dir_bytes(path: Path) -> int:
    """Total size of a file or of the files of a folder."""
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


# --------------------------------------------------------------------------- one case (child)


def _note_peak(rec: dict[str, Any], stage: str, rss_before: int) -> None:
    """Fold the peak RSS since the last reset into ``stage``'s record, then reset it.

    ``peak_wo_sift_bytes`` is the peak without SIFT's own working memory: during SIFT it
    counts the resident size SIFT started from, elsewhere the stage's peak.
    """
    peak = maxrss_bytes()
    if peak > rec["peak_bytes"]:
        rec["peak_bytes"], rec["peak_stage"] = peak, stage
    rec["stage_peak"][stage] = max(rec["stage_peak"].get(stage, 0), peak)
    if stage == "sift":
        rec["sift_working_bytes"] = max(rec.get("sift_working_bytes", 0), peak - rss_before)
    base = rss_before if stage == "sift" else peak
    rec["peak_wo_sift_bytes"] = max(rec.get("peak_wo_sift_bytes", 0), base)
    if not reset_peak():
        rec["peak_wo_sift_bytes"] = max(rec["peak_wo_sift_bytes"], peak)


def _wrap(fn: Callable[..., Any], stage: str, rec: dict[str, Any]) -> Callable[..., Any]:
    @functools.wraps(fn)
    def timed(*args: Any, **kwargs: Any) -> Any:
        _note_peak(rec, "other", rss_bytes())  # what ran since the last stage ended
        rss_before = rss_bytes()
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            rec["seconds"][stage] = rec["seconds"].get(stage, 0.0) + time.perf_counter() - t0
            _note_peak(rec, stage, rss_before)
    return timed


def _wrap_threaded(fn: Callable[..., Any], stage: str,
                   rec: dict[str, Any]) -> Callable[..., Any]:
    @functools.wraps(fn)
    def timed(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            threaded = rec.setdefault("threaded_seconds", {})
            threaded[stage] = threaded.get(stage, 0.0) + time.perf_counter() - t0
    return timed


def instrument(rec: dict[str, Any]) -> None:
    """Replace each stage function by a timed wrapper (in this process only)."""
    import importlib

    from sfm_laserscale.raycast import MeshRaycaster
    for stage, module, attr in WRAPPED:
        mod = importlib.import_module(module)
        if not hasattr(mod, attr):  # renamed: the stage reads 0 and the run says so
            rec.setdefault("not_wrapped", []).append(f"{module}.{attr}")
            continue
        setattr(mod, attr, _wrap(getattr(mod, attr), stage, rec))
    for stage, method in METHODS:
        setattr(MeshRaycaster, method, _wrap(getattr(MeshRaycaster, method), stage, rec))
    for stage, module, attr in THREADED:
        mod = importlib.import_module(module)
        setattr(mod, attr, _wrap_threaded(getattr(mod, attr), stage, rec))
    from sfm_laserscale.registration.sift_workers import SiftPool
    for stage, method in POOL_METHODS:
        setattr(SiftPool, method, _wrap(getattr(SiftPool, method), stage, rec))


def _record_index(rec: dict[str, Any]) -> None:
    """Keep the descriptor index's search method and pool size (exact scan or IVF)."""
    import sfm_laserscale.commands.scale as scale_command
    build = scale_command.build_index

    def recorded(*args: Any, **kwargs: Any) -> Any:
        index = build(*args, **kwargs)
        rec["index"] = {"method": index.method, "descriptors": index.num_descriptors,
                        "ivf_lists": index.ivf_lists, "ivf_probe": index.ivf_probe}
        return index
    scale_command.build_index = recorded  # type: ignore[assignment]
    crop = scale_command.crop_mesh

    def cropped(*args: Any, **kwargs: Any) -> Any:
        out = crop(*args, **kwargs)
        rec["crop"] = {"kept_triangles": len(out.triangles),
                       "kept_fraction": round(out.kept_fraction, 5)}
        return out
    scale_command.crop_mesh = cropped  # type: ignore[assignment]


def copy_seconds(src: Path, work: Path, repeat: int = 2) -> float:
    """Best time of a plain file copy of ``src`` (the mesh rescale's reference)."""
    best = float("inf")
    for _ in range(repeat):
        dst = work / ("copy_" + src.name)
        t0 = time.perf_counter()
        shutil.copyfile(src, dst)
        best = min(best, time.perf_counter() - t0)
        dst.unlink()
    return best


def run_case(work: Path, points: int, triangles: int, images: int,
             camera: str = "vga", workers: int | None = None) -> dict[str, Any]:
    """Run the scale job on one case in this process; timings, memory, sizes and results.
    ``workers``: SIFT worker processes (None: the tool's default)."""
    from sfm_laserscale.commands import scale as scale_command
    from sfm_laserscale.registration.sift_workers import SiftWorkerOptions
    from sfm_laserscale.run_types import ScaleOptions
    paths = case_inputs(work, points, triangles, images, camera)
    rec: dict[str, Any] = {"seconds": {}, "peak_bytes": 0, "peak_stage": "", "stage_peak": {}}
    baseline = maxrss_bytes()  # interpreter + numpy/open3d/pycolmap/opencv imported
    instrument(rec)
    _record_index(rec)
    inputs = scale_inputs(paths)
    load0 = loadavg()
    with tempfile.TemporaryDirectory(dir=work, prefix="out_") as tmp:
        t0 = time.perf_counter()
        try:
            res = scale_command.run(inputs, Path(tmp) / "out", ScaleOptions(
                progress=False, sift_workers=SiftWorkerOptions(workers=workers)))
        except Exception as exc:  # report the stages timed so far with the error
            return {"case": {"points": points, "triangles": triangles, "images": images},
                    "error": f"{type(exc).__name__}: {exc}"[-1000:],
                    "seconds": {k: round(v, 4) for k, v in rec["seconds"].items()},
                    "peak_rss_bytes": maxrss_bytes(), "loadavg_before": load0}
        total = time.perf_counter() - t0
        copy_s = copy_seconds(paths["mesh"], Path(tmp))
    sec = {k: rec["seconds"].get(k, 0.0) for k in STAGES if k != "other"}
    sec["other"] = max(0.0, total - sum(sec.values()))
    sec["total"] = total
    regs = [r.registration for r in res.images if r.registration is not None]
    return {
        "case": {"points": points, "triangles": triangles, "images": images},
        "seconds": {k: round(v, 4) for k, v in sec.items()},
        "pipeline_timings": res.report.get("timings_s", {}),
        "threaded_seconds": {k: round(v, 4) for k, v in rec.get("threaded_seconds", {}).items()},
        "peak_rss_bytes": max(rec["peak_bytes"], maxrss_bytes()), "baseline_rss_bytes": baseline,
        "peak_stage": rec["peak_stage"],
        "peak_wo_sift_bytes": max(rec.get("peak_wo_sift_bytes", 0), rss_bytes()),
        "sift_working_bytes": rec.get("sift_working_bytes", 0),
        "stage_peak_bytes": rec["stage_peak"],
        "mesh_bytes": paths["mesh"].stat().st_size,
        "model_bytes": dir_bytes(paths["model"]) + dir_bytes(paths["database"]),
        "copy_seconds": round(copy_s, 4),
        "registered": sum(r.success for r in regs), "n_images": len(res.images),
        "inliers": [r.num_inliers for r in regs], "scale": res.scale.value,
        "loadavg_before": load0, "loadavg_after": loadavg(), "index": rec.get("index", {}),
        "crop": rec.get("crop", {}),
        "not_wrapped": rec.get("not_wrapped", []),
        # the largest SIFT worker process's peak (0: none ran)
        "worker_peak_rss_bytes": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024,
    }


def fixed_library_memory(work: Path, camera: str = "vga") -> dict[str, int]:
    """Resident memory after imports, and after one complete run of the tiniest case (heap
    trimmed): the difference is what the libraries keep once used (OpenMP and BLAS thread
    buffers, FAISS, the SIFT extractor, Embree, matplotlib, ...), whatever the input size."""
    import gc

    from sfm_laserscale.commands import scale as scale_command
    from sfm_laserscale.memory import trim_heap
    from sfm_laserscale.run_types import ScaleOptions
    cold = rss_bytes()
    paths = case_inputs(work, WARM["points"], WARM["triangles"], WARM["images"], camera)
    inputs = scale_inputs(paths)
    with tempfile.TemporaryDirectory(dir=work, prefix="warm_") as tmp:
        scale_command.run(inputs, Path(tmp) / "out", ScaleOptions(progress=False))
    gc.collect()
    trim_heap()
    return {"cold_rss_bytes": cold, "warm_rss_bytes": rss_bytes()}


def sift_reference(work: Path, points: int = 100_000) -> dict[str, Any]:
    """SIFT and matching time for a laser image upscaled to 4000 × 3000 (a real camera's size):
    extraction grows with the pixels, matching with the keypoints (capped at 8192)."""
    import cv2

    from sfm_laserscale.io.images import read_rgb
    from sfm_laserscale.io.models import load_model
    from sfm_laserscale.registration.features import load_model_features
    from sfm_laserscale.registration.index import build_descriptor_index
    from sfm_laserscale.registration.match import match_to_model
    from sfm_laserscale.registration.sift import extract_sift
    from sfm_laserscale.run_types import ScaleOptions
    paths = case_inputs(work, points, 100_000, 1)
    opts = ScaleOptions()
    model = load_model(paths["model"])
    feats = load_model_features(model, paths["model"], paths["database"], None, None, opts.tie)
    index = build_descriptor_index(model, feats, opts.index)
    rgb = read_rgb(sorted(paths["lasers"].iterdir())[0])
    out: dict[str, Any] = {"points": points, "loadavg_before": loadavg()}
    for w, h in ((rgb.shape[1], rgb.shape[0]), (4000, 3000)):
        img = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_CUBIC)
        t0 = time.perf_counter()
        f = extract_sift(img, opts.sift)
        t1 = time.perf_counter()
        m = match_to_model(f, index, opts.registration.match)
        t2 = time.perf_counter()
        out[f"{w}x{h}"] = {"sift_s": round(t1 - t0, 3), "keypoints": len(f.xy_px),
                           "match_s": round(t2 - t1, 3), "matches": len(m)}
    out["loadavg_after"] = loadavg()
    return out


# --------------------------------------------------------------------------- parent


def run_case_subprocess(work: Path, case: dict[str, int], timeout: float,
                        camera: str = "vga", workers: int | None = None) -> dict[str, Any]:
    """Run one case in a fresh interpreter (its own peak RSS); the case's JSON result."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--work", str(work), "--child",
           f"{case['points']},{case['triangles']},{case['images']}", "--camera", camera]
    if workers is not None:
        cmd += ["--workers", str(workers)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0 or not proc.stdout.strip():
        return {"case": case, "error": f"exit {proc.returncode}: {proc.stderr[-2000:]}",
                "wall_s": time.perf_counter() - t0}
    out: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    out["wall_s"] = round(time.perf_counter() - t0, 2)
    out["camera"] = camera
    return out


def run_fixed_subprocess(work: Path, camera: str, timeout: float) -> int:
    """The libraries' fixed working memory (``fixed_library_memory`` in a fresh process)."""
    case_inputs(work, WARM["points"], WARM["triangles"], WARM["images"], camera)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--work", str(work), "--child",
           "fixed", "--camera", camera]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=True)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    return int(out["warm_rss_bytes"] - out["cold_rss_bytes"])


def plan(quick: bool) -> list[dict[str, int]]:
    """Cases: the base, then each axis varied alone (the big case last, full set only)."""
    base, axes = (QUICK_BASE, QUICK_AXES) if quick else (BASE, AXES)
    cases = [dict(base)]
    for axis, values in axes.items():
        for v in values:
            c = {**base, axis: v}
            if c not in cases:
                cases.append(c)
    if not quick:
        cases.append(dict(BIG))
    return cases


def derived(r: dict[str, Any]) -> dict[str, Any]:
    """Target checks of one case result."""
    s = r["seconds"]
    unavoidable = sum(s.get(k, 0.0) for k in UNAVOIDABLE)
    rest = s["total"] - unavoidable
    sift = sift_work(r)
    mem = r["peak_rss_bytes"] - r["baseline_rss_bytes"]
    mem_wo_sift = r.get("peak_wo_sift_bytes", r["peak_rss_bytes"]) - r["baseline_rss_bytes"]
    fixed = r.get("fixed_library_bytes", 0)
    budget = 2 * r["mesh_bytes"] + r["model_bytes"]
    thr = r["copy_seconds"] / s["mesh_write"] if s.get("mesh_write") else float("nan")
    return {"rest_s": rest, "rest_over_sift": rest / max(sift, 1e-9),
            "rest_ok": rest < 0.5 * sift, "sift_work_s": sift,
            "rescale_vs_copy": thr, "rescale_ok": thr >= 0.5,
            "mem_above_baseline": mem, "mem_wo_sift": mem_wo_sift, "mem_budget": budget,
            "mem_fixed": fixed, "mem_input": mem_wo_sift - fixed,
            "mem_ok": mem_wo_sift - fixed < budget}


def sift_work(r: dict[str, Any]) -> float:
    """SIFT extraction seconds on the laser images, summed over this process and the workers
    (with workers, this process's "sift" stage is partly waiting, so it is not the work)."""
    t = r.get("pipeline_timings", {})
    if "sift_in_workers" in t:
        return float(t.get("sift_here", 0.0)) + float(t["sift_in_workers"])
    return float(r["seconds"].get("sift", 0.0))


def slope(xs: Iterable[float], ys: Iterable[float]) -> float:
    """Least-squares slope of log(y) against log(x)."""
    lx, ly = np.log(np.asarray(list(xs), float)), np.log(np.asarray(list(ys), float))
    return float(np.polyfit(lx, ly, 1)[0]) if len(lx) >= 2 else float("nan")


def slopes(results: list[dict[str, Any]], base: dict[str, int]) -> dict[str, dict[str, float]]:
    """Per axis: log-log slope of total time, the rest, and the stages that depend on it."""
    out: dict[str, dict[str, float]] = {}
    ok = [r for r in results if "error" not in r]
    for axis in ("points", "triangles", "images"):
        along = sorted((r for r in ok if all(r["case"][k] == base[k] for k in base if k != axis)),
                       key=lambda r: r["case"][axis])
        along = [r for r in along if r["case"] != BIG or base == BIG]
        if len({r["case"][axis] for r in along}) < 2:
            continue
        xs = [r["case"][axis] for r in along]
        row = {"total": slope(xs, [r["seconds"]["total"] for r in along]),
               "rest": slope(xs, [max(derived(r)["rest_s"], 1e-6) for r in along]),
               "peak_mem": slope(xs, [r["peak_rss_bytes"] for r in along])}
        for st in STAGES:
            vals = [r["seconds"].get(st, 0.0) for r in along]
            if min(vals) > 0.01:
                row[st] = slope(xs, vals)
        out[axis] = row
    return out


def _fmt_case(c: dict[str, int]) -> str:
    def k(v: int) -> str:
        return f"{v // 1_000_000}M" if v >= 1_000_000 and v % 1_000_000 == 0 else (
            f"{v // 1000}k" if v >= 1000 else str(v))
    return f"{k(c['points'])} pts / {k(c['triangles'])} tri / {c['images']} img"


def markdown(results: list[dict[str, Any]], sl: dict[str, dict[str, float]]) -> str:
    """Tables: per-stage seconds, targets and memory, slopes."""
    ok = [r for r in results if "error" not in r]
    cols = ["total"] + STAGES
    lines = ["| case | " + " | ".join(cols) + " | load avg (1 min, before→after) |",
             "|---" * (len(cols) + 2) + "|"]
    for r in ok:
        s = r["seconds"]
        lines.append(f"| {_fmt_case(r['case'])} | " + " | ".join(
            f"{s.get(c, 0.0):.2f}" for c in cols)
            + f" | {r['loadavg_before'][0]:.2f}→{r['loadavg_after'][0]:.2f} |")
    lines += ["", "| case | rest (s) | SIFT work (s), in workers | rest / SIFT work (target < 0.5)"
              " | rescale vs copy (target ≥ 0.5) | peak RSS (GB), SIFT worker's "
              "| above imports (GB) | SIFT working set (GB) | libraries' fixed "
              "(GB) | input-dependent: above imports − SIFT set − fixed (GB) | budget "
              "2·mesh+model (GB) | peak in stage | registered | inliers | descriptor index | "
              "mesh kept by the crop |", "|---" * 16 + "|"]
    for r in ok:
        d = derived(r)
        lines.append(
            f"| {_fmt_case(r['case'])} | {d['rest_s']:.2f} | {d['sift_work_s']:.2f}, "
            f"{r.get('pipeline_timings', {}).get('sift_in_workers', 0.0):.2f} | "
            f"{d['rest_over_sift']:.2f} "
            f"{'✓' if d['rest_ok'] else '✗'} | {d['rescale_vs_copy']:.2f} "
            f"{'✓' if d['rescale_ok'] else '✗'} | {r['peak_rss_bytes'] / 2**30:.2f}, "
            f"{r.get('worker_peak_rss_bytes', 0) / 2**30:.2f} | "
            f"{d['mem_above_baseline'] / 2**30:.2f} | "
            f"{r.get('sift_working_bytes', 0) / 2**30:.2f} | {d['mem_fixed'] / 2**30:.2f} | "
            f"{d['mem_input'] / 2**30:.2f} {'✓' if d['mem_ok'] else '✗'} | "
            f"{d['mem_budget'] / 2**30:.2f} | {r['peak_stage']} | "
            f"{r['registered']}/{r['n_images']} | {r['inliers']} | "
            f"{r.get('index', {}).get('method', '?')}, "
            f"{r.get('index', {}).get('descriptors', 0):,} desc. | "
            f"{100 * r.get('crop', {}).get('kept_fraction', float('nan')):.2f} % |")
    for r in results:
        if "error" in r:
            lines.append(f"\nFAILED {_fmt_case(r['case'])}: {r['error'][-500:]} "
                         f"(stages timed before: {r.get('seconds', {})})")
    lines += ["", "| axis | total | rest | peak RSS | per stage (slope > 0.01 s stages) |",
              "|---|---|---|---|---|"]
    for axis, row in sl.items():
        per = ", ".join(f"{k} {v:.2f}" for k, v in row.items()
                        if k not in ("total", "rest", "peak_mem"))
        lines.append(f"| {axis} | {row['total']:.2f} | {row['rest']:.2f} | "
                     f"{row['peak_mem']:.2f} | {per} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "sfmls_bench",
                    help="folder for the generated inputs (kept between runs)")
    ap.add_argument("--quick", action="store_true", help="small subset (< 3 min)")
    ap.add_argument("--cases", help="only these cases: 'points,triangles,images;...'")
    ap.add_argument("--colmap", action="store_true", help="also compare with COLMAP 3.8")
    ap.add_argument("--json", type=Path, help="write all results as JSON")
    ap.add_argument("--markdown", type=Path, help="write the tables as Markdown")
    ap.add_argument("--timeout", type=float, default=3600.0, help="per case, seconds")
    ap.add_argument("--sift-reference", action="store_true",
                    help="also time SIFT + matching on a 4000 x 3000 upscaled laser image")
    ap.add_argument("--from-json", type=Path, help="only print the tables of a --json file")
    ap.add_argument("--camera", choices=list(CAMERAS), default="vga",
                    help="laser and model camera: the small demo's 640x480 (vga), a 1920x1080 "
                         "ROV camera (hd) or a 4000x3000 still camera (12mp); the data sets "
                         "of the last two take minutes to make, once")
    ap.add_argument("--workers", type=int,
                    help="SIFT worker processes (default: the tool's, one per free core)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.from_json:
        saved = json.loads(args.from_json.read_text(encoding="utf-8"))
        has_base = any(r["case"] == BASE for r in saved["results"])
        print(markdown(saved["results"], slopes(saved["results"],
                                                BASE if has_base else QUICK_BASE)))
        return 0
    args.work.mkdir(parents=True, exist_ok=True)
    if args.child == "fixed":
        print(json.dumps(fixed_library_memory(args.work, args.camera)))
        return 0
    if args.child:
        p, t, i = (int(v) for v in args.child.split(","))
        print(json.dumps(run_case(args.work, p, t, i, args.camera, args.workers)))
        return 0
    t_start, started = time.perf_counter(), time.strftime("%Y-%m-%d %H:%M:%S %Z")
    if args.cases:
        cases = [dict(zip(("points", "triangles", "images"), map(int, c.split(",")),
                          strict=True)) for c in args.cases.split(";")]
    else:
        cases = plan(args.quick)
    base = QUICK_BASE if args.quick else BASE
    fixed = run_fixed_subprocess(args.work, args.camera, args.timeout)
    print(f"libraries' fixed working memory: {fixed / 2**30:.3f} GB", flush=True)
    results = []
    for case in cases:
        # Inputs are made in the parent (not timed as part of the case).
        case_inputs(args.work, case["points"], case["triangles"], case["images"], args.camera)
        r = run_case_subprocess(args.work, case, args.timeout, args.camera, args.workers)
        r["fixed_library_bytes"] = fixed
        print(f"{_fmt_case(case)}: " + (f"{r['seconds']['total']:.1f} s, peak "
              f"{r['peak_rss_bytes'] / 2**30:.2f} GB, load {r['loadavg_before']}"
              if "error" not in r else "FAILED " + r["error"][-300:]), flush=True)
        results.append(r)
    sl = slopes(results, base)
    report: dict[str, Any] = {"machine": machine(), "started": started, "command": sys.argv,
                              "camera": args.camera, "results": results, "slopes": sl}
    if args.colmap:
        from colmap_compare import compare_with_colmap  # scripts/colmap_compare.py
        report["colmap"] = compare_with_colmap(demo_dataset(args.work), args.work)
    if args.sift_reference:
        report["sift_reference"] = sift_reference(args.work)
        print(json.dumps(report["sift_reference"]))
    report["elapsed_s"] = round(time.perf_counter() - t_start, 1)
    text = markdown(results, sl)
    print(text)
    if "colmap" in report:
        print(json.dumps(report["colmap"], indent=1))
    print(f"machine: {report['machine']}\nelapsed {report['elapsed_s']} s")
    if args.markdown:
        args.markdown.write_text(text, encoding="utf-8")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=float), encoding="utf-8")
    return 0 if all("error" not in r for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())

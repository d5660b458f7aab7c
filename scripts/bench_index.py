"""Descriptor index: build time, search time and match recall for IVF settings (issue #7).

Uses a benchmark case (``scripts/benchmark.py`` data, made once in ``--work``): the padded
model's descriptor pool, and the SIFT features of real laser images as queries. Recall is
that of the ratio-test matches of exact brute-force search (same 3D point, also passing
the test), on a seeded subset of each image's keypoints; search time is for all of them.

    .venv/bin/python scripts/bench_index.py --work /tmp/lsbench/work --camera hd \\
        --points 1000000 --configs "1,8;1,6;1,4;2,8;2,12"
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _case(work: Path, camera: str, points: int) -> dict[str, Path]:
    import benchmark
    return benchmark.case_inputs(work, points, 100_000, 6, camera)


def _queries(lasers: Path, images: int) -> list[Any]:
    """SIFT features of the first ``images`` laser images (pipeline options)."""
    from sfm_laserscale.io.images import read_rgb
    from sfm_laserscale.registration.options import RegistrationOptions
    from sfm_laserscale.registration.sift import extract_sift
    files = sorted(p for p in lasers.iterdir() if p.suffix.lower() in (".png", ".jpg"))
    return [extract_sift(read_rgb(p), RegistrationOptions()) for p in files[:images]]


def _matched(matches: Any) -> set[tuple[int, int]]:
    return set(zip(matches.query_idx.tolist(), matches.point_rows.tolist(), strict=True))


def measure(pool: Any, model: Any, queries: list[Any], lists_factor: float, probe: int,
            exact: list[set[tuple[int, int]]], subsets: list[np.ndarray]) -> dict[str, Any]:
    """Build an IVF with ``lists_factor`` × √P cells and ``probe`` probes; time and recall."""
    from sfm_laserscale.model import ImageFeatures
    from sfm_laserscale.registration.index import index_pool
    from sfm_laserscale.registration.match import match_to_model
    from sfm_laserscale.registration.options import IndexOptions, MatchOptions
    nlist = int(np.clip(round(lists_factor * np.sqrt(len(pool.descriptors))), 16, 1 << 14))
    t0 = time.perf_counter()
    index = index_pool(model, pool, IndexOptions(ivf_lists=nlist, ivf_probe=probe))
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    for q in queries:
        match_to_model(q, index, MatchOptions())
    search = time.perf_counter() - t0
    found = total = 0
    for q, sub, truth in zip(queries, subsets, exact, strict=True):
        got = _matched(match_to_model(ImageFeatures(q.xy_px[sub], q.descriptors[sub]), index,
                                      MatchOptions()))
        found += len(truth & got)
        total += len(truth)
    return {"lists": nlist, "probe": probe, "build_s": round(build, 3),
            "search_s_per_image": round(search / len(queries), 3),
            "queries_per_image": int(np.mean([len(q.descriptors) for q in queries])),
            "recall": round(found / max(total, 1), 4), "exact_matches": total}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/lsbench/work"))
    ap.add_argument("--camera", default="hd", choices=("vga", "hd", "12mp"))
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--images", type=int, default=2)
    ap.add_argument("--subset", type=int, default=1500, help="keypoints per image for recall")
    ap.add_argument("--configs", default="1,8;1,6;1,4;2,8;2,12",
                    help="'lists factor (× √P),probe;...'")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    from sfm_laserscale.io.models import load_model
    from sfm_laserscale.model import ImageFeatures
    from sfm_laserscale.registration.features import load_model_features
    from sfm_laserscale.registration.index import descriptor_pool, index_pool
    from sfm_laserscale.registration.match import match_to_model
    from sfm_laserscale.registration.options import IndexOptions, MatchOptions
    from sfm_laserscale.run_types import ScaleOptions
    paths = _case(args.work, args.camera, args.points)
    opts = ScaleOptions(progress=False)
    model = load_model(paths["model"])
    feats = load_model_features(model, paths["model"], paths["database"], None, None,
                                replace(opts.tie, progress=False))
    pool = descriptor_pool(model, feats, opts.index)
    del feats
    queries = _queries(paths["lasers"], args.images)
    rng = np.random.default_rng(0)
    subsets = [np.sort(rng.choice(len(q.descriptors), min(args.subset, len(q.descriptors)),
                                  replace=False)) for q in queries]
    exact_index = index_pool(model, pool, IndexOptions(exact=True))
    exact = [_matched(match_to_model(ImageFeatures(q.xy_px[s], q.descriptors[s]), exact_index,
                                     MatchOptions()))
             for q, s in zip(queries, subsets, strict=True)]
    del exact_index
    rows = []
    for spec in args.configs.split(";"):
        factor, probe = spec.split(",")
        rows.append(measure(pool, model, queries, float(factor), int(probe), exact, subsets))
        print(json.dumps(rows[-1]), flush=True)
    print(f"\npool: {len(pool.descriptors):,} descriptors ({args.camera}, {args.points:,} points)")
    print("| cells | probe | build (s) | search per image (s) | recall |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['lists']} | {r['probe']} | {r['build_s']} | {r['search_s_per_image']} | "
              f"{r['recall']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Scenes whose SfM model has its own focal-length error (docs/SIMULATE.md, "Real SfM with a
focal error"): the demo's data set rendered and reconstructed by pycolmap with the focal length
off by ε and held fixed (the mesh carried into that model), then ``scale`` as a user runs it.
Reports, per scene, the headline's error in its σ, the intrinsics term's share, what the focal
check measured and the warnings' codes.

    .venv/bin/python scripts/bench_focal_error.py --out /tmp/focal [--eps -0.0015 0.0015 ...]
        [--seeds 0 1] [--rig diverging rov] [--small]

Writes OUT/results.json and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from sfm_laserscale.commands import scale as scale_command
from sfm_laserscale.commands.demo import scale_inputs_for
from sfm_laserscale.run_types import ScaleOptions
from sfm_laserscale.synthetic.dataset import DemoDataOptions, make_demo_dataset


def one(out: Path, eps: float, seed: int, rig: str, small: bool) -> dict[str, Any]:
    tag = f"{rig}_{'small' if small else 'full'}_s{seed}_e{eps:+.4f}"
    t0 = time.perf_counter()
    data = make_demo_dataset(out / tag / "data", DemoDataOptions(
        small=small, seed=seed, progress=False, rig=rig, sfm_focal_error=eps), overwrite=True)
    res = scale_command.run(scale_inputs_for(data), out / tag / "scale",
                            ScaleOptions(progress=False), overwrite=True)
    r, truth = res.report, data.true_scale
    s, f = r["scale"], r["model_checks"]["focal"]
    fc = r["methods"].get("focal_corrected")
    return {
        "scene": tag, "eps_pct": 100 * eps, "seed": seed, "rig": rig, "small": small,
        "method": s["method"], "error_pct": 100 * (s["value"] / truth - 1),
        "sigma_pct": 100 * s["std"] / truth, "z": (s["value"] - truth) / s["std"],
        "intrinsics_share": s["budget_shares"].get("intrinsics"),
        "focal_sigma_pct": r["model_error"]["intrinsics"]["cameras"][0]["focal_sigma_pct"],
        "focal_fit_pct": f["focal_error_pct"], "focal_fit_sigma_pct": f["sigma_pct"],
        "widened": f["headline_widened"],
        "corrected_z": None if not fc else (fc["value"] - truth) / fc["std"],
        "warnings": [w["code"] for w in r["warnings"] if w["level"] == "warning"],
        "seconds": time.perf_counter() - t0,
    }


def table(rows: list[dict[str, Any]]) -> str:
    out = ["| scene | SfM focal error | headline error | σ | error / σ | intrinsics share | "
           "focal fit | focal-corrected error / σ | warnings |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        fit = ("–" if r["focal_fit_pct"] is None
               else f"{r['focal_fit_pct']:+.3f} ± {r['focal_fit_sigma_pct']:.3f} %")
        cz = "–" if r["corrected_z"] is None else f"{r['corrected_z']:+.2f}"
        out.append(f"| {r['scene']} | {r['eps_pct']:+.2f} % | {r['error_pct']:+.3f} % | "
                   f"{r['sigma_pct']:.3f} % | {r['z']:+.2f} | {r['intrinsics_share']:.2f} | "
                   f"{fit} | {cz} | {', '.join(r['warnings']) or '–'} |")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--eps", type=float, nargs="+",
                    default=[-0.0015, -0.001, -0.0005, 0.0, 0.0005, 0.001, 0.0015, 0.005])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--rig", nargs="+", default=["diverging"])
    ap.add_argument("--small", action="store_true")
    a = ap.parse_args()
    rows = []
    for rig in a.rig:
        for seed in a.seeds:
            for eps in a.eps:
                rows.append(one(a.out, eps, seed, rig, a.small))
                print(table(rows[-1:]).splitlines()[-1], flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "results.json").write_text(json.dumps(rows, indent=1), encoding="utf-8")
    print(table(rows))


if __name__ == "__main__":
    main()

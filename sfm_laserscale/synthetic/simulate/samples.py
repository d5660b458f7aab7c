"""The trial records as rows of estimates (a column store per setting, method and laser or
pair), the rejection counts, and the PCM-joint groups of views with their rows."""

from __future__ import annotations

import math
from array import array
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.fusion import fuse
from sfm_laserscale.methods.pcm_joint import PcmJointOptions, estimate_pcm_joint
from sfm_laserscale.rig import Rig
from sfm_laserscale.synthetic.simulate.configs import LaserSetting, SimulationOptions
from sfm_laserscale.synthetic.simulate.trial import LaserOutcome, TrialRecord
from sfm_laserscale.synthetic.simulate.views import ViewJob
from sfm_laserscale.uncertainty import ImageEstimates, ImageObservation

Z95 = 1.959963984540054  # two-sided 95 % normal quantile


class SettingKey(NamedTuple):
    """What one row of results.json aggregates over."""

    config: str
    area: str
    distance_m: float
    sigma_f_px: float
    sigma_l_px: float


class SampleTable:
    """Column store of every estimate: one row per (view, method, laser or pair)."""

    FLOATS = ("value", "sigma", "lo", "hi", "pitch", "roll", "depth")
    INTS = ("key", "view", "round", "sign", "method", "sub", "edge")

    def __init__(self) -> None:
        self.keys: list[SettingKey] = []
        self.vocab: list[str] = []
        self._key_ids: dict[SettingKey, int] = {}
        self._codes: dict[str, int] = {}
        self._f = {c: array("d") for c in self.FLOATS}
        self._i = {c: array("q") for c in self.INTS}

    def key_id(self, key: SettingKey) -> int:
        """Index of a setting key (added when new)."""
        if key not in self._key_ids:
            self._key_ids[key] = len(self.keys)
            self.keys.append(key)
        return self._key_ids[key]

    def code(self, text: str) -> int:
        """Integer code of a method or laser name."""
        if text not in self._codes:
            self._codes[text] = len(self.vocab)
            self.vocab.append(text)
        return self._codes[text]

    def add(self, key: SettingKey, method: str, sub: str, value: float, sigma: float,
            interval: tuple[float, float], view: tuple[int, int, int, float, float],
            depth: float = float("nan"), edge: int = 0) -> None:
        """One estimate; view = (view id, round, sign, pitch, roll); edge: 0 normal, 1 only
        without the depth-edge check (it uses an edge spot), −1 only with it (as ``scale``)."""
        floats = (value, sigma, interval[0], interval[1], view[3], view[4], depth)
        for c, v in zip(self.FLOATS, floats, strict=True):
            self._f[c].append(float(v))
        ints = (self.key_id(key), view[0], view[1], view[2], self.code(method), self.code(sub),
                edge)
        for c, n in zip(self.INTS, ints, strict=True):
            self._i[c].append(int(n))

    def __len__(self) -> int:
        return len(self._f["value"])

    def arrays(self) -> dict[str, NDArray[Any]]:
        """Every column as a numpy array (methods and subs as integer codes)."""
        out: dict[str, NDArray[Any]] = {c: np.frombuffer(a, dtype=np.float64)
                                        for c, a in self._f.items()}
        out.update({c: np.frombuffer(a, dtype=np.int64) for c, a in self._i.items()})
        return out


@dataclass
class Collected:
    """Trial records turned into estimate rows, rejection counts and PCM-joint groups."""

    table: SampleTable = field(default_factory=SampleTable)
    rejected: Counter[tuple[SettingKey, str]] = field(default_factory=Counter)
    groups: dict[tuple[SettingKey, int, int], list[tuple[ViewJob, LaserOutcome]]] = field(
        default_factory=lambda: defaultdict(list))
    views: int = 0
    failed: Counter[str] = field(default_factory=Counter)
    rotation_error_deg: list[float] = field(default_factory=list)
    centre_error_m: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)  # per trial


def _view(job: ViewJob) -> tuple[int, int, int, float, float]:
    return (job.index, job.round, job.sign, job.pitch_deg, job.roll_deg)


def _interval(value: float, sigma: float) -> tuple[float, float]:
    return (value - Z95 * sigma, value + Z95 * sigma)


def _ingest_fused(col: Collected, key: SettingKey, v: tuple[int, int, int, float, float],
                  out: LaserOutcome) -> None:
    """Per-view fusions (pipeline σ and σ without Birge inflation), with and without the edge
    spots when the view has any."""
    variants = [(out.fused, -1 if out.edge_spots else 0)]
    if out.edge_spots:
        variants.append((out.fused_unchecked, 1))
    for fused, edge in variants:
        for m, (value, std, lo, hi, gls) in fused.items():
            if not math.isfinite(value):
                col.rejected[(key, f"{m}_fused")] += edge <= 0
                continue
            col.table.add(key, f"{m}_fused", "", value, std, (lo, hi), v, edge=edge)
            col.table.add(key, f"{m}_fused_gls", "", value, gls, _interval(value, gls), v,
                          edge=edge)


def _ingest_outcome(col: Collected, key: SettingKey, job: ViewJob, out: LaserOutcome) -> None:
    """Rows of one laser setting in one view: singles, per-view fusions, Davis & Tusting."""
    t, v = col.table, _view(job)
    for laser in out.spot_reasons:
        col.rejected[(key, f"spot:{laser}")] += 1
    for laser in out.edge_spots:
        col.rejected[(key, f"edge:{laser}")] += 1
    if out.estimates is not None:
        for e in out.estimates.estimates:
            if e.rejected or not (math.isfinite(e.scale) and math.isfinite(e.sigma)):
                col.rejected[(key, e.method)] += 1
                continue
            depth = abs(out.depth_difference_m.get(e.laser, float("nan")))
            edge = int(any(las in out.edge_spots for las in e.laser.split("+")))
            t.add(key, e.method, e.laser, e.scale, e.sigma, _interval(e.scale, e.sigma), v,
                  depth, edge)
    _ingest_fused(col, key, v, out)
    if math.isfinite(out.davis_tusting):
        t.add(key, "davis_tusting", "", out.davis_tusting, float("nan"), (np.nan, np.nan), v)
    if out.observation is not None and out.estimates is not None:
        col.groups[(key, job.round, job.sign)].append((job, out))


def collect(records: Iterable[TrialRecord], settings: Sequence[LaserSetting]) -> Collected:
    """Turn trial records into estimate rows (and remember the views for PCM-joint)."""
    col = Collected()
    for rec in records:
        col.views += 1
        col.cpu_s.append(rec.cpu_s)
        job = rec.job
        if not rec.registered:
            col.failed[rec.reason or "registration failed"] += 1
            for s in settings:
                key = SettingKey(s.config, job.area, job.distance_m, job.sigma_f_px, s.sigma_l_px)
                col.rejected[(key, "registration")] += 1
            continue
        col.rotation_error_deg.append(rec.rotation_error_deg)
        col.centre_error_m.append(rec.centre_error_m)
        for out in rec.outcomes:
            s = settings[out.setting]
            key = SettingKey(s.config, job.area, job.distance_m, job.sigma_f_px, s.sigma_l_px)
            _ingest_outcome(col, key, job, out)
    return col


@dataclass(frozen=True)
class GroupTask:
    """A group of views of one setting for PCM-joint (sent to a worker)."""

    key: SettingKey
    gid: int
    views: tuple[tuple[int, int, int, float, float], ...]  # _view of each member
    depths: tuple[dict[str, float], ...]
    observations: tuple[ImageObservation, ...]
    estimates: tuple[ImageEstimates, ...]
    rig: Rig
    options: SimulationOptions


Row = tuple[str, str, float, float, tuple[float, float], tuple[int, int, int, float, float],
            float]


@dataclass(frozen=True)
class GroupResult:
    """Rows (method, laser/pair, value, σ, interval, view, depth) and rejected methods."""

    key: SettingKey
    rows: tuple[Row, ...]
    rejected: tuple[str, ...]


def joint_group(task: GroupTask) -> GroupResult:
    """PCM-joint over one group of views, the midpoint PCM fused over the same views, and
    each view's scale with the joint beam direction."""
    opts = task.options
    res = estimate_pcm_joint(task.observations, task.rig,
                             PcmJointOptions(estimation=opts.estimation, fusion=opts.fusion))
    nan = float("nan")
    first = task.views[0]
    gview = (task.gid, first[1], first[2], nan, nan)
    rows: list[Row] = []
    rejected = []
    f = res.fused
    if res.joint and math.isfinite(f.value):
        rows.append(("pcm_joint", "", f.value, f.std, f.ci95, gview, nan))
    else:
        rejected.append("pcm_joint")
    mid = fuse(task.estimates, "pcm", opts.fusion)
    if math.isfinite(mid.value):
        rows.append(("pcm_group", "", mid.value, mid.std, mid.ci95, gview, nan))
    member = {o.image: i for i, o in enumerate(task.observations)}
    for fit in res.pairs if res.joint else ():
        for im in fit.images:
            if im.rejected or im.image not in member:
                continue
            i = member[im.image]
            rows.append(("pcm_joint_view", fit.pair, im.implied_scale, im.implied_sigma,
                         _interval(im.implied_scale, im.implied_sigma), task.views[i],
                         abs(task.depths[i].get(fit.pair, nan))))
    return GroupResult(task.key, tuple(rows), tuple(rejected))


def group_tasks(col: Collected, settings: Sequence[LaserSetting], options: SimulationOptions
                ) -> list[GroupTask]:
    """Random groups of ``group_size`` views of one setting, noise draw and sign (none for the
    noise table: its views are identical, which leaves the beam direction undetermined)."""
    if options.mode == "noise-table":
        return []
    rigs = {s.config: s.rig for s in settings}
    tasks: list[GroupTask] = []
    for n, ((key, _, _), items) in enumerate(sorted(col.groups.items(), key=lambda kv: kv[0])):
        rig = rigs[key.config]
        if not rig.pairs or len(items) < options.group_size:
            continue
        rng = np.random.default_rng(np.random.SeedSequence([options.seed, 5, n]))
        order = rng.permutation(len(items))
        for idx in np.array_split(order, len(items) // options.group_size):
            members = [items[i] for i in idx]
            tasks.append(GroupTask(
                key, len(tasks), tuple(_view(j) for j, _ in members),
                tuple(o.depth_difference_m for _, o in members),
                tuple(o.observation for _, o in members if o.observation is not None),
                tuple(o.estimates for _, o in members if o.estimates is not None), rig,
                options))
    return tasks


def add_groups(col: Collected, results: Iterable[GroupResult]) -> None:
    """Add the PCM-joint rows of every group (and forget the views kept for grouping)."""
    for res in results:
        for method, sub, value, sigma, interval, view, depth in res.rows:
            col.table.add(res.key, method, sub, value, sigma, interval, view, depth)
        for method in res.rejected:
            col.rejected[(res.key, method)] += 1
    col.groups.clear()

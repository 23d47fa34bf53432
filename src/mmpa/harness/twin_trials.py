"""Trials of the paper 000 experiments on twin sites: each task taught once per run (a task
bundle in the run folder's ``taught/``), every trial run in a site world built from that
bundle (kept per process, :func:`trial_job` on any executor) and seeded on its own, so a
trial's row is the same alone, inside a run, or on another worker."""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mmpa.backends.twin.scene import SceneConfig
from mmpa.core.errors import ConfigError
from mmpa.harness.executor import SerialExecutor
from mmpa.harness.ipe_eval import ipe_rows, offset_row, pose_errors
from mmpa.harness.recording import record_spec, trial_bag_name
from mmpa.harness.twin_site import SITE_DEMOS, TEACH_SITE, MMPAExperimentConfig, TwinSite
from mmpa.missions.teach_repeat import (
    AutomationConfig,
)
from mmpa.tasks import Task, read_bundle, write_bundle
from mmpa.tasks.bundle import BUNDLE_FILES

__all__ = [
    "TIMING_COLUMNS",
    "TrialGroup",
    "clear_site_cache",
    "ipe_trials",
    "run_trial_groups",
    "trial_job",
]

#: a progress callback: (message, fraction done)
Progress = Callable[[str, float], None]


@dataclass
class TrialGroup:
    """One group of trials of a run: ``label`` (extra columns of its rows, and part of each
    trial's key ``{**label, "site", "trial"}``), its ``sites``, the automation settings
    (None: the site's, :meth:`TwinSite.automation_config`), the world (None:
    ``cfg.scene``); ``execute``/``tmma`` as in :func:`ipe_trials`."""

    label: dict = field(default_factory=dict)
    sites: list[str] | None = None
    automation: AutomationConfig | None = None
    scene: SceneConfig | None = None
    execute: bool = False  # execute the adapted path (re-parks allowed), score the tool tip
    tmma: bool = False  # replay the taught joints (TMMA) first from the same park
    trials: list[int] | None = None  # which trials (None: all, 0 .. cfg.n_trials() - 1)


#: the columns of a trial's row that measure time or memory: the only ones that differ
#: between two runs of the same trial (executor, worker count, machine load)
TIMING_COLUMNS = frozenset({"trial_s", "worker_rss_mb", "compute_s", "final_s", "register_s_mean"})


def worker_config_json(cfg: MMPAExperimentConfig) -> str:
    """The settings a trial worker needs: ``cfg``'s :class:`MMPAExperimentConfig` fields less
    ``trials`` (a trial does not depend on how many there are), as canonical JSON."""
    keep = set(MMPAExperimentConfig.model_fields) - {"trials"}
    return json.dumps(cfg.model_dump(mode="json", include=keep), sort_keys=True)


def _digest(*parts: object) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


def teach_bundle_files(
    cfg_json: str, site: str, demo: str, scene_json: str | None
) -> dict[str, bytes]:
    """Teach ``demo`` at ``site`` in a new twin (a worker job); the task bundle's files
    (:func:`~mmpa.tasks.write_bundle`) by name."""
    cfg = MMPAExperimentConfig.model_validate_json(cfg_json)
    scene = SceneConfig.model_validate_json(scene_json) if scene_json else None
    with TwinSite(cfg, site, scene, demo=demo) as ts, tempfile.TemporaryDirectory() as d:
        path = write_bundle(ts.taught.task, Path(d) / "task")
        return {f: (path / f).read_bytes() for f in BUNDLE_FILES}


#: a worker's sites, built from task bundles: (settings, site, world, task) digest -> site
_SITES: OrderedDict[str, TwinSite] = OrderedDict()
_SITES_KEPT = 2


def clear_site_cache() -> None:
    """Close the sites this process keeps between trials."""
    while _SITES:
        _SITES.popitem(last=False)[1].close()


def _read_bundle_handle(handle: str | dict[str, bytes]) -> Task:
    if isinstance(handle, str):
        return read_bundle(handle)
    with tempfile.TemporaryDirectory() as d:  # the files themselves (a Ray object)
        for name, data in handle.items():
            (Path(d) / Path(name).name).write_bytes(data)
        return read_bundle(d)


def _world_key(spec: dict) -> str:
    return _digest(spec["cfg"], spec["site"], spec["scene"], spec["bundle_id"])


def _cached_site(spec: dict, bundle: str | dict[str, bytes]) -> TwinSite:
    key = _world_key(spec)
    if key in _SITES:
        _SITES.move_to_end(key)
        return _SITES[key]
    cfg = MMPAExperimentConfig.model_validate_json(spec["cfg"])
    scene = SceneConfig.model_validate_json(spec["scene"]) if spec["scene"] else None
    ts = TwinSite(cfg, spec["site"], scene, task=_read_bundle_handle(bundle))
    _SITES[key] = ts
    while len(_SITES) > _SITES_KEPT:
        _SITES.popitem(last=False)[1].close()
    return ts


def trial_job(spec_json: str, bundle: str | dict[str, bytes], trial: int) -> dict:
    """Run trial ``trial`` of one site (a worker job): ``{"row": ..., "iters": [...]}``.
    ``spec_json`` holds the settings (``cfg``), ``site``, ``scene``, ``automation``,
    ``kind`` (``"ipe"``: park and IPE; ``"park"``: park only), ``execute``, ``tmma``,
    ``label``, and ``record`` when the trial records itself (a folder: the trial's bag is
    :func:`~mmpa.harness.recording.trial_bag_name` there;
    :func:`~mmpa.harness.recording.record_trials`); ``bundle`` the taught task (a bundle's
    path, or its files)."""
    spec = json.loads(spec_json)
    ts = _cached_site(spec, bundle)
    ts.begin_trial(trial)
    record = spec.get("record")
    if record is None:
        return _trial(ts, spec, trial)
    with ts.recording(Path(record) / trial_bag_name(spec["label"], spec["site"], trial)):
        return _trial(ts, spec, trial)


def _trial(ts: TwinSite, spec: dict, trial: int) -> dict:
    if spec["kind"] == "park":
        ts.park(session=trial + 1)
        row = {"site": spec["site"], "trial": trial, "mode": ts.cfg.parking}
        return {"row": {**row, **offset_row(ts.parking_truth())}, "iters": []}
    auto = spec["automation"]
    a = AutomationConfig.model_validate_json(auto) if auto else ts.automation_config()
    if not spec["execute"]:  # IPE-only experiments measure IPE at the first park
        a = a.model_copy(update={"max_reparks": 0})
    row, its = _ipe_trial(ts, trial, a, spec["execute"], spec["tmma"], spec["label"])
    return {"row": row, "iters": its}


def _ipe_trial(
    ts: TwinSite, i: int, a: AutomationConfig, execute: bool, tmma: bool, label: dict
) -> tuple[dict, list[dict]]:
    site = ts.site
    ts.park(session=i + 1)
    before = ts.parking_truth()
    row: dict = {**label, "site": site, "trial": i}
    if tmma:
        # TMMA may bump into the bench (the paper skipped Site 2' for that reason):
        # replay it in its own episode, then park again at the same pose
        row["tmma_mm"] = ts.run_tmma() * 1e3
        row["tmma_base_shift_mm"] = float(
            np.linalg.norm((ts.parking_truth() - before)[:3, 3]) * 1e3
        )
        ts.world.reset(site=site, pose2d=ts.parked_pose2d)
        before = ts.parking_truth()
    res = ts.run_ipe(a, execute=False)
    truth = ts.parking_truth()
    if res.reparks:  # the IPE figures are those of the last park
        e_r0, e_t0 = pose_errors(np.eye(4), before)
        row["park0_E_t"], row["park0_E_R"] = e_t0, e_r0
        before = ts.truth_after_repark
    r, its = ipe_rows(res.ipe, truth)
    row.update(offset_row(truth))
    row.update(r)
    row["base_drift_mm"] = float(np.linalg.norm((truth - before)[:3, 3]) * 1e3)
    row["plan_ok"] = res.ok
    row["reason"] = res.reason
    row["reparks"] = len(res.reparks)
    if execute:
        row["mmpa_mm"] = ts.execute(res) * 1e3 if res.ok else float("nan")
    return row, [{**label, "site": site, "trial": i, **it} for it in its]


def _trial_ids(g: TrialGroup, n: int) -> list[int]:
    ids = list(range(n)) if g.trials is None else [int(i) for i in g.trials]
    if any(i < 0 for i in ids):
        raise ConfigError(f"trial numbers must be >= 0, got {ids}")
    return ids


def _label_text(label: dict) -> str:
    return "".join(f"{k} {v}, " for k, v in label.items())


def run_trial_groups(
    cfg: MMPAExperimentConfig,
    progress: Progress,
    groups: list[TrialGroup],
    *,
    kind: str = "ipe",
    executor=None,
) -> list[tuple[list[dict], list[dict]]]:
    """Run ``cfg.n_trials()`` trials per site of every group on ``executor`` (an
    :class:`~mmpa.harness.executor.Executor`; None: in this process); rows per trial
    and per IPE iteration, per group, in the order (group, site, trial).

    Each task is taught once per (settings, teaching site, demonstration, world) in a twin
    of its own and kept as a task bundle in the run folder's ``taught/`` (reused by a
    resumed run); every trial then runs in a site world built from that bundle, seeded on
    its own (:meth:`TwinSite.begin_trial`), so its row is the same whatever ran before it
    and wherever it ran. Rows carry the trial's wall time ``trial_s`` and the peak memory
    of the process that ran it ``worker_rss_mb``. ``kind="park"`` only parks
    (``mmpa experiment parking``)."""

    own = executor is None
    ex = SerialExecutor() if own else executor
    try:
        return _run_groups(cfg, progress, groups, kind, ex)
    finally:
        clear_site_cache()
        if own:
            ex.close()


def _run_groups(cfg, progress, groups, kind, ex):
    cfg_json = worker_config_json(cfg)
    n = cfg.n_trials()
    taught_dir = ex.out / "taught"
    # 1. teach what is not taught yet (in parallel where the executor can)
    teach: dict[str, tuple] = {}
    for g in groups:
        scene_json = g.scene.model_dump_json() if g.scene is not None else None
        for site in g.sites or cfg.sites:
            if site not in TEACH_SITE:
                raise ConfigError(
                    f"no MMPA task is defined for site {site!r}; use {list(SITE_DEMOS)}"
                )
            args = (cfg_json, TEACH_SITE[site], SITE_DEMOS[site], scene_json)
            teach[_digest(*args)] = args
    missing = [k for k in teach if not (ex.resume and (taught_dir / k / BUNDLE_FILES[0]).exists())]
    if missing:
        progress(f"teaching {len(missing)} task(s)", 0.0)
        taught = ex.map(teach_bundle_files, [teach[k] for k in missing])
        for k, files in zip(missing, taught, strict=True):
            tmp = taught_dir / f".{k}.tmp"
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            for name, data in files.items():
                (tmp / name).write_bytes(data)
            shutil.rmtree(taught_dir / k, ignore_errors=True)
            tmp.rename(taught_dir / k)
    handles = {k: ex.bundle_handle(taught_dir / k) for k in teach}
    # 2. the trials
    jobs = []
    worlds: list[str] = []  # the site world of each job (as the worker caches it)
    for g in groups:
        scene_json = g.scene.model_dump_json() if g.scene is not None else None
        auto = g.automation.model_dump_json() if g.automation is not None else None
        for site in g.sites or cfg.sites:
            bundle_id = _digest(cfg_json, TEACH_SITE[site], SITE_DEMOS[site], scene_json)
            spec = {
                "cfg": cfg_json,
                "site": site,
                "scene": scene_json,
                "automation": auto,
                "kind": kind,
                "execute": g.execute,
                "tmma": g.tmma,
                "label": g.label,
                "bundle_id": bundle_id,
                **record_spec(),  # the bag folder while recording (record_trials)
            }
            spec_json = json.dumps(spec, sort_keys=True)
            world = _world_key(spec)
            for i in _trial_ids(g, n):
                worlds.append(world)
                key = {**g.label, "site": site, "trial": i}
                jobs.append((key, trial_job, (spec_json, handles[bundle_id], i)))

    def on_result(done: int, total: int, rec: dict) -> None:
        k = rec["key"]
        lab = {x: v for x, v in k.items() if x not in ("site", "trial")}
        progress(
            f"{_label_text(lab)}site {k['site']}: trial {k['trial'] + 1}/{n} done", done / total
        )

    # hand out the trials of one site world together (in the order the worlds first come):
    # a worker then builds each world about once
    first: dict[str, int] = {}
    for w in worlds:
        first.setdefault(w, len(first))
    order = sorted(range(len(jobs)), key=lambda i: (first[worlds[i]], i))
    records = ex.run(jobs, on_result, order=order)
    out: list[tuple[list[dict], list[dict]]] = []
    it = iter(records)
    for g in groups:
        rows: list[dict] = []
        iters: list[dict] = []
        for _site in g.sites or cfg.sites:
            for _ in _trial_ids(g, n):
                rec = next(it)
                row = dict(rec["result"]["row"])
                row["trial_s"] = rec["trial_s"]
                row["worker_rss_mb"] = rec["worker_rss_mb"]
                rows.append(row)
                iters += rec["result"]["iters"]
        out.append((rows, iters))
    progress("done", 1.0)
    return out


def ipe_trials(
    cfg: MMPAExperimentConfig,
    progress: Progress,
    *,
    execute: bool = False,
    tmma: bool = False,
    automation: AutomationConfig | None = None,
    sites: list[str] | None = None,
    scene: SceneConfig | None = None,
    label: dict | None = None,
    executor=None,
) -> tuple[list[dict], list[dict]]:
    """Park / IPE (/ execute, / TMMA) trials of one group (:func:`run_trial_groups`); rows
    per trial and per IPE iteration.

    The parking truth is read after IPE (arm motion can nudge the base), the TMMA replay
    (when asked) runs first from the same parked pose. Re-parks (a path out of reach) only
    when the path is executed: the IPE-only tables are about the first park."""
    group = TrialGroup(label or {}, sites, automation, scene, execute, tmma)
    return run_trial_groups(cfg, progress, [group], executor=executor)[0]

"""``mmpa experiment ipe``: paper 000 Table 3, Fig. 8 and Fig. 9 in the twin.

Per site (1, 2, 2'), 30 trials by default: park with a Table 2 offset, run IPE, compare the
estimated ``dT_B`` with the truth (E_R, E_t of eq. 12-13, and the 6D vector difference).
"""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mmpa.experiments.paper000 import figures as paper000
from mmpa.harness.ipe_eval import ipe_stats
from mmpa.harness.runner import Context, Outcome, markdown_table, stats, write_csv
from mmpa.harness.twin_site import PAPER_BETA, MMPAExperimentConfig
from mmpa.harness.twin_trials import TrialGroup, run_trial_groups
from mmpa.missions.teach_repeat import AutomationConfig

#: the runner may run this experiment's trials on an executor (``--workers``, ``--executor``)
PARALLEL_TRIALS = True
#: every trial can record itself to a bag of its own (``mmpa experiment --record DIR``)
RECORDS_TRIALS = True

PAPER = "paper 000 Table 3, Fig. 8 and Fig. 9 (IPE accuracy, iterations, registration time)"


class Config(MMPAExperimentConfig):
    # also run the paper's own IPE settings (AutomationConfig.paper) on the same parks
    paper_method: bool = True


def paper_method_groups(cfg: MMPAExperimentConfig, execute: bool = False) -> list[TrialGroup]:
    """The same trials (same seed: the same teaching and parks) with the paper's own
    automation settings (:meth:`AutomationConfig.paper`, the paper's beta per site); rows
    labelled ``method="paper"``."""
    groups = []
    for site in cfg.sites:
        beta = PAPER_BETA.get(site) if cfg.beta_per_site else cfg.automation.ipe.beta
        groups.append(
            TrialGroup(
                {"method": "paper"}, [site], AutomationConfig.paper(beta=beta), execute=execute
            )
        )
    return groups


def method_trials(
    cfg: MMPAExperimentConfig,
    paper_method: bool,
    ctx: Context,
    execute: bool = False,
    tmma: bool = False,
) -> tuple[list[dict], list[dict], list[dict]]:
    """mmpa's trials (with TMMA first when ``tmma``) and (``paper_method``) the paper
    method's on the same parks, all on ``ctx.executor`` at once: ``(rows, paper rows,
    iteration rows)``."""
    groups = [TrialGroup({"method": "mmpa"}, execute=execute, tmma=tmma)]
    if paper_method:
        groups += paper_method_groups(cfg, execute)
    res = run_trial_groups(cfg, ctx.progress, groups, executor=ctx.executor)
    rows, iters = res[0]
    prows = [r for g in res[1:] for r in g[0]]
    iters += [r for g in res[1:] for r in g[1]]
    return rows, prows, iters


def summarize_sites(rows: list[dict], sites: list[str]) -> dict:
    out = {}
    for s in sites:
        r = [x for x in rows if x["site"] == s]
        out[s] = {
            "trials": len(r),
            **ipe_stats(r),
            "park_E_R": stats(x["park_E_R"] for x in r),
            "park_E_t": stats(x["park_E_t"] for x in r),
            "compute_s": stats(x["compute_s"] for x in r),
            "final_s": stats(x["final_s"] for x in r),
            "register_s": stats(x["register_s_mean"] for x in r),
        }
    return out


def run(cfg: Config, ctx: Context) -> Outcome:
    """The trials (:func:`method_trials`), the per-site figures, Fig. 8 and 9, the report."""
    rows, prows, iters = method_trials(cfg, cfg.paper_method, ctx)
    write_csv(ctx.out / "iterations.csv", iters)
    S = summarize_sites(rows, cfg.sites)
    P = summarize_sites(prows, cfg.sites) if prows else None
    figs = [plot_fig8(rows, cfg.sites, ctx.out / "fig8_parking_vs_ipe.png")]
    figs.append(plot_fig9(rows, iters, cfg.sites, ctx.out / "fig9_iterations.png"))
    table = []
    for s in cfg.sites:
        table += _table3_rows(s, S[s], P[s] if P is not None else None)
    report = _report(cfg, rows, table)
    summary = {s: _site_summary(S[s]) for s in cfg.sites}
    if P is not None:
        for s in cfg.sites:
            summary[s]["paper_method"] = _site_summary(P[s])
    return Outcome(rows + prows, summary, report, figs)


def _table3_rows(s: str, m: dict, q: dict | None) -> list[list]:
    """Table 3's lines of site ``s``: the paper (lab), the paper method (``q``, NaN when not
    run) and mmpa (``m``) in the twin; E_t in mm."""
    nan = float("nan")
    p = paper000.TABLE3.get(s, {})

    def pm(f, q=q):  # the paper method's figure, or NaN when not run
        return f(q) if q is not None else nan

    return [
        ["success", s, p.get("suc", nan), pm(lambda x: x["success"]), m["success"]],
        [
            "mean E_t (mm)",
            s,
            p.get("E_t", nan) * 1e3,
            pm(lambda x: x["E_t"]["mean"] * 1e3),
            m["E_t"]["mean"] * 1e3,
        ],
        [
            "SD E_t (mm)",
            s,
            p.get("E_t_sd", nan) * 1e3,
            pm(lambda x: x["E_t"]["sd"] * 1e3),
            m["E_t"]["sd"] * 1e3,
        ],
        ["max E_t (mm)", s, nan, pm(lambda x: x["E_t"]["max"] * 1e3), m["E_t"]["max"] * 1e3],
        ["mean E_R", s, p.get("E_R", nan), pm(lambda x: x["E_R"]["mean"]), m["E_R"]["mean"]],
        ["SD E_R", s, p.get("E_R_sd", nan), pm(lambda x: x["E_R"]["sd"]), m["E_R"]["sd"]],
        [
            "mean iterations",
            s,
            nan,
            pm(lambda x: x["iterations"]["mean"]),
            m["iterations"]["mean"],
        ],
        [
            "IPE compute, median (s)",
            s,
            nan,
            pm(lambda x: x["compute_s"]["median"]),
            m["compute_s"]["median"],
        ],
        [
            "per registration, mean (s)",
            s,
            1.6,
            pm(lambda x: x["register_s"]["mean"]),
            m["register_s"]["mean"],
        ],
        [
            "parking E_t, mean (mm)",
            s,
            paper000.TABLE2.get(s, {}).get("E_t", nan) * 1e3,
            pm(lambda x: x["park_E_t"]["mean"] * 1e3),
            m["park_E_t"]["mean"] * 1e3,
        ],
    ]


def _report(cfg: Config, rows: list[dict], table: list[list]) -> str:
    """report.md: the set-up, Table 3, the failures and the figures."""
    return (
        "IPE estimate of the relative parking pose dT_B against the simulator's truth "
        f"({cfg.n_trials()} trials per site, seed {cfg.seed}). Parking offsets are drawn from "
        "paper Table 2 (planar part; z, roll and pitch come from the terrain: the speed bump "
        "at Site 2'). Paper figures are from its robot (AGX Xavier) in its lab; the paper "
        "method is the paper's own IPE settings (one frame per view, global registration "
        "every iteration, colored ICP, no refinement, no retreat, no localization prior) on "
        "the same parks in the same twin.\n\n"
        + markdown_table(
            ["figure", "site", "paper (lab)", "paper method (twin)", "mmpa (twin)"],
            table,
            digits=4,
        )
        + "\nFailures (reason):\n\n"
        + "".join(
            f"- site {r['site']} trial {r['trial']}: {r['reason']}\n"
            for r in rows
            if not r["ipe_ok"]
        )
        + "\n![Fig. 8](fig8_parking_vs_ipe.png)\n\n![Fig. 9](fig9_iterations.png)\n"
    )


def _site_summary(m: dict) -> dict:
    return {
        "success": m["success"],
        "E_t_mm": m["E_t"]["mean"] * 1e3,
        "E_t_max_mm": m["E_t"]["max"] * 1e3,
        "E_R": m["E_R"]["mean"],
        "iterations": m["iterations"]["mean"],
        "compute_s_median": m["compute_s"]["median"],
        "final_s_median": m["final_s"]["median"],
    }


def plot_fig8(rows: list[dict], sites: list[str], path) -> str:
    fig = Figure(figsize=(9, 7))
    FigureCanvasAgg(fig)
    ax = fig.subplots(2, 2)
    pairs = [("park_E_R", "E_R"), ("park_E_R", "E_t"), ("park_E_t", "E_R"), ("park_E_t", "E_t")]
    for a, (x, y) in zip(ax.ravel(), pairs, strict=True):
        for s in sites:
            r = [q for q in rows if q["site"] == s and q["ipe_ok"]]
            a.scatter([q[x] for q in r], [q[y] for q in r], s=14, label=f"site {s}")
        a.set_xlabel(f"parking {x.split('_')[-1]}" + (" (m)" if x.endswith("E_t") else ""))
        a.set_ylabel(f"IPE {y}" + (" (m)" if y == "E_t" else ""))
        a.grid(alpha=0.3)
    ax[0, 0].legend()
    fig.suptitle("Fig. 8: parking error vs IPE error (twin)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path.name


def plot_fig9(rows: list[dict], iters: list[dict], sites: list[str], path) -> str:
    fig = Figure(figsize=(4 * len(sites), 12))
    FigureCanvasAgg(fig)
    ax = fig.subplots(4, len(sites), squeeze=False)
    for j, s in enumerate(sites):
        it = [q for q in iters if q["site"] == s and np.isfinite(q["E_t"])]
        ks = sorted({q["k"] for q in it})
        for i, (key, lab) in enumerate([("E_R", "E_R"), ("E_t", "E_t (m)")]):
            data = [[q[key] for q in it if q["k"] == k] for k in ks]
            if data:
                ax[i, j].boxplot(data, tick_labels=[str(k) for k in ks])
            ax[i, j].set_ylabel(lab)
            ax[i, j].set_title(f"site {s}: {key} per iteration")
        n_it = [q["iterations"] for q in rows if q["site"] == s and q["ipe_ok"]]
        if n_it:
            ax[2, j].hist(n_it, bins=np.arange(0.5, max(n_it) + 1.5, 1.0))
        ax[2, j].set_title("iterations to converge")
        data = [[q["register_s"] for q in it if q["k"] == k] for k in ks]
        ax[3, j].bar([str(k) for k in ks], [np.mean(d) if d else 0 for d in data])
        ax[3, j].set_title("mean time per registration (s)")
        for a in ax[:, j]:
            a.grid(alpha=0.3)
    fig.suptitle("Fig. 9: IPE per iteration (twin)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return path.name

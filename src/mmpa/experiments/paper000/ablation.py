"""``mmpa experiment ablation-alpha`` / ``ablation-beta``: paper 000 Appendix A.1-A.2.

For each convergence threshold alpha_1..alpha_5 (Tables A.1-A.3) or iteration limit
beta_1..beta_5 (Tables A.4-A.6) and each site, run IPE trials and report the success rate,
the mean number of iterations of the successful runs and E_R/E_t next to the paper's.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from mmpa.experiments.paper000 import figures as paper000
from mmpa.harness.ipe_eval import ipe_stats
from mmpa.harness.runner import Context, Outcome, markdown_table
from mmpa.harness.twin_site import PAPER_BETA, MMPAExperimentConfig
from mmpa.harness.twin_trials import TrialGroup, run_trial_groups

PARALLEL_TRIALS = True
#: every trial can record itself to a bag of its own (``mmpa experiment --record DIR``)
RECORDS_TRIALS = True

PAPER = "paper 000 Appendix A, Tables A.1-A.3 (alpha) and A.4-A.6 (beta)"


class Config(MMPAExperimentConfig):
    experiment: Literal["ablation-alpha", "ablation-beta"] = "ablation-alpha"
    levels: tuple[int, ...] = (1, 2, 3, 4, 5)  # which alpha_i / beta_i


def run(cfg: Config, ctx: Context) -> Outcome:
    is_alpha = cfg.experiment == "ablation-alpha"
    groups = []
    for site in cfg.sites:
        for lev in cfg.levels:
            ipe = cfg.automation.ipe
            if is_alpha:
                a = paper000.ALPHAS[f"alpha{lev}"]
                ipe = ipe.model_copy(
                    update={
                        "alpha": (*a[:3], *np.deg2rad(a[3:]).tolist()),
                        "beta": PAPER_BETA.get(site, ipe.beta),
                    }
                )
            else:
                ipe = ipe.model_copy(update={"beta": paper000.BETAS[site][lev - 1]})
            auto = cfg.automation.model_copy(update={"ipe": ipe})
            groups.append(TrialGroup({"level": lev}, [site], auto))
    res = run_trial_groups(cfg, ctx.progress, groups, executor=ctx.executor)
    rows = [r for g in res for r in g[0]]
    table, summary = [], {}
    paper = paper000.TABLE_A_ALPHA if is_alpha else paper000.TABLE_A_BETA
    for site in cfg.sites:
        for lev in cfg.levels:
            g = ipe_stats([x for x in rows if x["site"] == site and x["level"] == lev])
            suc, L, er, et = g["success"], g["iterations"]["mean"], g["E_R"], g["E_t"]
            p = paper[site][lev - 1]
            name = f"alpha{lev}" if is_alpha else f"beta{lev} = {paper000.BETAS[site][lev - 1]}"
            table.append(
                [site, name, suc, p[0], L, p[1], er["mean"], p[2], et["mean"] * 1e3, p[4] * 1e3]
            )
            summary[f"{site}/{name}"] = {
                "success": suc,
                "iterations": L,
                "E_t_mm": et["mean"] * 1e3,
            }
    report = (
        f"{cfg.n_trials()} trials per site and level, seed {cfg.seed}; iterations and errors over "
        "the successful runs. 'paper' columns are Tables "
        + ("A.1-A.3" if is_alpha else "A.4-A.6")
        + ".\n\n"
        + markdown_table(
            [
                "site",
                "setting",
                "suc",
                "suc (paper)",
                "L",
                "L (paper)",
                "E_R",
                "E_R (paper)",
                "E_t (mm)",
                "E_t (paper, mm)",
            ],
            table,
            digits=4,
        )
    )
    return Outcome(rows, summary, report)

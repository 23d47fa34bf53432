"""Evaluation of IPE and parking against the twin's truth (paper 000 §4.2-4.3): the pose
errors ``E_R`` (rad) and ``E_t`` (m) of eq. 12-13, the parking offset row ``dT_B*`` as
``[tx, ty, tz, r, p, y]`` (m, deg), and the per-trial / per-iteration rows of an IPE run."""

from __future__ import annotations

import numpy as np

from mmpa.core.geometry import (
    Array,
    T_to_vec6,
    rotation_error,
    translation_error,
)
from mmpa.harness.runner import stats
from mmpa.ipe.loop import IPEResult

__all__ = ["ipe_rows", "ipe_stats", "offset_row", "pose_errors"]


def pose_errors(est: Array | None, truth: Array) -> tuple[float, float]:
    """(E_R, E_t) of eq. 12-13; NaN when there is no estimate."""
    if est is None:
        return float("nan"), float("nan")
    return float(rotation_error(truth, est)), float(translation_error(truth, est))


def offset_row(truth: Array) -> dict[str, float]:
    """The 6D vector of a relative pose (m, deg) and its E_R/E_t against identity."""
    v = T_to_vec6(truth)
    e_r, e_t = pose_errors(np.eye(4), truth)
    return {
        "park_tx": v[0],
        "park_ty": v[1],
        "park_tz": v[2],
        "park_r_deg": np.rad2deg(v[3]),
        "park_p_deg": np.rad2deg(v[4]),
        "park_y_deg": np.rad2deg(v[5]),
        "park_E_R": e_r,
        "park_E_t": e_t,
    }


def ipe_stats(rows: list[dict]) -> dict:
    """Success rate of a group of IPE trial rows, and iterations, E_R, E_t statistics (see
    :func:`mmpa.harness.runner.stats`) over its successful trials."""

    ok = [x for x in rows if x["ipe_ok"]]
    return {
        "success": len(ok) / len(rows) if rows else float("nan"),
        "iterations": stats(x["iterations"] for x in ok),
        "E_R": stats(x["E_R"] for x in ok),
        "E_t": stats(x["E_t"] for x in ok),
    }


def ipe_rows(ipe: IPEResult, truth: Array) -> tuple[dict, list[dict]]:
    """Per-trial IPE figures and per-iteration errors (Fig. 9)."""
    e_r, e_t = pose_errors(ipe.dT_B, truth)
    v = T_to_vec6(ipe.dT_B) - T_to_vec6(truth) if ipe.dT_B is not None else np.full(6, np.nan)
    w = ipe.witness_disagreement
    row = {
        "ipe_ok": ipe.ok,
        "ipe_reason": ipe.reason,
        "iterations": ipe.n_iterations,
        "E_R": e_r,
        "E_t": e_t,
        "d_tx": v[0],
        "d_ty": v[1],
        "d_tz": v[2],
        "d_r_deg": np.rad2deg(v[3]),
        "d_p_deg": np.rad2deg(v[4]),
        "d_y_deg": np.rad2deg(v[5]),
        "compute_s": ipe.seconds_compute,
        "final_s": ipe.seconds_final,
        "register_s_mean": float(
            np.mean([it.seconds_register for it in ipe.iterations]) if ipe.iterations else np.nan
        ),
        # the witness view against the estimate (IPEConfig.witness; NaN when off)
        "witness_mm": 1e3 * w[0] if w else np.nan,
        "witness_deg": float(np.rad2deg(w[1])) if w else np.nan,
    }
    its = []
    for it in ipe.iterations:
        er, et = pose_errors(it.dT_B, truth)
        its.append(
            {
                "k": it.k,
                "E_R": er,
                "E_t": et,
                "register_s": it.seconds_register,
                "fitness": it.registration.fitness,
                "rmse": it.registration.rmse,
            }
        )
    return row, its

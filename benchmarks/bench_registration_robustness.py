"""Robustness of the global registration (FPFH + FGR + ICP) to parking errors, per config.

Run on purpose: ``python benchmarks/bench_registration_robustness.py [--per-site 15]
[--sigma 0.04] [--yaw-deg 3] [--seed 11] [--config NAME=JSON ...]``.

Pairs come from the digital twin at Sites 1 and 2 (``view_bench``): the taught capture at the
site's park pose and ``--per-site`` current captures after a planar parking error drawn with
standard deviations ``--sigma`` (m, x and y) and ``--yaw-deg``. Every config (``base`` is
:class:`RegistrationConfig`'s defaults; ``--config name={"field": value}`` adds one)
registers every pair without ``init`` (both clouds raw, as the IPE's first view without a
localization prior). A pair is ``correct`` when accepted within 5 mm of the truth, ``wrong``
when accepted farther (the failure that matters: a pose the arm would act on), else refused.
Prints one line per refused or wrong pair and a summary per config. Exits 0.

The defaults of :class:`RegistrationConfig` were chosen with it (seed 11: ``--sigma 0.04``
for 10 pairs and 0.06 for 5 per site, i.e. ``--per-site 15 --far 5``; seed 23: ``--sigma
0.03 --per-site 20 --far 0``).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
if os.environ["MUJOCO_GL"] == "osmesa":
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import argparse
import json

import numpy as np

from mmpa.core.geometry import inv, translation_error
from mmpa.registration import RegistrationConfig, register


def make_pairs(per_site: int, far: int, sigma: float, yaw_deg: float, seed: int) -> list:
    """(taught, current, T_true, offset) per pair; the last ``far`` pairs of each site have
    1.5x the standard deviation."""
    from mmpa.backends.twin.world import SimWorld

    rng = np.random.default_rng(seed)
    out = []
    for site in ("1", "2"):
        with SimWorld(site=site) as w:
            q = np.array(w.nominal.arm.view_bench)
            park = np.asarray(w.scene.site(site).pose2d)
            w.reset(site=site, q_arm=q)
            taught = w.camera.capture().to_point_cloud(min_depth=0.2, max_depth=3.0)
            T0 = w.truth.T_map_camera()
            for k in range(per_site):
                s = sigma * (1.5 if k >= per_site - far else 1.0)
                off = np.array([*rng.normal(0, s, 2), np.deg2rad(rng.normal(0, yaw_deg))])
                w.reset(pose2d=park + off, q_arm=q)
                cur = w.camera.capture().to_point_cloud(min_depth=0.2, max_depth=3.0)
                out.append((taught, cur, inv(w.truth.T_map_camera()) @ T0, off))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-site", type=int, default=15)
    ap.add_argument("--far", type=int, default=5)
    ap.add_argument("--sigma", type=float, default=0.04)
    ap.add_argument("--yaw-deg", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--config", action="append", default=[], help='NAME={"field": value}')
    a = ap.parse_args()
    configs = {"base": RegistrationConfig()}
    for c in a.config:
        name, js = c.split("=", 1)
        configs[name] = RegistrationConfig(**json.loads(js))
    pairs = make_pairs(a.per_site, a.far, a.sigma, a.yaw_deg, a.seed)
    for name, cfg in configs.items():
        correct, wrong, errors = 0, 0, []
        for i, (taught, cur, T_true, off) in enumerate(pairs):
            r = register(taught, cur, cfg)
            e = translation_error(T_true, r.T) * 1e3
            where = f"{name} pair {i} (offset {np.round(off, 3)})"
            if r.ok and e < 5.0:
                correct += 1
                errors.append(e)
            elif r.ok:
                wrong += 1
                print(f"{where}: WRONG pose accepted, E_t {e:.1f} mm")
            else:
                print(f"{where}: refused: {r.reason[:90]}")
        print(
            f"{name}: correct {correct}/{len(pairs)}, wrong {wrong}, "
            f"mean E_t {np.mean(errors) if errors else np.nan:.3f} mm"
        )


if __name__ == "__main__":
    main()

"""``mmpa perception``: render data, train and evaluate the object detector."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from mmpa.cli.common import ProfileOpt, console, fail
from mmpa.core.errors import MMPAError

perception_app = typer.Typer(help="Object detector (paper 001 §3.2.1): data, training, evaluation.")


def _log(msg: str) -> None:
    console.print(msg, highlight=False)
    console.file.flush()


def _weights(text: str) -> dict[str, float]:
    """``"dark=1,normal=1,high=2"`` -> ``{"dark": 1.0, "normal": 1.0, "high": 2.0}``."""
    out: dict[str, float] = {}
    for part in text.split(","):
        k, sep, v = part.partition("=")
        try:
            out[k.strip()] = float(v)
        except ValueError:
            sep = ""
        if not sep:
            raise typer.BadParameter(f"expected name=weight[,name=weight...], got {text!r}")
    return out


@perception_app.command("dataset")
def dataset_cmd(
    out: Annotated[Path, typer.Option(help="output .npz")],
    n: Annotated[int, typer.Option(help="number of images")] = 2400,
    seed: Annotated[int, typer.Option(help="seed of the rendered scenes", min=0)] = 0,
    work_view_prob: Annotated[
        float, typer.Option(help="fraction of working views (the robot's pre-grasp view)")
    ] = 0.0,
    exact_lighting: Annotated[
        bool, typer.Option(help="working views at the twin's exact dark/normal/high factors")
    ] = False,
    work_servo_prob: Annotated[
        float, typer.Option(help="fraction of the working views taken from the servo's approach")
    ] = 0.0,
    lighting: Annotated[
        str | None, typer.Option(help="weights per condition, e.g. dark=1,normal=1,high=2")
    ] = None,
    profile: ProfileOpt = None,
) -> None:
    """Render a labelled data set in the twin."""
    try:
        from mmpa.apps.perception import render
        from mmpa.harness.perception_data import DatasetConfig

        cfg = DatasetConfig(
            n_images=n,
            seed=seed,
            work_view_prob=work_view_prob,
            work_exact_lighting=exact_lighting,
            work_servo_prob=work_servo_prob,
            **({"lighting": _weights(lighting)} if lighting else {}),
            **({"profile": profile} if profile else {}),
        )
        ds = render(cfg, out, _log)
    except MMPAError as e:
        fail(e)
    _log(f"wrote {len(ds)} images to {out}")


@perception_app.command("train")
def train_cmd(
    out: Annotated[Path, typer.Option(help="weights file to write (.pt)")],
    data: Annotated[
        list[Path] | None, typer.Option(help="training .npz, repeatable (default: render)")
    ] = None,
    n: Annotated[int, typer.Option(help="images to render when no --data")] = 2400,
    seed: Annotated[int, typer.Option(help="data and training seed", min=0)] = 0,
    epochs: Annotated[int, typer.Option()] = 12,
    lr: Annotated[float, typer.Option(help="peak learning rate")] = 2e-3,
    threads: Annotated[int, typer.Option(help="CPU threads for torch")] = 2,
    max_minutes: Annotated[float | None, typer.Option(help="stop after this time")] = None,
    dark_preprocess_prob: Annotated[float, typer.Option()] = 0.0,
    crop_prob: Annotated[float, typer.Option(help="random crop-and-zoom probability")] = 0.0,
    init: Annotated[
        Path | None, typer.Option(help="fine-tune these weights (architecture from the file)")
    ] = None,
    val: Annotated[
        Path | None,
        typer.Option(help="validation .npz: choose the operating score threshold (max F1)"),
    ] = None,
) -> None:
    """Train the SSD on rendered images (reproducible: seeded data and training)."""
    try:
        from mmpa.apps.perception import train_detector

        settings = {
            "epochs": epochs,
            "lr": lr,
            "threads": threads,
            "max_minutes": max_minutes,
            "dark_preprocess_prob": dark_preprocess_prob,
            "crop_prob": crop_prob,
        }
        train_detector(out, data, n, seed, settings, init, val, _log)
    except MMPAError as e:
        fail(e)
    _log(f"wrote {out}")


@perception_app.command("prune")
def prune_cmd(
    out: Annotated[Path, typer.Option(help="pruned weights file to write (.pt)")],
    data: Annotated[
        list[Path], typer.Option(help="training .npz, repeatable (fine-tuning and validation)")
    ],
    weights: Annotated[Path | None, typer.Option(help="weights (default: shipped)")] = None,
    target: Annotated[float, typer.Option(help="keep this fraction of the MACs")] = 0.5,
    short_term_batches: Annotated[int, typer.Option()] = 4,
    long_term_epochs: Annotated[int, typer.Option()] = 1,
    threads: Annotated[int, typer.Option()] = 2,
) -> None:
    """NetAdapt-style channel pruning of a trained detector."""
    try:
        from mmpa.apps.perception import prune_detector

        settings = {
            "target_ratio": target,
            "short_term_batches": short_term_batches,
            "long_term_epochs": long_term_epochs,
            "threads": threads,
        }
        channels, ratio = prune_detector(out, data, weights, settings, _log)
    except MMPAError as e:
        fail(e)
    _log(f"wrote {out}: channels {channels}, {ratio:.2f} of the MACs")


@perception_app.command("evaluate")
def evaluate_cmd(
    weights: Annotated[Path | None, typer.Option(help="weights (default: shipped)")] = None,
    data: Annotated[Path | None, typer.Option(help="test .npz (default: render)")] = None,
    n: Annotated[int, typer.Option(help="images to render when no --data")] = 300,
    seed: Annotated[
        int, typer.Option(help="test-set seed (keep apart from training)", min=0)
    ] = 1000,
    preprocess_dark: Annotated[bool, typer.Option(help="paper's dark preprocessing")] = False,
    json_out: Annotated[Path | None, typer.Option("--json", help="write results")] = None,
    threshold: Annotated[
        float | None, typer.Option(help="score threshold (default: the model's)")
    ] = None,
) -> None:
    """Per-class AP@0.5 and detection success per lighting on a separately seeded set."""
    try:
        from dataclasses import asdict

        from rich.table import Table

        from mmpa.apps.perception import evaluate_detector

        res, n_images = evaluate_detector(weights, data, n, seed, preprocess_dark, threshold)
    except MMPAError as e:
        fail(e)
    t = Table(title=f"detector on {n_images} images (mAP@0.5 {res.mean_ap:.3f})")
    t.add_column("class")
    t.add_column("AP@0.5")
    conds = list(res.success)
    for c in conds:
        t.add_column(f"success {c}")
    for name, ap in res.ap.items():
        t.add_row(name, f"{ap:.3f}", *[f"{res.success[c][name]:.3f}" for c in conds])
    t.add_row("all", f"{res.mean_ap:.3f}", *[f"{res.success_all[c]:.3f}" for c in conds])
    console.print(t)
    if res.work_success:
        w = Table(title="working views: target detected (paper 001 Table 3's definition)")
        w.add_column("class")
        wc = list(res.work_success)
        for c in wc:
            w.add_column(c)
        for name in res.ap:
            w.add_row(
                name,
                *[f"{res.work_success[c][name]:.3f} ({res.work_counts[c][name]})" for c in wc],
            )
        w.add_row("all", *[f"{res.work_success_all[c]:.3f}" for c in wc])
        console.print(w)
        _log(f"targets hidden or out of view (counted as misses): {res.work_hidden}")
    _log(f"score threshold {res.threshold:.2f}")
    _log(f"precision at the operating point: {res.precision}; {res.ms_per_image:.1f} ms/image")
    if json_out:
        json_out.write_text(json.dumps(asdict(res), indent=2))

"""Trials that record themselves: inside :func:`record_trials` (``mmpa experiment NAME
--record DIR``) every twin trial writes its own ROS 2 bag ``DIR/<label>site-<site>-trial-<n>.mcap``
(:func:`trial_bag_name`) through a :class:`~mmpa.backends.bag.Recorder`
(:func:`trial_recorder`), in the process that runs it."""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mmpa.backends.bag import BagWriter, Recorder
from mmpa.core.errors import ConfigError

__all__ = [
    "record_spec",
    "record_trials",
    "recording_folder",
    "trial_bag_name",
    "trial_recorder",
]


@dataclass
class _RecordTarget:
    folder: Path
    used: bool = False


#: where the trials of :func:`run_trial_groups` record their bags (:func:`record_trials`)
_RECORD: ContextVar[_RecordTarget | None] = ContextVar("mmpa_record_trials", default=None)


@contextmanager
def record_trials(folder: str | Path) -> Iterator[_RecordTarget]:
    """Inside the ``with`` block, every trial run by :func:`run_trial_groups` records itself
    (:meth:`TwinSite.recording`: parking, its localization, IPE, the executed paths) to its
    own ROS 2 bag ``folder/<label>site-<site>-trial-<n>.mcap`` (:func:`trial_bag_name`),
    written by the process that runs the trial (``folder`` is made absolute: workers on
    other machines need it on a shared file system). The rows are those of a run without
    recording. Yields a target whose ``used`` tells whether any trials were handed the
    folder (``mmpa experiment --record`` refuses experiments that ran none)."""
    target = _RecordTarget(Path(folder).resolve())
    if target.folder.exists() and not target.folder.is_dir():
        raise ConfigError(f"--record needs a folder for the trials' bags; {folder} is a file")
    target.folder.mkdir(parents=True, exist_ok=True)
    token = _RECORD.set(target)
    try:
        yield target
    finally:
        _RECORD.reset(token)


def recording_folder() -> str | None:
    """The folder the trials about to be handed out record their bags to, inside
    :func:`record_trials` (and noted as used); None outside it."""
    target = _RECORD.get()
    if target is None:
        return None
    target.used = True
    return str(target.folder)


def record_spec() -> dict:
    """The trial spec's ``record`` entry (the bag folder) inside :func:`record_trials`."""
    folder = recording_folder()
    return {} if folder is None else {"record": folder}


def trial_bag_name(label: dict, site: str, trial: int) -> str:
    """File name of a trial's bag: ``<label>site-<site>-trial-<n>.mcap``, the label as
    ``key-value-`` pairs (``method-mmpa-site-1-trial-0.mcap``); characters other than
    letters, digits and ``._'+-`` become ``_``."""
    text = "".join(f"{k}-{v}-" for k, v in label.items()) + f"site-{site}-trial-{int(trial)}"
    return re.sub(r"[^A-Za-z0-9._'+-]", "_", text) + ".mcap"


@contextmanager
def trial_recorder(
    folder: str | Path,
    label: dict,
    site: str,
    trial: int,
    world: Any,
    joint_rate_hz: float | None = None,
) -> Iterator[Any]:
    """A :class:`mmpa.backends.bag.Recorder` of ``world`` writing the trial's ROS 2 bag
    ``folder/<label>site-<site>-trial-<n>.mcap`` (:func:`trial_bag_name`; overwritten), with
    ``joint_rate_hz`` (None: the arm only with the scans and frames); unhooked and the bag
    closed after the block (``mmpa experiment --record`` in every twin experiment)."""
    path = Path(folder) / trial_bag_name(label, site, trial)
    with (
        BagWriter(path, overwrite=True) as bag,
        Recorder(bag, world, joint_rate_hz=joint_rate_hz) as rec,
    ):
        yield rec

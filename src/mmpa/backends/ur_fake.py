"""A FAKE of the UR controller, for tests: it records every command and replays given readings.

:class:`FakeRTDE` stands in for ur-rtde's ``RTDEControlInterface`` and
``RTDEReceiveInterface`` (one object serves both) so that :class:`mmpa.backends.ur.URArm`,
the direct backend (:mod:`mmpa.backends.direct`) and the missions run without a controller
or URSim. It is NOT a model of a UR: its 'arm' jumps to every ``moveJ`` / ``servoJ`` target,
it has no dynamics and no limits of its own. What it is good for:

- **every command is recorded** in :attr:`FakeRTDE.calls` as ``(virtual time s, name, args)``:
  a test asserts what was sent (:meth:`motion_commands`: zero after a dry run) and that every
  servo set-point kept the limits (:meth:`servo_targets`);
- **given readings are replayed**: :meth:`replay_freedrive` plays a person's demonstration
  (joint angles over time) as ``getActualQ`` while teach mode is on, :meth:`digital_inputs`
  plays the controller's digital inputs over time (a start/stop button), and
  :meth:`stop_answering` freezes the receive interface (its ``getTimestamp`` stops moving:
  what the watchdog must notice); ``protective_stop_at`` / ``emergency_stop_at`` raise the
  safety states at a virtual time;
- **a virtual clock**: ``initPeriod`` / ``waitPeriod`` advance it by one control period
  (``period`` s) without sleeping, counted in whole periods (no drift: ``clock = n period``).

``on_move`` (optional) is called with every joint target the fake arm takes (``moveJ``,
``servoJ``): a test can mirror the fake arm into the twin (its camera then sees where the
'real' arm went).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

__all__ = ["FakeRTDE"]

#: command names that move the arm (or let a person move it)
MOTION_COMMANDS = frozenset(
    {"moveJ", "moveL", "servoJ", "speedJ", "teachMode", "freedriveMode", "movePath"}
)


class FakeRTDE:
    """A fake of ur-rtde's control + receive interfaces (module docstring): ``q0`` the
    arm's joints (rad), ``period`` the control period (s; 0.002 = 500 Hz)."""

    def __init__(
        self,
        q0,
        period: float = 0.002,
        on_move: Callable[[np.ndarray], None] | None = None,
    ) -> None:
        self.q = np.asarray(q0, float).copy()
        self.calls: list[tuple[float, str, tuple]] = []
        self.period = float(period)
        self.ticks = 0  # control periods elapsed (virtual clock = ticks * period)
        self.on_move = on_move
        self.protective_stop_at: float | None = None  # virtual time of a protective stop
        self.emergency_stop_at: float | None = None
        self.teach_mode = False
        self._hand: tuple[np.ndarray, np.ndarray] | None = None
        self._inputs: tuple[np.ndarray, np.ndarray] | None = None
        self._silent_at: float | None = None
        self._frozen: tuple[float, np.ndarray] | None = None
        self._lock = threading.Lock()

    @property
    def clock(self) -> float:
        """Virtual controller time (s)."""
        return self.ticks * self.period

    # ------------------------------------------------------------------ given readings
    def replay_freedrive(self, t, q) -> None:
        """A person's demonstration: while teach mode is on, ``getActualQ`` returns the
        latest of ``q`` (N, 6) rad stamped at or before the virtual clock (``t`` (N,) s,
        virtual time; before ``t[0]``: ``q[0]``)."""
        t, q = np.asarray(t, float), np.asarray(q, float)
        if t.ndim != 1 or q.shape != (len(t), 6) or np.any(np.diff(t) <= 0):
            raise ValueError(f"replay_freedrive needs increasing t (N,) and q (N, 6): {q.shape}")
        self._hand = (t, q)

    def digital_inputs(self, t, bits) -> None:
        """The controller's digital inputs over virtual time: ``bits[i]`` (an int, bit n =
        input n) from ``t[i]`` s on (0 before ``t[0]``)."""
        self._inputs = (np.asarray(t, float), np.asarray(bits, dtype=np.int64))

    def stop_answering(self, at: float) -> None:
        """From virtual time ``at`` on, the receive interface answers with its last data:
        ``getTimestamp`` and ``getActualQ`` stop changing (a lost connection)."""
        self._silent_at = float(at)

    def _latest(self, t: np.ndarray, now: float) -> int:
        return int(np.searchsorted(t, now + 1e-9, side="right")) - 1

    # ------------------------------------------------------------------ control
    def _log(self, name: str, *args) -> None:
        with self._lock:
            self.calls.append((self.clock, name, args))

    def _move(self, q) -> None:
        self.q = np.asarray(q, float).copy()
        if self.on_move is not None:
            self.on_move(self.q.copy())

    def moveJ(self, q, speed=1.05, accel=1.4, asynchronous=False) -> bool:
        self._log("moveJ", tuple(q), speed, accel)
        self._move(q)
        return True

    def servoJ(self, q, speed, accel, time, lookahead, gain) -> bool:
        self._log("servoJ", tuple(q), time, lookahead, gain)
        self._move(q)
        return True

    def servoStop(self, a=10.0) -> bool:
        self._log("servoStop", a)
        return True

    def stopJ(self, a=2.0, asynchronous=False) -> bool:
        self._log("stopJ", a)
        return True

    def initPeriod(self) -> float:
        return self.clock

    def waitPeriod(self, t_start) -> None:
        self.ticks += 1

    def teachMode(self) -> bool:
        self._log("teachMode")
        self.teach_mode = True
        return True

    def endTeachMode(self) -> bool:
        self._log("endTeachMode")
        self.teach_mode = False
        return True

    def disconnect(self) -> None:
        self._log("disconnect")

    # ------------------------------------------------------------------ receive
    def _silent(self) -> bool:
        return self._silent_at is not None and self.clock >= self._silent_at - 1e-12

    def getTimestamp(self) -> float:
        """Controller time of the latest data (s): stops moving when it stops answering."""
        if self._silent():
            assert self._silent_at is not None
            return self._silent_at
        return self.clock

    def getActualQ(self) -> list[float]:
        if self._silent():
            if self._frozen is None:
                self._frozen = (self.clock, self.q.copy())
            return self._frozen[1].tolist()
        if self.teach_mode and self._hand is not None:
            t, q = self._hand
            self.q = q[max(self._latest(t, self.clock), 0)].copy()
        return self.q.tolist()

    def getActualDigitalInputBits(self) -> int:
        if self._inputs is None:
            return 0
        t, bits = self._inputs
        i = self._latest(t, self.clock)
        return 0 if i < 0 else int(bits[i])

    def getDigitalInState(self, input_id: int) -> bool:
        return bool((self.getActualDigitalInputBits() >> int(input_id)) & 1)

    def isProtectiveStopped(self) -> bool:
        return self.protective_stop_at is not None and self.clock >= self.protective_stop_at

    def isEmergencyStopped(self) -> bool:
        return self.emergency_stop_at is not None and self.clock >= self.emergency_stop_at

    # ------------------------------------------------------------------ for the tests
    def motion_commands(self) -> list[tuple[float, str, tuple]]:
        """The recorded calls that move the arm (or hand it to a person)."""
        return [c for c in self.calls if c[1] in MOTION_COMMANDS]

    def servo_targets(self) -> tuple[np.ndarray, np.ndarray]:
        """Virtual times (K,) and joint targets (K, 6) of every servoJ call."""
        rows = [(t, a[0]) for t, n, a in self.calls if n == "servoJ"]
        return np.array([r[0] for r in rows]), np.array([r[1] for r in rows])

"""A FAKE of ur-rtde's RTDE interfaces (no URSim here): it records every call with a virtual
clock, and its 'arm' follows servoJ/moveJ targets exactly. Labelled a fake: it checks mmpa's
command stream and limits, not a controller's dynamics."""

from __future__ import annotations

import threading

import numpy as np


class FakeRTDE:
    """``control`` and ``receive`` in one object (the two interfaces share the fake arm)."""

    def __init__(self, q0, period: float = 0.002) -> None:
        self.q = np.asarray(q0, float).copy()
        self.calls: list[tuple[float, str, tuple]] = []
        self.clock = 0.0
        self.period = period
        self.protective_stop_at: float | None = None  # virtual time of a protective stop
        self._lock = threading.Lock()

    # --- control
    def _log(self, name: str, *args) -> None:
        with self._lock:
            self.calls.append((self.clock, name, args))

    def moveJ(self, q, speed, accel, asynchronous=False) -> bool:
        self._log("moveJ", tuple(q), speed, accel)
        self.q = np.asarray(q, float).copy()
        return True

    def servoJ(self, q, speed, accel, time, lookahead, gain) -> bool:
        self._log("servoJ", tuple(q), time, lookahead, gain)
        self.q = np.asarray(q, float).copy()
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
        self.clock = t_start + self.period

    def freedriveMode(self) -> bool:
        self._log("freedriveMode")
        return True

    def endFreedriveMode(self) -> bool:
        self._log("endFreedriveMode")
        return True

    def disconnect(self) -> None:
        self._log("disconnect")

    # --- receive
    #: a person moving the arm in freedrive: q as a function of the virtual clock (or None)
    hand = None

    def getActualQ(self):
        if self.hand is not None and any(n == "freedriveMode" for _, n, _ in self.calls):
            self.q = np.asarray(self.hand(self.clock), float)
        return self.q.tolist()

    def isProtectiveStopped(self) -> bool:
        return self.protective_stop_at is not None and self.clock >= self.protective_stop_at

    def isEmergencyStopped(self) -> bool:
        return False

    def servo_targets(self) -> tuple[np.ndarray, np.ndarray]:
        """Virtual times (K,) and joint targets (K, 6) of every servoJ call."""
        rows = [(t, a[0]) for t, n, a in self.calls if n == "servoJ"]
        return np.array([r[0] for r in rows]), np.array([r[1] for r in rows])

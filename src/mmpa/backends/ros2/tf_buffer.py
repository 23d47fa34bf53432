"""A small tf buffer: ``/tf`` and ``/tf_static`` composed by frame names (no ``tf2_ros``).

Each transform is ``child``'s pose in ``parent`` (4x4, m / rad), as a ``TransformStamped``
carries it. Static transforms (``/tf_static``) hold at every time; dynamic ones (``/tf``) keep
the last :attr:`TfBuffer.history` stamps per child and are looked up at a time ``t``:
interpolated as tf2 does (translation linearly, rotation by slerp) between the two
stamps around ``t``, or the nearest stamp when ``t`` lies outside them by at most
``tolerance`` s (``None``: the latest, whatever its stamp). Pure numpy: the node feeds it what
:func:`mmpa.backends.ros2.messages.from_tf_message` reads.

``lookup(target, source, t)`` is ``source``'s pose in ``target`` (tf2's ``lookupTransform``
convention: it maps points of ``source`` into ``target``), composed along the tree through the
frames' common ancestor; None (and :meth:`TfBuffer.why` the reason) when a link is missing.
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np

from mmpa.core.geometry import Array, exp_so3, inv, log_so3

__all__ = ["TfBuffer"]


def _interpolate(T0: Array, T1: Array, s: float) -> Array:
    """tf2's interpolation: the translation linearly, the rotation on the geodesic (slerp):
    ``R0 exp(s log(R0^T R1))`` (:func:`~mmpa.core.geometry.log_so3`, a few 3x3 products: the
    localization node looks up the odometry at every scan, and scipy's logarithm cost 0.5 ms
    of its latency), the stamps themselves at ``s`` = 0 and 1."""
    if s <= 0.0 or s >= 1.0:
        return T0 if s <= 0.0 else T1
    out = np.eye(4)
    out[:3, 3] = (1 - s) * T0[:3, 3] + s * T1[:3, 3]
    out[:3, :3] = T0[:3, :3] @ exp_so3(s * log_so3(T0[:3, :3].T @ T1[:3, :3]))
    return out


class TfBuffer:
    """Transforms by child frame (each child has one parent, as in tf)."""

    def __init__(self, history: int = 100) -> None:
        self.history = history
        self._static: dict[str, tuple[str, Array]] = {}
        self._dynamic: dict[str, tuple[str, deque[tuple[float, Array]]]] = {}
        self._why = ""

    def set(self, stamp: float, parent: str, child: str, Tm: Array, static: bool = False) -> None:
        """Store ``child``'s pose ``Tm`` (4x4) in ``parent`` at ``stamp`` s."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        Tm = np.asarray(Tm, float)
        if static:
            self._static[child] = (parent, Tm)
            return
        old = self._dynamic.get(child)
        if old is None or old[0] != parent:
            old = (parent, deque(maxlen=self.history))
            self._dynamic[child] = old
        hist = old[1]
        if hist and stamp < hist[-1][0]:  # out of order: keep the history sorted
            items = sorted([*hist, (stamp, Tm)], key=lambda x: x[0])
            hist.clear()
            hist.extend(items[-self.history :])
        else:
            hist.append((stamp, Tm))

    def latest_stamp(self, child: str) -> float | None:
        """The last stamp (s) of ``child``'s dynamic transform; None when it has none (static
        or unknown)."""
        entry = self._dynamic.get(child.lstrip("/"))
        return entry[1][-1][0] if entry and entry[1] else None

    def why(self) -> str:
        """Why the last lookup returned None ('' after a successful one)."""
        return self._why

    def _link(self, child: str, t: float | None, tolerance: float) -> tuple[str, Array] | None:
        if child in self._static:
            return self._static[child]
        if child not in self._dynamic:
            return None
        parent, hist = self._dynamic[child]
        if t is None:
            return parent, hist[-1][1]
        stamps = [s for s, _ in hist]
        i = bisect.bisect_left(stamps, t)  # numpy's searchsorted, without the array
        if 0 < i < len(hist):
            (t0, T0), (t1, T1) = hist[i - 1], hist[i]
            s = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
            return parent, _interpolate(T0, T1, s)
        near = hist[0] if i == 0 else hist[-1]
        if abs(near[0] - t) <= tolerance:
            return parent, near[1]
        self._why = (
            f"{parent} -> {child} at {t:.3f} s: have {stamps[0]:.3f}..{stamps[-1]:.3f} s "
            f"(tolerance {tolerance} s)"
        )
        return None

    def _chain(self, frame: str, t: float | None, tol: float) -> tuple[dict[str, Array], str]:
        """Every ancestor of ``frame`` reachable at ``t`` (itself included) -> ``frame``'s
        pose in it, and why the walk stopped short of the root ('' at the root)."""
        out = {frame: np.eye(4)}
        T = np.eye(4)
        while True:
            self._why = ""
            link = self._link(frame, t, tol)
            if link is None:
                return out, self._why
            frame, T = link[0], link[1] @ T
            if frame in out:  # a loop: not a tree
                return out, f"the transforms loop through {frame}"
            out[frame] = T

    def lookup(
        self, target: str, source: str, t: float | None = None, tolerance: float = 0.0
    ) -> Array | None:
        """``source``'s pose in ``target`` (4x4) at ``t`` s (None: the latest); None when the
        frames are not connected or a dynamic link has no stamp near ``t`` (see
        :meth:`why`)."""
        target, source = target.lstrip("/"), source.lstrip("/")
        a, why_a = self._chain(source, t, tolerance)
        b, why_b = self._chain(target, t, tolerance)
        common = next((f for f in a if f in b), None)
        if common is None:
            why = "; ".join(w for w in (why_a, why_b) if w)
            self._why = f"no transform connects {target} and {source}" + (
                f" ({why})" if why else ""
            )
            return None
        self._why = ""
        return inv(b[common]) @ a[common]

"""The background thread of an arm backend's streaming ``command`` (the UR over RTDE, the
ROS 2 arm): its state and how it ends. The backend's own ``_run_stream`` follows
``_target`` (under ``_lock``) until ``_stop`` is set."""

from __future__ import annotations

import threading

from mmpa.core.geometry import Array

__all__ = ["CommandStream"]


class CommandStream:
    """Mixin: ``_init_stream`` in the backend's ``__init__``, ``stop_stream`` to end it."""

    _lock: threading.Lock
    _target: Array | None
    _stream: threading.Thread | None
    _stop: threading.Event

    def _init_stream(self) -> None:
        self._lock = threading.Lock()
        self._target = None
        self._stream = None
        self._stop = threading.Event()

    def stop_stream(self) -> None:
        """End a ``command`` stream: the thread is stopped and joined, the target dropped
        (what the arm does then is the backend's: the UR decelerates to rest, a ROS 2
        controller holds the last set-point)."""
        if self._stream is not None:
            self._stop.set()
            self._stream.join()
            self._stream = None
            with self._lock:
                self._target = None

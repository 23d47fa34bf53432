"""The recording FAKE of ur-rtde's RTDE interfaces lives in :mod:`mmpa.backends.ur_fake`
(labelled there: it records every command and replays given readings; no URSim here)."""

from mmpa.backends.ur_fake import FakeRTDE

__all__ = ["FakeRTDE"]

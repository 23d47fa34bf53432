"""The RealSense backend for real: frames written through the SDK's own software device and
recorder play back through the backend as a camera's would (no camera needed), and IPE runs
on the twin with the camera replaced by that playback."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import pytest

pytest.importorskip("pyrealsense2", reason="the optional extra 'realsense'")

from mmpa.backends.realsense import RealSenseCamera, RealSenseConfig, record_frames
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import Camera, RGBDFrame, RobotDevices


def _frames(n: int = 4) -> list[RGBDFrame]:
    rng = np.random.default_rng(0)
    k = CameraIntrinsics(width=64, height=48, fx=60.0, fy=61.0, cx=31.2, cy=23.7)
    out = []
    for i in range(n):
        depth = rng.uniform(0.3, 2.0, (48, 64)).astype(np.float32)
        depth[5:9, 10:20] = 0.0  # holes stay holes
        color = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
        out.append(RGBDFrame(color, depth, k, stamp=10.0 + i / 30))
    return out


def test_recording_plays_back_through_the_backend(tmp_path) -> None:
    frames = _frames()
    path = record_frames(frames, tmp_path / "cam.db3")
    with RealSenseCamera(RealSenseConfig(playback=path, timeout_ms=500)) as cam:
        assert isinstance(cam, Camera)
        k, k0 = cam.intrinsics.model_dump(), frames[0].intrinsics.model_dump()
        assert k == pytest.approx(k0, rel=1e-6)  # the SDK stores float32
        assert cam.depth_scale == pytest.approx(0.001, rel=1e-6)
        for f in frames:
            got = cam.capture()
            np.testing.assert_array_equal(got.color, f.color)
            np.testing.assert_allclose(got.depth, f.depth, atol=0.0005 + 1e-6)  # 1 mm units
            assert np.all((got.depth == 0) == (f.depth == 0))
            assert got.stamp == pytest.approx((f.stamp - frames[0].stamp), abs=1e-3)  # 1/30 s
        with pytest.raises(MMPAError, match="no RealSense frame"):
            cam.capture()  # the recording ended: an error, not a hang or a stale frame


def test_bad_recordings_and_frames_are_refused(tmp_path) -> None:
    with pytest.raises(InvalidInputError, match=r"\.db3"):
        record_frames(_frames(1), tmp_path / "cam.bag")
    with pytest.raises(InvalidInputError, match="at least one"):
        record_frames([], tmp_path / "cam.db3")
    with pytest.raises(InvalidInputError, match="no RealSense recording"):
        RealSenseCamera(RealSenseConfig(playback=tmp_path / "none.db3"))


class _RecordingCamera:
    """The twin's camera, keeping every frame it hands out (to write a recording)."""

    def __init__(self, camera) -> None:
        self._camera, self.frames = camera, []

    @property
    def intrinsics(self):
        return self._camera.intrinsics

    def capture(self):
        f = self._camera.capture()
        self.frames.append(f)
        return f


def test_ipe_runs_on_the_realsense_playback(tmp_path) -> None:
    """IPE on the twin, its camera recorded through the SDK; the same park again with the
    camera replaced by the RealSense playback (1 mm depth units, as a D400 streams): the
    estimate agrees with the live one and with the truth."""
    from mmpa.backends.twin.error_model import ErrorModelConfig
    from mmpa.harness.twin_site import MMPAExperimentConfig, TwinSite
    from mmpa.missions.teach_repeat import automate

    cfg = MMPAExperimentConfig(errors=ErrorModelConfig(profile="reference"))
    with TwinSite(cfg, "1") as ts:
        w = ts.world
        ts.park()
        pose = w.truth.base_pose2d()
        auto = ts.automation_config().model_copy(update={"execute": False})
        rec = _RecordingCamera(w.camera)
        live = automate(
            ts.taught.task,
            RobotDevices(w.nominal, arm=w.arm, camera=rec, gripper=w.gripper, clock=w),
            cfg=auto,
        )
        assert live.ok, live.reason
        path = record_frames(rec.frames, tmp_path / "ipe.db3")
        w.reset(site="1", pose2d=pose)
        with RealSenseCamera(RealSenseConfig(playback=path, timeout_ms=1000)) as cam:
            replay = automate(
                ts.taught.task,
                RobotDevices(w.nominal, arm=w.arm, camera=cam, gripper=w.gripper, clock=w),
                cfg=auto,
            )
        assert replay.ok, replay.reason
        truth = ts.parking_truth()
        for res in (live, replay):
            assert np.linalg.norm(res.ipe.dT_B[:3, 3] - truth[:3, 3]) < 2e-3
        d = np.linalg.norm(replay.ipe.dT_B[:3, 3] - live.ipe.dT_B[:3, 3])
        assert d < 5e-4, d  # quantized depth moves the estimate by a fraction of a mm

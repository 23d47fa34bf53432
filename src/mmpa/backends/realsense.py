"""Intel RealSense camera backend (``pyrealsense2``, the optional extra ``realsense``).

:class:`RealSenseCamera` implements :class:`mmpa.robot.interfaces.Camera` over a live
device (by serial number, or the first one) or a RealSense recording played back
(librealsense >= 2.57 writes rosbag2 ``.db3`` recordings; older ``.bag`` files play too).
Depth is aligned to colour by librealsense (``rs.align``; a recording of aligned frames is
used as is), converted to metres with the device's depth scale; intrinsics come from the
colour stream profile.

:func:`record_frames` writes mmpa ``RGBDFrame`` s as a RealSense recording through the SDK's
own software device and recorder: frames from the twin (or from disk) become a file that the
SDK, ``realsense-viewer`` and this backend play back like a camera's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import RGBDFrame

__all__ = ["RealSenseCamera", "RealSenseConfig", "record_frames"]

_log = logging.getLogger(__name__)


def _rs() -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError as e:  # pragma: no cover - depends on the install
        raise MMPAError(
            "the RealSense backend needs pyrealsense2: pip install 'mmpa[realsense]'"
        ) from e
    return rs


class RealSenseConfig(BaseModel):
    """Streams of :class:`RealSenseCamera`. ``playback``: a recording to play instead of a
    device; ``serial``: which device (default: the first). ``real_time`` False plays a
    recording frame by frame (nothing dropped)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    width: int = Field(640, gt=0)
    height: int = Field(480, gt=0)
    fps: int = Field(30, gt=0)
    serial: str | None = None
    playback: Path | None = None
    real_time: bool = False
    timeout_ms: int = Field(5000, gt=0)
    queue_size: int = Field(256, gt=0)  # frames buffered per stream when playing a recording


class RealSenseCamera:
    """A RealSense RGB-D camera (or a recording of one) as an mmpa ``Camera``."""

    def __init__(self, cfg: RealSenseConfig | None = None) -> None:
        self.cfg = cfg = cfg or RealSenseConfig()
        rs = _rs()
        self._rs = rs
        self._pipe: Any = None
        self._queues: dict[str, Any] | None = None
        self._sensors: list[Any] = []
        self._align: Any = None
        if cfg.playback is not None:
            device, cprof, dprof = self._open_playback(Path(cfg.playback))
        else:
            device, cprof, dprof = self._start_pipeline(None)
        self.depth_scale = float(device.first_depth_sensor().get_depth_scale())
        i = cprof.get_intrinsics()
        if any(abs(c) > 1e-9 for c in i.coeffs):
            _log.warning("colour stream has distortion %s; mmpa assumes a pinhole", i.coeffs)
        self._intrinsics = CameraIntrinsics(
            width=i.width, height=i.height, fx=i.fx, fy=i.fy, cx=i.ppx, cy=i.ppy
        )
        if self._queues is None and not _aligned(dprof, cprof):
            self._align = rs.align(rs.stream.color)
        self._closed = False
        _log.info(
            "RealSense %s: %dx%d, depth scale %.6f m",
            cfg.playback or device.get_info(rs.camera_info.serial_number),
            i.width,
            i.height,
            self.depth_scale,
        )

    def _start_pipeline(self, playback: Path | None) -> tuple[Any, Any, Any]:
        """Stream through ``rs.pipeline`` (a device, or a recording of a real camera: its
        syncer pairs depth with colour and ``rs.align`` aligns them)."""
        rs, cfg = self._rs, self.cfg
        config = rs.config()
        if playback is not None:
            config.enable_device_from_file(str(playback), repeat_playback=False)
        else:
            if cfg.serial is not None:
                config.enable_device(cfg.serial)
            config.enable_stream(rs.stream.depth, cfg.width, cfg.height, rs.format.z16, cfg.fps)
            config.enable_stream(rs.stream.color, cfg.width, cfg.height, rs.format.rgb8, cfg.fps)
        self._pipe = rs.pipeline()
        try:
            profile = self._pipe.start(config)
        except RuntimeError as e:
            what = playback or (cfg.serial or "the first RealSense device")
            raise MMPAError(f"cannot start RealSense streaming from {what}: {e}") from e
        device = profile.get_device()
        if playback is not None:
            device.as_playback().set_real_time(cfg.real_time)
        cprof = profile.get_stream(rs.stream.color).as_video_stream_profile()
        dprof = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        return device, cprof, dprof

    def _open_playback(self, path: Path) -> tuple[Any, Any, Any]:
        """A recording: depth already aligned to colour (recordings of aligned frames, e.g.
        :func:`record_frames`) is read frame by frame from each sensor's queue, depth and
        colour paired by frame number (the pipeline's syncer may drop the first frames of a
        playback); anything else goes through the pipeline and ``rs.align``."""
        rs = self._rs
        if not path.is_file():
            raise InvalidInputError(f"no RealSense recording at {path}")
        try:
            device = rs.context().load_device(str(path))
        except RuntimeError as e:
            raise MMPAError(f"cannot open the RealSense recording {path}: {e}") from e
        streams: dict[str, tuple[Any, Any]] = {}
        for sensor in device.query_sensors():
            for prof in sensor.get_stream_profiles():
                streams[str(prof.stream_type())] = (sensor, prof)
        if "stream.depth" not in streams or "stream.color" not in streams:
            raise MMPAError(f"{path} lacks a depth or a colour stream: {sorted(streams)}")
        cprof = streams["stream.color"][1].as_video_stream_profile()
        dprof = streams["stream.depth"][1].as_video_stream_profile()
        if not _aligned(dprof, cprof):
            return self._start_pipeline(path)
        playback = device.as_playback()
        playback.set_real_time(self.cfg.real_time)
        self._queues = {}
        for kind in ("stream.depth", "stream.color"):
            sensor, prof = streams[kind]
            queue = rs.frame_queue(self.cfg.queue_size, True)
            sensor.open(prof)
            sensor.start(queue)
            self._sensors.append(sensor)
            self._queues[kind] = queue
            if kind == "stream.depth":
                # the playback starts with the first sensor: hold it until both listen, or
                # the first colour frame may be read before its queue exists (and lost)
                playback.pause()
        playback.resume()
        return device, cprof, dprof

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intrinsics

    def capture(self) -> RGBDFrame:
        """The next colour + aligned depth pair: ``color`` (H, W, 3) uint8 RGB, ``depth``
        (H, W) float32 m (0 invalid), ``stamp`` s (the colour frame's timestamp)."""
        if self._closed:
            raise MMPAError("the RealSense camera is closed")
        try:
            if self._queues is not None:
                c, d = self._next_pair()
            else:
                frames = self._pipe.wait_for_frames(self.cfg.timeout_ms)
                if self._align is not None:
                    frames = self._align.process(frames)
                c, d = frames.get_color_frame(), frames.get_depth_frame()
        except RuntimeError as e:
            where = f"the recording {self.cfg.playback} ended or" if self.cfg.playback else ""
            raise MMPAError(f"no RealSense frame: {where} {e}".replace("  ", " ")) from e
        if not c or not d:
            raise MMPAError("the RealSense frameset lacks a colour or a depth frame")
        color = np.asanyarray(c.get_data()).copy()
        if color.ndim != 3 or color.shape[2] != 3:
            raise MMPAError(f"colour stream format {c.profile.format()} is not rgb8/bgr8")
        if c.profile.format() == self._rs.format.bgr8:
            color = color[..., ::-1].copy()
        depth = np.asanyarray(d.get_data()).astype(np.float32) * self.depth_scale
        return RGBDFrame(color, depth, self._intrinsics, c.get_timestamp() / 1000.0)

    def _next_pair(self) -> tuple[Any, Any]:
        """The next depth and colour frames with the same frame number (queue mode)."""
        assert self._queues is not None
        t = self.cfg.timeout_ms
        d = self._queues["stream.depth"].wait_for_frame(t)
        c = self._queues["stream.color"].wait_for_frame(t)
        while d.get_frame_number() != c.get_frame_number():  # one of them was dropped
            if d.get_frame_number() < c.get_frame_number():
                d = self._queues["stream.depth"].wait_for_frame(t)
            else:
                c = self._queues["stream.color"].wait_for_frame(t)
        return c, d

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if self._pipe is not None:
                self._pipe.stop()
            for sensor in self._sensors:
                sensor.stop()
                sensor.close()

    def __enter__(self) -> RealSenseCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _aligned(dprof: Any, cprof: Any) -> bool:
    """Depth already aligned to colour: the same intrinsics and identity extrinsics (then
    ``rs.align`` would only re-project it and move ~5 % of the pixels by one)."""
    di, ci = dprof.get_intrinsics(), cprof.get_intrinsics()
    ext = dprof.get_extrinsics_to(cprof)
    return bool(
        (di.width, di.height, di.fx, di.fy, di.ppx, di.ppy)
        == (ci.width, ci.height, ci.fx, ci.fy, ci.ppx, ci.ppy)
        and np.allclose(ext.rotation, np.eye(3).ravel())
        and np.allclose(ext.translation, 0.0)
    )


def _rs_intrinsics(rs: Any, k: CameraIntrinsics) -> Any:
    i = rs.intrinsics()
    i.width, i.height = k.width, k.height
    i.fx, i.fy, i.ppx, i.ppy = k.fx, k.fy, k.cx, k.cy
    i.model = rs.distortion.none
    i.coeffs = [0.0] * 5
    return i


def record_frames(
    frames: Iterable[RGBDFrame], path: str | Path, depth_scale: float = 0.001, fps: int = 30
) -> Path:
    """Write ``frames`` (one camera: same intrinsics) as a RealSense recording at ``path``
    (``.db3``) through the SDK's software device and recorder. Depth is stored as z16 in
    units of ``depth_scale`` m (rounded; beyond 65535 units: invalid, 0). Frames are stamped
    ``n / fps`` s: the playback's syncer keeps one frame per stamp and pairs depth with colour
    by stamp, so captures of one still view (one stamp) or a gap between views would be
    merged or mispaired; the frames' own stamps are not kept."""
    rs = _rs()
    frames = list(frames)
    if not frames:
        raise InvalidInputError("record_frames needs at least one RGB-D frame")
    p = Path(path)
    if p.suffix != ".db3":
        raise InvalidInputError(f"RealSense recordings are rosbag2 .db3 files, got {p.name}")
    p.parent.mkdir(parents=True, exist_ok=True)
    if p.exists():
        p.unlink()
    k = frames[0].intrinsics
    if any(f.intrinsics != k for f in frames):
        raise InvalidInputError("record_frames: all frames must share one camera's intrinsics")
    dev = rs.software_device()
    sensors, profiles = [], []
    for uid, (name, stream, fmt, bpp) in enumerate(
        (
            ("Depth", rs.stream.depth, rs.format.z16, 2),
            ("Color", rs.stream.color, rs.format.rgb8, 3),
        )
    ):
        sensor = dev.add_sensor(name)
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = stream, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = k.width, k.height, fps, bpp, fmt
        vs.intrinsics = _rs_intrinsics(rs, k)
        profiles.append(sensor.add_video_stream(vs))
        sensors.append(sensor)
    sensors[0].add_read_only_option(rs.option.depth_units, float(depth_scale))
    ext = rs.extrinsics()
    ext.rotation, ext.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    profiles[0].register_extrinsics_to(profiles[1], ext)  # depth is aligned to colour
    dev.create_matcher(rs.matchers.dlr_c)
    recorder = rs.recorder(str(p), dev)
    for sensor, prof in zip(sensors, profiles, strict=True):
        sensor.open(prof)
        sensor.start(lambda f: None)
    keep = []  # the SDK reads the pixel buffers asynchronously: keep them alive to the end
    # one frame per 1 / fps: the playback's syncer pairs depth and colour by stamp and keeps
    # one frame per stamp (captures of one still view share a stamp; gaps desynchronise it)
    stamps_ms = [1000.0 * n / fps for n in range(len(frames))]
    try:
        for n, fr in enumerate(frames):
            units = np.where(
                np.isfinite(fr.depth) & (fr.depth > 0), np.round(fr.depth / depth_scale), 0
            )
            z16 = np.where(units <= 65535, units, 0).astype(np.uint16)
            rgb = np.ascontiguousarray(fr.color, dtype=np.uint8)
            keep += [z16, rgb]
            for sensor, prof, img, bpp in (
                (sensors[0], profiles[0], z16, 2),
                (sensors[1], profiles[1], rgb, 3),
            ):
                vf = rs.software_video_frame()
                vf.pixels, vf.stride, vf.bpp = img, k.width * bpp, bpp
                vf.timestamp = stamps_ms[n]
                vf.domain = rs.timestamp_domain.hardware_clock
                vf.frame_number = n
                vf.profile = prof.as_video_stream_profile()
                sensor.on_video_frame(vf)
            time.sleep(0.01)  # the recorder writes on its own thread; it drops frames pushed faster
    finally:
        for sensor in sensors:
            sensor.stop()
            sensor.close()
        del recorder  # the recorder writes the file when released
    return p

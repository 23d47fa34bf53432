"""The localization node's ``/amcl_pose`` as raw bytes: rclpy reads them back to the message
the typed path builds (rosbags' serializer -> rclpy), and the pose and covariance read from
them are the ones given."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip(
    "rclpy", reason="the ros2 extra is not installed (make setup installs it on x86-64 Linux)"
)

from rclpy.serialization import deserialize_message

from mmpa.backends.ros2 import localization_msgs as lm


@pytest.mark.parametrize("frame_id", ["map", "m", "abcdefgh", "a_longer_frame"])
def test_pose_with_covariance_bytes_read_back_to_the_message(frame_id: str) -> None:
    pose = np.array([1.25, -3.5, 2.9])
    cov = np.array([[0.01, 0.002, 0.0], [0.002, 0.02, 0.001], [0.0, 0.001, 0.003]])
    ref = lm.pose_with_covariance(123.456789, frame_id, pose, cov)
    back = deserialize_message(
        lm.pose_with_covariance_cdr(123.456789, frame_id, pose, cov), type(ref)
    )
    assert back == ref
    t, got, got_cov = lm.from_pose_with_covariance(back)
    assert t == pytest.approx(123.456789, abs=1e-9)
    np.testing.assert_allclose(got, pose, atol=1e-12)
    np.testing.assert_array_equal(got_cov, cov)

"""IPE's estimate on recorded frames: two real RGB-D captures of a desk (tests/data/desk) stand
for the teaching capture and the capture after parking, taken at the same arm joints. mmpa
registers the taught cloud onto the new frame (global + colored ICP, then the projective
refinement on the depth image), turns the camera motion into the parking offset of the arm
base (paper 000 eq. 9-10) and moves a taught tool path by it (eq. 11).

The frames' own poses (TSDF tracking, cm-level) check the camera motion. Run:
``python examples/ipe_on_recorded_frames.py [DATA_DIR]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mmpa.apps.register import load_png_frame, register_frames
from mmpa.core.geometry import inv
from mmpa.ipe.core import delta_T_B, transform_path
from mmpa.robot.description import default_robot
from mmpa.robot.kinematics import fk

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "desk"


def frame(data: Path, n: int):
    stem = data / f"frame-{n:06d}"
    f = load_png_frame(f"{stem}.color.png", f"{stem}.depth.png", data / "intrinsics.K.txt")
    return f, np.loadtxt(f"{stem}.pose.txt")  # camera-to-world, for the check only


def main(data: Path = DATA) -> dict:
    taught, P_taught = frame(data, 15)  # the teaching capture X_i(O)
    now, P_now = frame(data, 17)  # the capture after parking, same arm joints
    reg = register_frames(taught, now)  # T_Ck_Co: taught camera -> camera now
    if not reg.ok:
        raise SystemExit(f"registration refused: {reg.reason}")  # the arm would not move
    dT_C = reg.T
    check = inv(P_now) @ P_taught  # the same motion from the recorded poses
    err_mm = 1e3 * np.linalg.norm(dT_C[:3, 3] - check[:3, 3])

    robot = default_robot()  # the twin's arm and hand-eye stand in for yours (--robot FILE)
    q = np.array(robot.arm.view_bench)  # the sampling joints, the same at both captures
    T_B_C = fk(robot.arm.dh, q) @ robot.camera.T_flange_camera
    dT_B = delta_T_B(T_B_C, dT_C, T_B_C)  # eq. 9-10: taught arm base -> arm base now
    tool = fk(robot.arm.dh, q, robot.gripper.T_flange_tcp)  # a taught tool pose
    moved = transform_path(dT_B, tool[None])[0]  # eq. 11

    print(
        f"camera motion: {1e3 * np.linalg.norm(dT_C[:3, 3]):.1f} mm, "
        f"agrees with the recorded poses within {err_mm:.1f} mm (they are cm-level)"
    )
    print(f"parking offset of the arm base: {1e3 * np.linalg.norm(dT_B[:3, 3]):.1f} mm")
    print(
        f"the taught tool point moves by {1e3 * np.linalg.norm(moved[:3, 3] - tool[:3, 3]):.1f} mm"
    )
    proj = reg.projective
    print(
        f"verdict: ICP ok (fitness {reg.icp.fitness:.2f}), projective "
        f"{'ok' if proj is not None and proj.ok else 'not used'}"
    )
    return {"dT_C": dT_C, "dT_B": dT_B, "err_mm": err_mm}


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DATA)

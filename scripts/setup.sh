#!/usr/bin/env bash
# Sets up a fresh machine for mmpa: system libraries, a virtual environment and the package.
# Idempotent: a stamp records what was installed; rerunning is quick.
#   MMPA_OPEN3D=cuda   use the CUDA build of Open3D instead of the CPU wheel
#   MUJOCO_GL=egl      render with EGL on a GPU machine (default here: osmesa)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
FLAVOR=${MMPA_OPEN3D:-cpu}
PYTHON=${PYTHON:-python3}

# 1. System libraries: Open3D needs libusb; offscreen MuJoCo without a GPU needs OSMesa.
need=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib libusb-1.0.so.0 || need+=(libusb-1.0-0)
have_lib libOSMesa.so || need+=(libosmesa6)
have_lib libGL.so.1 || need+=(libgl1)
have_lib libEGL.so.1 || need+=(libegl1)
# ROS 2 (the extra ros2, x86-64 Linux; MMPA_ROS2=0 leaves it out): cmake and a C/C++ compiler
# build the interface packages that are not published as wheels (scripts/ros2-interfaces.sh)
ROS2=${MMPA_ROS2:-1}
[ "$(uname -sm)" = "Linux x86_64" ] || ROS2=0
if [ "$ROS2" = 1 ]; then
  command -v cmake >/dev/null || need+=(cmake)
  command -v g++ >/dev/null || need+=(g++)
fi
if ((${#need[@]})); then
  echo "[setup] installing system libraries: ${need[*]}"
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || { echo "[setup] need root or sudo to install ${need[*]}" >&2; exit 1; }
    SUDO=sudo
  fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

# 2. Python environment.
"$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' || {
  echo "[setup] mmpa needs Python >= 3.11; set PYTHON=python3.11" >&2; exit 1; }
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
EXTRAS=dev,$FLAVOR,perception
[ "$ROS2" = 0 ] || EXTRAS+=,ros2
stamp=$(cat pyproject.toml constraints.txt scripts/setup.sh | sha256sum | cut -c1-16)-$EXTRAS
if [ "$(cat .setup-stamp 2>/dev/null)" != "$stamp" ]; then
  echo "[setup] installing mmpa[$EXTRAS] into $VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  # constraints.txt pins the exact versions tested together (regenerate with
  # `.venv/bin/pip freeze --exclude-editable | grep -v ^mmpa > constraints.txt`)
  cons=(-c constraints.txt)
  [ "$FLAVOR" = cpu ] || cons=()  # the CUDA flavor resolves its own Open3D dependencies
  "$VENV/bin/python" -m pip install -q "${cons[@]}" -e ".[$EXTRAS]"
  echo "$stamp" > .setup-stamp
fi

# 3. ROS 2 interface packages without wheels (tf2_msgs, nav2_msgs): built once into the venv.
[ "$ROS2" = 0 ] || VENV="$VENV" bash scripts/ros2-interfaces.sh

#!/usr/bin/env bash
# Builds the ROS 2 interface packages that are not published as wheels (tf2_msgs, and
# nav2_msgs' particle cloud) from src/mmpa/backends/ros2/interfaces into the virtual
# environment, with the rosidl generator wheels of the `ros2` extra and cmake + a C/C++
# compiler. Run by scripts/setup.sh; idempotent: a stamp in the venv records what was built
# (the sources, this script, the generator versions), so a rerun with nothing changed starts
# no process. Does nothing where the extra is not installed. See docs/ros2.md.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
VENV=$(cd "$VENV" && pwd)
IFC=src/mmpa/backends/ros2/interfaces
PACKAGES=(tf2_msgs nav2_msgs)

site=$(echo "$VENV"/lib/python3*/site-packages)
if [ ! -f "$site/rclpy/__init__.py" ]; then
  echo "[ros2] the ros2 extra is not installed in $VENV: no interfaces to build"
  exit 0
fi
# what the build depends on: the sources, this script, the generators' and rclpy's versions
gens=$(cd "$site" && ls -d ros_rosidl_generator_*.dist-info ros_rclpy-*.dist-info)
stamp=$( (cat "$0"; find "$IFC" -type f | sort | xargs cat; echo "$gens") | sha256sum | cut -c1-16)
stamp_file="$VENV/share/mmpa_ros2_interfaces.stamp"
if [ "$(cat "$stamp_file" 2>/dev/null)" = "$stamp" ]; then
  exit 0
fi

for tool in cmake cc c++; do
  command -v "$tool" >/dev/null || {
    echo "[ros2] building the ROS 2 interfaces needs $tool (apt-get install cmake g++)" >&2; exit 1; }
done
pyinc=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
[ -f "$pyinc/Python.h" ] || {
  echo "[ros2] building the ROS 2 interfaces needs Python's headers ($pyinc/Python.h):" \
    "apt-get install python3-dev" >&2; exit 1; }
gen=(-G "Unix Makefiles")
command -v ninja >/dev/null && gen=(-G Ninja)

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
for pkg in "${PACKAGES[@]}"; do
  echo "[ros2] building $pkg into $VENV"
  log="$work/$pkg.log"
  if ! {
    cmake -S "$IFC/$pkg" -B "$work/$pkg" "${gen[@]}" -DCMAKE_BUILD_TYPE=Release \
      -DCMAKE_INSTALL_PREFIX="$VENV" -DCMAKE_PREFIX_PATH="$VENV" \
      -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF &&
      cmake --build "$work/$pkg" -j "$(nproc)" &&
      cmake --install "$work/$pkg"
  } >"$log" 2>&1; then
    tail -40 "$log" >&2
    echo "[ros2] building $pkg failed (the log's end above)" >&2
    exit 1
  fi
done
# the built types import (the bootstrapper of the ros-* wheels sets LD_LIBRARY_PATH)
"$VENV/bin/python" -c 'from tf2_msgs.msg import TFMessage; from nav2_msgs.msg import ParticleCloud'
echo "$stamp" >"$stamp_file"

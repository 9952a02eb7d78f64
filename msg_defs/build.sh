#!/usr/bin/env bash
# Build the w2e_msgs interface package (this folder) with rosidl + plain CMake into a Python
# virtual environment that holds the ROS 2 Jazzy wheels, so `import w2e_msgs.msg` works there;
# and, the same way, the upstream interface packages of upstream/ that the package index lacks
# (tf2_msgs, control_msgs, franka_msgs: only the types the stack uses, upstream/README.md),
# each skipped where another install (a sourced ROS 2) already provides it.
#
#   bash msg_defs/build.sh [VENV]        (default: .venv next to msg_defs/; build/ holds its
#                                         build, another venv builds in VENV/build/)
#
# Why not colcon: colcon and ros2cli are not on the package index. Why the patching: the
# wheels' exported CMake files name the wheel build host's Python include directories
# (/opt/python/cp311-cp311/... for the cp311 wheels, cp312-cp312 for the cp312 ones), which do
# not exist on this machine: they are pointed at the venv's Python. Re-running is cheap:
# the patch is skipped once applied and CMake/ninja rebuild only what changed.
set -euo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(dirname "$HERE")"
VENV="${1:-$ROOT/.venv}"
VENV="$(cd "$VENV" && pwd)"
PY="$VENV/bin/python"
# the build folders: build/ for the default .venv; another venv (another Python, another
# prefix) builds in its own, so neither reuses a configuration made for the other
if [ -n "${W2E_MSGS_BUILD_DIR:-}" ]; then BUILD="$W2E_MSGS_BUILD_DIR"
elif [ "$VENV" = "$ROOT/.venv" ]; then BUILD="$ROOT/build/w2e_msgs"
else BUILD="$VENV/build/w2e_msgs"; fi

for tool in cmake ninja g++; do
  command -v "$tool" >/dev/null || { echo "[w2e_msgs] missing '$tool' (apt: cmake ninja-build g++)" >&2; exit 1; }
done
[ -x "$PY" ] || { echo "[w2e_msgs] no python at $PY" >&2; exit 1; }
[ -f "$VENV/share/rosidl_default_generators/cmake/rosidl_default_generatorsConfig.cmake" ] || {
  echo "[w2e_msgs] rosidl_default_generators is not installed in $VENV (pip install -r requirements.txt)" >&2
  exit 1
}

# --- 1. Python modules the CMake side needs but no wheel declares -------------------------
if ! _ROS_WHEELS_BOOTSTRAP_COMPLETE=1 "$PY" -c 'import catkin_pkg, em, lark' 2>/dev/null; then
  echo "[w2e_msgs] installing catkin_pkg, empy, lark (read by ament_cmake / rosidl at build time)"
  "$PY" -m pip install -q catkin_pkg "empy>=4,<5" lark
fi

# --- 2. point the wheels' exported CMake files at this machine's Python and numpy ----------
read -r PY_INC NP_INC PY_VER PY_TAG < <(_ROS_WHEELS_BOOTSTRAP_COMPLETE=1 "$PY" -c \
  'import sys, sysconfig, numpy; v = sys.version_info
print(sysconfig.get_paths()["include"], numpy.get_include(), f"{v[0]}.{v[1]}", f"cp{v[0]}{v[1]}")')
HOST_PY=/opt/python/$PY_TAG-$PY_TAG
mapfile -t stale < <(grep -rlF --include='*.cmake' "$HOST_PY" "$VENV/share" "$VENV/lib/cmake" 2>/dev/null || true)
if [ "${#stale[@]}" -gt 0 ]; then
  echo "[w2e_msgs] patching ${#stale[@]} CMake files: $HOST_PY -> $PY_INC, $NP_INC"
  # the numpy path first: it contains the generic prefix
  sed -i -e "s#$HOST_PY/lib/python$PY_VER/site-packages/numpy/_core/include#$NP_INC#g" \
         -e "s#$HOST_PY/include/python$PY_VER#$PY_INC#g" "${stale[@]}"
  left=$(grep -rlF --include='*.cmake' "$HOST_PY" "$VENV/share" 2>/dev/null | wc -l || true)
  [ "$left" = 0 ] || echo "[w2e_msgs] warning: $left CMake files still name $HOST_PY" >&2
fi

# --- 3. configure (once) and build + install into the venv prefix ------------------------
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
export LD_LIBRARY_PATH="$VENV/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export PATH="$VENV/bin:$PATH"
# the generators run under the venv's Python; skip the wheels' re-exec bootstrap there
export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1

mkdir -p "$(dirname "$BUILD")"
start=$(date +%s)
# build_package SOURCE_DIR BUILD_DIR: configure (once), build and install into the venv prefix
build_package() {
  local src="$1" build="$2"
  if [ -f "$build/CMakeCache.txt" ] &&
     ! grep -qxF "CMAKE_INSTALL_PREFIX:PATH=$VENV" "$build/CMakeCache.txt"; then
    echo "[w2e_msgs] $build was configured for another venv: configuring it anew"
    rm -rf "$build"
  fi
  if [ ! -f "$build/build.ninja" ]; then
    cmake -S "$src" -B "$build" -G Ninja \
      -DCMAKE_BUILD_TYPE=Release \
      -DCMAKE_INSTALL_PREFIX="$VENV" \
      -DPython3_EXECUTABLE="$PY" \
      -DPython3_FIND_VIRTUALENV=ONLY \
      -DBUILD_TESTING=OFF \
      -Wno-dev >"$build.configure.log" 2>&1 || {
        mkdir -p "$build"; tail -40 "$build.configure.log" >&2; return 1; }
  fi
  cmake --build "$build" --target install -- -j"${W2E_BUILD_JOBS:-2}" >"$build.build.log" 2>&1 || {
    tail -60 "$build.build.log" >&2; return 1; }
}

# upstream packages first (w2e_msgs does not use them, but a later one may); one provided by
# another install (its Python package outside this venv) is left alone
for src in "$HERE"/upstream/*/; do
  pkg="$(basename "$src")"
  where=$(unset _ROS_WHEELS_BOOTSTRAP_COMPLETE; "$PY" -c \
    "import importlib.util as u; s = u.find_spec('$pkg'); print(s.origin if s else '')" \
    2>/dev/null || true)
  if [ -n "$where" ] && [[ "$where" != "$VENV"/* ]]; then
    echo "[w2e_msgs] $pkg: provided by $where, not built"
    continue
  fi
  build_package "$src" "$(dirname "$BUILD")/$pkg" || exit 1
done
build_package "$HERE" "$BUILD" || exit 1

# --- 4. check from the venv's Python (through its normal start-up) -----------------------
unset _ROS_WHEELS_BOOTSTRAP_COMPLETE
"$PY" -c 'import w2e_msgs.msg, w2e_msgs.srv, w2e_msgs.action; w2e_msgs.action.ExecuteInteraction.Goal()' || {
  echo "[w2e_msgs] built, but 'import w2e_msgs' fails in $PY" >&2; exit 1; }
"$PY" -c 'from tf2_msgs.msg import TFMessage; from control_msgs.action import GripperCommand
from franka_msgs.action import Grasp, Move; TFMessage(); GripperCommand.Goal(); Grasp.Goal()' || {
  echo "[w2e_msgs] built, but tf2_msgs / control_msgs / franka_msgs do not import in $PY" >&2
  exit 1; }
echo "[w2e_msgs] installed into $VENV in $(( $(date +%s) - start )) s"

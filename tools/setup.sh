#!/usr/bin/env bash
# Idempotent set-up: Debian packages (when missing), .venv, torch (CPU build), the project (editable, with
# its native module). Called by `make setup`; safe to run again, it only does what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

DEB_PACKAGES=(
  libcgal-dev libgmp-dev libmpfr-dev libboost-dev libtbb-dev libeigen3-dev  # native core
  cmake g++ make                                                             # build tools
  libosmesa6 libegl1 libgl1-mesa-dri                                         # pyrender offscreen (OSMesa/EGL)
  libusb-1.0-0 libgomp1                                                      # open3d runtime
)
missing=()
for p in "${DEB_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$PY" -m venv .venv
fi
VPY=.venv/bin/python
PIP=(.venv/bin/python -m pip --disable-pip-version-check -q)
# pip warns about every missing folder of a local index configured on some machines; keep real errors only.
pip_install() { "${PIP[@]}" install "$@" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2); }

# torch first and pinned to the CPU build, so no later requirement pulls a CUDA build.
if ! "$VPY" -c "import torch, sys; sys.exit(0 if torch.__version__.startswith('2.13.0') else 1)" 2>/dev/null; then
  echo "setup: installing torch==2.13.0 (CPU)"
  pip_install --upgrade pip
  pip_install torch==2.13.0
fi

# Build requirements in the venv so the editable install needs no isolated build environment.
"$VPY" -c "import scikit_build_core, nanobind" 2>/dev/null || \
  pip_install "scikit-build-core>=0.10" "nanobind>=2.0" ninja

stamp=.venv/.dmesh-installed
inputs=$(cat pyproject.toml native/CMakeLists.txt native/src/* native/bindings/* | sha1sum | cut -c1-40)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$inputs" ] || ! "$VPY" -c "import dmesh._native" 2>/dev/null; then
  echo "setup: installing the project (editable) and building the native module"
  pip_install --no-build-isolation -e ".[harness,test]" torch==2.13.0
  # pyrender pins PyOpenGL 3.1.0, whose OSMesa binding is broken; 3.1.10 works (deps_bench.md section 6).
  pip_install --no-deps "PyOpenGL==3.1.10"
  echo "$inputs" > "$stamp"
fi

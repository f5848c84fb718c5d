#!/usr/bin/env bash
# polarface's two entry points. Each does all set-up (a virtual environment in .venv with the
# project and its dependencies) and then runs:
#   ./run.sh demo [--out DIR]   the main job on the embedded default (writes DIR, default demo_out/)
#   ./run.sh test [PYTEST ARGS] the whole test suite (oracles included)
# Needs only Python >= 3.11 on PATH (override with PYTHON=...). PyTorch is pinned by
# POLARFACE_TORCH (default torch==2.13.0); on a CUDA machine pip picks the CUDA build.
set -euo pipefail
cd "$(dirname "$0")"
PYTHON=${PYTHON:-python3}
VENV=${POLARFACE_VENV:-.venv}
TORCH_SPEC=${POLARFACE_TORCH:-torch==2.13.0}

setup() {
  local extras=$1 stamp="$VENV/.polarface-$1"
  if [ ! -x "$VENV/bin/python" ]; then
    "$PYTHON" -m venv "$VENV"
  fi
  # Reinstall only when the project's packaging changed since the last set-up.
  if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ run.sh -nt "$stamp" ]; then
    "$VENV/bin/python" -m pip install --quiet --upgrade pip
    "$VENV/bin/python" -m pip install --quiet "$TORCH_SPEC"
    "$VENV/bin/python" -m pip install --quiet -e ".$extras"
    touch "$stamp"
  fi
  if [ ! -f "$VENV/.polarface-system" ] || [ "$stamp" -nt "$VENV/.polarface-system" ]; then
    system_libraries
    touch "$VENV/.polarface-system"
  fi
}

# System libraries that Open3D's wheel links and a minimal machine may lack (a bare Debian has no
# libusb-1.0): installed with apt-get when running as root; otherwise the error names the packages.
system_libraries() {
  "$VENV/bin/python" -c "import open3d" >/dev/null 2>&1 && return 0
  local packages
  packages=$("$VENV/bin/python" -c \
    "from polarface.geometry.open3d_library import DEBIAN_PACKAGES; print(' '.join(DEBIAN_PACKAGES))")
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "run.sh: installing the system libraries Open3D links: $packages" >&2
    # shellcheck disable=SC2086
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $packages >/dev/null) \
      || echo "run.sh: apt-get could not install $packages" >&2
  fi
  "$VENV/bin/python" -c "
import sys
from polarface.geometry.open3d_library import open3d_module
try:
    open3d_module()
except ImportError as exc:
    sys.exit(f'run.sh: {exc}')"
}

cmd=${1:-}
[ $# -gt 0 ] && shift
case "$cmd" in
  demo)
    setup ""
    exec "$VENV/bin/polarface" demo "$@"
    ;;
  test)
    setup "[dev]"
    bash tests/tools/install_test_tools.sh "$VENV"
    exec "$VENV/bin/python" -m pytest -n "${POLARFACE_TEST_WORKERS:-2}" --dist worksteal "$@"
    ;;
  *)
    echo "usage: ./run.sh demo [--out DIR] | ./run.sh test [pytest args]" >&2
    exit 2
    ;;
esac

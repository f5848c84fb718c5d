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
    exec "$VENV/bin/python" -m pytest -n "${POLARFACE_TEST_WORKERS:-2}" "$@"
    ;;
  *)
    echo "usage: ./run.sh demo [--out DIR] | ./run.sh test [pytest args]" >&2
    exit 2
    ;;
esac

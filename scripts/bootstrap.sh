#!/usr/bin/env bash
# Idempotent set-up: system library for open3d, a virtual environment in .venv, torch (CPU
# wheel 2.13.0) and nerfpipe with all extras, installed editable. Safe to run repeatedly.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${NERFPIPE_VENV:-.venv}

# --test: also the system packages only the tests need (headless Chromium for the report and viewer tests).
WITH_TEST_DEPS=0
[ "${1:-}" = "--test" ] && WITH_TEST_DEPS=1

apt_install() {
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    echo "bootstrap: apt-get install $*"
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@"; } >/dev/null
  else
    echo "bootstrap: warning: please install the system packages: $*" >&2
  fi
}

# open3d's wheel links libusb-1.0 (and libgomp); install them when missing and we may.
if ! ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then
  apt_install libusb-1.0-0 libgomp1
fi
if [ "$WITH_TEST_DEPS" = 1 ] && ! command -v chromium >/dev/null 2>&1; then
  apt_install chromium fonts-liberation fonts-dejavu-core
fi

[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
stamp="$VENV/.nerfpipe-installed"
want=$( (cat pyproject.toml scripts/bootstrap.sh; cat plugins/*/pyproject.toml 2>/dev/null || true) | sha256sum | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "bootstrap: installing dependencies into $VENV (first run takes a few minutes)"
  quiet() { { grep -v "is ignored: it is neither a file nor a directory" || true; } >&2; }  # local index noise
  "$VENV/bin/pip" install -q --disable-pip-version-check "torch==2.13.0" 2>&1 | quiet
  "$VENV/bin/pip" install -q --disable-pip-version-check -e ".[all]" 2>&1 | quiet
  echo "$want" > "$stamp"
fi

#!/usr/bin/env bash
# Idempotent set-up: system library for open3d, a virtual environment in .venv, torch (CPU
# wheel 2.13.0) and nerfpipe with all extras, installed editable. Safe to run repeatedly.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${NERFPIPE_VENV:-.venv}

# open3d's wheel links libusb-1.0 (and libgomp); install them when missing and we may.
if ! ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    echo "bootstrap: installing libusb-1.0-0 (needed by open3d)"
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null
  else
    echo "bootstrap: warning: libusb-1.0 is missing; install it (apt-get install libusb-1.0-0) for open3d" >&2
  fi
fi

[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
stamp="$VENV/.nerfpipe-installed"
want=$( (cat pyproject.toml scripts/bootstrap.sh; cat plugins/*/pyproject.toml 2>/dev/null || true) | sha256sum | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "bootstrap: installing dependencies into $VENV (first run takes a few minutes)"
  "$VENV/bin/pip" install -q --disable-pip-version-check "torch==2.13.0"
  "$VENV/bin/pip" install -q --disable-pip-version-check -e ".[all]"
  echo "$want" > "$stamp"
fi

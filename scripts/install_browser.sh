#!/usr/bin/env bash
# Install what the in-browser viewer tests need: Debian's `chromium` (only if missing) and the
# Python `playwright` package into .venv (no browser download: the tests launch
# /usr/bin/chromium through `executable_path`). Idempotent; safe to call from .ci/run.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
if ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = "0" ]; then SUDO=""; else SUDO="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -q >/dev/null || { echo "install_browser: apt-get update failed" >&2; exit 1; }
  $SUDO apt-get install -y -q --no-install-recommends chromium fonts-liberation >/dev/null \
    || { echo "install_browser: apt-get install chromium failed" >&2; exit 1; }
fi
if ! "$PY" -c "import playwright" >/dev/null 2>&1; then
  PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 "$PY" -m pip install -q -c constraints.txt "playwright>=1.40"
fi
echo "browser: $(command -v chromium) ($(chromium --version 2>/dev/null || echo '?'))"
echo "playwright: $("$PY" -c 'import importlib.metadata as m; print(m.version("playwright"))')"

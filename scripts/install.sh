#!/usr/bin/env bash
# Install everything NePF needs on a fresh Debian 12 machine (Python 3.11), idempotently:
#   Debian packages (headless EGL/OSMesa for previews, Chromium for browser tests, Redis,
#   PostgreSQL client/server when missing), a virtual environment .venv with the library, the
#   service and the test tools (`pip install -e ".[service,test]"`), torch at the version pinned
#   in constraints.txt (pyproject.toml only bounds it), and the npm packages (web viewer build,
#   Khronos glTF validator).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi

echo "== apt packages"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
pkgs=$(grep -v '^\s*#' .ci/apt-packages.txt | tr '\n' ' ')
pkgs="$pkgs python3-venv python3-dev zip"
command -v node >/dev/null 2>&1 || pkgs="$pkgs nodejs npm"
command -v redis-server >/dev/null 2>&1 || pkgs="$pkgs redis-server"
command -v pg_ctlcluster >/dev/null 2>&1 || pkgs="$pkgs postgresql"
$SUDO apt-get install -y -q --no-install-recommends $pkgs

echo "== python virtual environment (.venv)"
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip setuptools wheel
# torch first, at the pin of constraints.txt (the Dockerfile and the benchmarks use the same file).
# Both installs take -c constraints.txt: pyproject.toml asks only torch>=2.4,<3, and without the
# constraint the resolver could pick another torch (on Linux, PyPI's default wheel pulls GBs of
# CUDA packages) or replace the pinned one.
.venv/bin/python -m pip install -q -c constraints.txt torch
.venv/bin/python -m pip install -q -c constraints.txt -e ".[service,test]"

echo "== npm packages"
while read -r dir; do
  [ -z "$dir" ] && continue
  case "$dir" in \#*) continue;; esac
  (cd "$ROOT/$dir" && npm ci --no-audit --no-fund --loglevel=error && \
   if grep -q '"build"' package.json; then npm run build --silent; fi)
done < .ci/npm-dirs.txt
echo "== installed"

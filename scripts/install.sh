#!/usr/bin/env bash
# Install everything NePF needs on a fresh Debian 12 machine (Python 3.11), idempotently:
#   Debian packages (headless EGL/OSMesa for previews, Chromium for browser tests, Redis,
#   PostgreSQL client/server when missing), a virtual environment .venv with the library, the
#   service and the test tools (`pip install -e ".[service,test]"`), torch at the version pinned
#   in pyproject.toml, and the npm packages (web viewer build, Khronos glTF validator).
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
# torch first, at the one pin in pyproject.toml (the Dockerfile reads the same line)
TORCH_SPEC=$(.venv/bin/python -c 'import tomllib; deps = tomllib.load(open("pyproject.toml", "rb"))["project"]["dependencies"]; print(next(d for d in deps if d.startswith("torch")))')
.venv/bin/python -m pip install -q "$TORCH_SPEC"
.venv/bin/python -m pip install -q -e ".[service,test]"

echo "== npm packages"
while read -r dir; do
  [ -z "$dir" ] && continue
  case "$dir" in \#*) continue;; esac
  (cd "$ROOT/$dir" && npm ci --no-audit --no-fund --loglevel=error && \
   if grep -q '"build"' package.json; then npm run build --silent; fi)
done < .ci/npm-dirs.txt
echo "== installed"

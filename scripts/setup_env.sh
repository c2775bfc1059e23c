#!/usr/bin/env bash
# Creates .venv and installs lidarmap with its test extras; installs the system libraries it
# needs when running as root (CI, containers), otherwise says exactly what to install.
set -euo pipefail
cd "$(dirname "$0")/.."

need_pkgs=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib "libusb-1.0.so.0" || need_pkgs+=(libusb-1.0-0)
if [[ "${LIDARMAP_SETUP_TEST_DEPS:-0}" == "1" ]]; then
    command -v redis-server >/dev/null 2>&1 || need_pkgs+=(redis-server)
    compgen -G "/usr/lib/postgresql/*/bin/initdb" >/dev/null || command -v initdb >/dev/null 2>&1 \
        || need_pkgs+=(postgresql)  # the PostgreSQL job store tests start a throw-away server
    command -v chromium >/dev/null 2>&1 || need_pkgs+=(chromium)
    command -v docker-compose >/dev/null 2>&1 || need_pkgs+=(docker-compose)  # `compose config` of the README's deploy
fi
if ((${#need_pkgs[@]})); then
    if [[ "$(id -u)" == "0" ]] && command -v apt-get >/dev/null 2>&1; then
        echo "setup: installing system packages: ${need_pkgs[*]}"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq >/dev/null || true
        apt-get install -y -qq --no-install-recommends "${need_pkgs[@]}" >/dev/null
    else
        echo "setup: missing system packages: ${need_pkgs[*]}" >&2
        echo "setup: install them with: sudo apt-get install ${need_pkgs[*]}" >&2
        have_lib "libusb-1.0.so.0" || exit 1
    fi
fi

PYTHON="${PYTHON:-}"
if [[ -z "$PYTHON" ]]; then
    for cand in python3.11 python3.12 python3; do
        if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(not ((3, 11) <= sys.version_info[:2] < (3, 13)))'; then
            PYTHON="$cand"; break
        fi
    done
fi
if [[ -z "$PYTHON" ]]; then
    echo "setup: lidarmap needs Python 3.11 or 3.12 (python3.11 not found on PATH)" >&2
    exit 1
fi
# Compile the engine's numba kernels into numba's on-disk cache (beside the sources), so that no run
# compiles at first use; quick (a few seconds) when the cache is already warm.
warm_kernels() {
    .venv/bin/python -m slam_engine.kernels || {
        echo "setup: compiling the engine's kernels failed (see the messages above)" >&2; exit 1; }
}
if [[ -f .venv/.installed && .venv/.installed -nt pyproject.toml && .venv/.installed -nt scripts/setup_env.sh ]]; then
    warm_kernels
    exit 0  # already installed and up to date
fi
[[ -x .venv/bin/python ]] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip 2>/dev/null || true
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[dev,distributed]" 2>&1 \
    | grep -v "is ignored: it is neither a file nor a directory" || true
.venv/bin/python -c "import slam_engine, service, open3d" || {
    echo "setup: installation check failed (see the messages above)" >&2; exit 1; }
touch .venv/.installed
warm_kernels

#!/usr/bin/env bash
# Create or update the project virtualenv (.venv) with this package, its pinned deps and test deps.
# Idempotent: reinstalls only when pyproject.toml changed since the last successful install.
set -euo pipefail
cd "$(dirname "$0")/.."

python_bin="${PACDP_PYTHON:-python3}"  # resolves to $(cat .python-version) under pyenv
if ! "$python_bin" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
  echo "error: Python >= 3.12 is required (lerobot 0.6.1); '$python_bin' is $("$python_bin" --version 2>&1)." >&2
  echo "fix: install Python $(cat .python-version) (e.g. 'pyenv install $(cat .python-version)') or set PACDP_PYTHON." >&2
  exit 2
fi

if [ ! -x .venv/bin/python ]; then
  echo "[bootstrap] creating .venv with $("$python_bin" --version)"
  "$python_bin" -m venv .venv
fi

# System libraries, where this user may install them (root with apt): OSMesa renders rollout videos on a
# CPU machine; FFmpeg's libraries let torchcodec load (else LeRobot prints a long traceback at start-up).
system_libs=(libosmesa6 libavutil57 libavcodec59 libavformat59 libavdevice59 libavfilter8 libswscale6 libswresample4)
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null && command -v dpkg-query >/dev/null; then
  missing=()
  for lib in "${system_libs[@]}"; do
    dpkg-query -W -f='${Status}' "$lib" 2>/dev/null | grep -q "install ok installed" || missing+=("$lib")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    echo "[bootstrap] installing ${missing[*]} (offscreen rendering, video decoding)"
    if ! DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}" >/dev/null 2>&1; then
      DEBIAN_FRONTEND=noninteractive apt-get update -q >/dev/null 2>&1 || true
      DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}" >/dev/null 2>&1 \
        || echo "[bootstrap] note: could not install ${missing[*]}; rollout videos will be blank (see README)"
    fi
  fi
fi

stamp=.venv/.pacdp-install-stamp
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[bootstrap] installing lerobot_policy_pacdp and its dependencies into .venv (first time: several minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[test]"
  echo "$want" > "$stamp"
else
  echo "[bootstrap] .venv is up to date"
fi

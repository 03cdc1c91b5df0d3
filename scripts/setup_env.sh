#!/usr/bin/env bash
# Creates (or reuses) the project's virtualenv and links it to ./.venv.
# The environment is cached outside the clone, keyed by a hash of the pins, so a second
# clone or CI run reuses it; a fresh machine builds it from nothing (~6 min, ~8.5 GB).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

python_bin="${PYTHON:-python3}"
pins_hash="$(cat requirements.txt constraints.txt | sha256sum | cut -c1-16)"
cache_dir="${SPLATREPLACE_CACHE:-$HOME/.cache/splatreplace_ns}"
venv="$cache_dir/venv-$pins_hash"

# open3d 0.20 needs libusb at import time; install it when we can (root on Debian).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "[setup] installing libusb-1.0-0 (needed by open3d)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "[setup] warning: libusb-1.0-0 is missing; open3d will not import (sudo apt-get install libusb-1.0-0)" >&2
  fi
fi

if [ ! -f "$venv/.complete" ]; then
  echo "[setup] creating $venv (first time only)"
  rm -rf "$venv"
  mkdir -p "$cache_dir"
  "$python_bin" -m venv "$venv"
  "$venv/bin/python" -m pip install -q --upgrade pip
  "$venv/bin/python" -m pip install -c constraints.txt -r requirements.txt
  # Three wheels ship cv2/ (nerfstudio's opencv-python-headless, nuscenes-devkit's opencv-python,
  # and ours); install the contrib build last so it owns cv2/ deterministically.
  "$venv/bin/python" -m pip install -q --no-deps --force-reinstall opencv-contrib-python-headless==4.10.0.84
  touch "$venv/.complete"
fi

ln -sfn "$venv" "$root/.venv"
# Editable install of this clone (cheap; re-run so the venv points at the current clone).
"$venv/bin/python" -m pip install -q --no-deps --no-build-isolation -e "$root"

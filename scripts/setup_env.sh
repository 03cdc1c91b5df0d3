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

# Debian packages: libusb (open3d 0.20 needs it at import time), colmap and ffmpeg (ns-process-data on a folder
# of photos), chromium (the viewer test clicks in a real browser) and npm (installs that test's driver).
# Installed when we can (root on Debian); otherwise the exact command to run is printed and setup goes on.
missing=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
command -v colmap >/dev/null || missing+=(colmap)
command -v ffmpeg >/dev/null || missing+=(ffmpeg)
command -v chromium >/dev/null || missing+=(chromium)
command -v npm >/dev/null || missing+=(npm)
if [ "${#missing[@]}" -gt 0 ]; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "[setup] installing ${missing[*]} (apt-get)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  else
    echo "[setup] warning: missing Debian packages; run: sudo apt-get install -y ${missing[*]}" >&2
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

# The viewer test's browser driver (playwright-core, pinned in tests/browser/package-lock.json), cached like the
# venv, keyed by the lock file's hash, and linked to tests/browser/node_modules. Nothing downloads at test time.
lock_hash="$(sha256sum tests/browser/package-lock.json | cut -c1-16)"
node_env="$cache_dir/browser-$lock_hash"
if [ ! -f "$node_env/.complete" ]; then
  if command -v npm >/dev/null; then
    echo "[setup] installing playwright-core into $node_env (first time only)"
    rm -rf "$node_env"
    mkdir -p "$node_env"
    cp tests/browser/package.json tests/browser/package-lock.json "$node_env/"
    if (cd "$node_env" && npm ci --no-audit --no-fund --ignore-scripts >/dev/null); then
      touch "$node_env/.complete"
    else
      echo "[setup] warning: npm ci failed; the viewer browser test will skip (or fail in CI)" >&2
    fi
  else
    echo "[setup] warning: npm is missing (sudo apt-get install -y npm); the viewer browser test will skip" >&2
  fi
fi
link="$root/tests/browser/node_modules"
if [ -f "$node_env/.complete" ] && { [ -L "$link" ] || [ ! -e "$link" ]; }; then  # a real folder there is kept
  ln -sfn "$node_env/node_modules" "$link"
fi

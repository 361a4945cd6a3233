#!/usr/bin/env bash
# Idempotent set-up of a fresh machine: Debian packages (only if missing) and the venv in .venv.
# Re-running it is cheap: the venv is reinstalled only when pyproject.toml changes.
# libclang-rt-14-dev carries libFuzzer + the sanitizer runtimes (only a recommend of clang).
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(gcc-arm-none-eabi libnewlib-arm-none-eabi libllvm19 mbpoll clang libclang-rt-14-dev qemu-system-arm chromium chromium-driver)
missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "setup: installing Debian packages: ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$PY" -m venv .venv
fi
stamp=".venv/.installed-$(sha256sum pyproject.toml | cut -c1-16)"
if [ ! -f "$stamp" ]; then
  echo "setup: installing trimeter into .venv (with the maps, hardware, docs and dev extras)"
  # uv fetches and installs the wheels in parallel (pip one by one, which dominated a fresh clone's
  # `make test` set-up); it resolves the same versions. pip where uv cannot be had.
  if .venv/bin/python -m pip install -q uv; then
    .venv/bin/uv pip install -q --python .venv/bin/python -e ".[maps,hardware,docs,dev]"
  else
    echo "setup: uv could not be installed; installing with pip (slower)"
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q -e ".[maps,hardware,docs,dev]"
  fi
  rm -f .venv/.installed-*
  touch "$stamp"
fi

#!/usr/bin/env bash
# Install everything the project needs into .venv (idempotent). `scripts/setup.sh test` adds the test tools.
set -euo pipefail
cd "$(dirname "$0")/.."
want=${1:-run}
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
apt_install() {  # Debian packages, only when missing
  local missing=()
  for pkg in "$@"; do dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg"); done
  if [ ${#missing[@]} -gt 0 ]; then
    echo "installing Debian packages: ${missing[*]}"
    $SUDO apt-get update -qq && $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
  fi
}
apt_install libusb-1.0-0            # open3d's wheel links against it
if [ "$want" = test ]; then apt_install chromium; fi   # the end-to-end browser test
pipq() {  # pip, quiet, without the noise of this machine's find-links warnings
  .venv/bin/python -m pip install -q "$@" 2>&1 | { grep -v -e "^WARNING: Location" -e "is ignored: it is neither" -e "^cpas-toolbox 1.0.0 requires" -e "dependency conflicts" || true; }
}
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.installed-$want-$(cat pyproject.toml constraints.txt scripts/setup.sh | sha1sum | cut -c1-12)
if [ ! -e "$stamp" ]; then
  pipq --upgrade pip
  if [ "$want" = test ]; then
    pipq -c constraints.txt -e ".[test]"
    # cpas_toolbox 1.0.0 pins matplotlib<3.6 (does not build on 3.11): install it without its pins,
    # plus what its metrics and Redwood dataset modules import (torch: the CPU wheel on this disk).
    pipq --no-deps cpas-toolbox==1.0.0
    pipq -c constraints.txt torch==2.13.0 yoco gdown requests
  else
    pipq -c constraints.txt -e .
  fi
  touch "$stamp"
fi

#!/usr/bin/env bash
# Installs the Debian packages phasecal's backends and tests need. Runs apt-get only when
# something is missing and we are root on a Debian-like system; elsewhere it prints what
# to install and carries on.
#   Aravis (GenICam cameras, GigE Vision fake for tests): gir1.2-aravis-0.8, libaravis-0.8-0
#   building PyGObject<3.51 (pip): libgirepository1.0-dev libcairo2-dev pkg-config gcc
#     python3-dev (pycairo/PyGObject compile C extensions)
#   SDL display tests under X: xvfb (read-back through Xvfb -fbdir)
#   pyusb: libusb-1.0-0
#   mrcal export tests (the real mrcal loads and projects .cameramodel files; it runs
#     under the system Python /usr/bin/python3): python3-mrcal
#   hand-eye methods checked against OpenCV 4's own (system Python): python3-opencv
#   web page end-to-end test (selenium): chromium chromium-driver
set -euo pipefail
packages=(
  gir1.2-aravis-0.8 libaravis-0.8-0 libgirepository1.0-dev libcairo2-dev pkg-config
  gcc python3-dev xvfb libusb-1.0-0 python3-mrcal python3-opencv
  chromium chromium-driver
)
missing=()
if command -v dpkg-query >/dev/null 2>&1; then
  for p in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
else
  echo "install-system-deps: not a Debian system; make sure these are installed: ${packages[*]}" >&2
  exit 0
fi
if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null 2>&1; then
  echo "install-system-deps: missing Debian packages (run as root: apt-get install ${missing[*]})" >&2
  exit 0
fi
echo "install-system-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
# Fresh machines often run unattended upgrades at boot: wait (up to 10 min) for the dpkg
# and list locks instead of failing at once.
apt_wait=(-o DPkg::Lock::Timeout=600)
apt-get "${apt_wait[@]}" update -qq
apt-get "${apt_wait[@]}" install -y -qq --no-install-recommends "${missing[@]}" >/dev/null

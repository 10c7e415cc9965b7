#!/usr/bin/env bash
# Extracts OpenCV's sample stereo chessboard images (left01..left14.jpg, right01..right14.jpg,
# no 10: 13 real pairs of a 9x6 inner-corner board, 640x480) from Debian's opencv-doc
# package into data/opencv-samples/ (ignored by git), for the passive-target tests and
# benchmarks. Only the images are kept; nothing is installed. Skips when they are there.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dest="${root}/data/opencv-samples"
if [ -f "${dest}/left01.jpg" ] && [ -f "${dest}/right14.jpg" ]; then
  exit 0
fi
if ! command -v apt-get >/dev/null 2>&1 || ! command -v dpkg-deb >/dev/null 2>&1; then
  echo "fetch-opencv-samples: needs apt-get and dpkg-deb (Debian's opencv-doc package)" >&2
  exit 0
fi
work="$(mktemp -d)"
trap 'rm -rf "${work}"' EXIT
download() { (cd "${work}" && apt-get download -qq opencv-doc 2>/dev/null); }
# A machine whose packages came preinstalled may have no package lists yet: refresh once.
download || { [ "$(id -u)" -eq 0 ] && apt-get -o DPkg::Lock::Timeout=600 update -qq && download; } || {
  echo "fetch-opencv-samples: apt-get download opencv-doc failed (run apt-get update as root)" >&2
  exit 0
}
dpkg-deb --fsys-tarfile "${work}"/opencv-doc_*.deb \
  | tar -x -C "${work}" --wildcards './usr/share/doc/opencv-doc/examples/data/left[0-9][0-9].jpg' \
      './usr/share/doc/opencv-doc/examples/data/right[0-9][0-9].jpg'
mkdir -p "${dest}"
cp "${work}"/usr/share/doc/opencv-doc/examples/data/{left,right}[0-9][0-9].jpg "${dest}/"
echo "fetch-opencv-samples: $(ls "${dest}" | wc -l) images in data/opencv-samples/"

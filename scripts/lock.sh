#!/usr/bin/env bash
# Regenerates constraints.txt: the exact versions of every package of phasecal with all
# extras and the dev tools, resolved in a fresh venv. Versions already pinned stay as they are
# (the current constraints.txt constrains the resolution) unless `--upgrade` is given; new
# dependencies get the newest versions within pyproject.toml's ranges. Run after changing a
# dependency and commit the result (the README's set-up and CI install from it).
set -euo pipefail
cd "$(dirname "$0")/.."
keep=(-c constraints.txt)
if [ "${1:-}" = "--upgrade" ] || [ ! -f constraints.txt ]; then
  keep=()
fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m venv "$tmp/venv"
"$tmp/venv/bin/pip" install -q --upgrade pip
"$tmp/venv/bin/pip" install -q "${keep[@]}" '.[all,dev]'
{
  echo "# Exact versions for phasecal[all,dev] (scripts/lock.sh; Python 3.11, Linux x86_64)."
  echo "# Install with: pip install -c constraints.txt -e '.[all,dev]'"
  "$tmp/venv/bin/pip" freeze --exclude phasecal | LC_ALL=C sort -f
} > constraints.txt.new
mv constraints.txt.new constraints.txt
echo "wrote constraints.txt ($(grep -vc '^#' constraints.txt) packages)"

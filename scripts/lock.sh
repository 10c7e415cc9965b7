#!/usr/bin/env bash
# Regenerates constraints.txt: the exact versions of every package of phasecal with all
# extras and the dev tools, resolved from pyproject.toml's ranges in a fresh venv.
# Run after changing a dependency; commit the result (the README's set-up and CI install
# from it, so results stay reproducible).
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m venv "$tmp/venv"
"$tmp/venv/bin/pip" install -q --upgrade pip
"$tmp/venv/bin/pip" install -q '.[all,dev]'
{
  echo "# Exact versions for phasecal[all,dev] (scripts/lock.sh; Python 3.11, Linux x86_64)."
  echo "# Install with: pip install -c constraints.txt -e '.[all,dev]'"
  "$tmp/venv/bin/pip" freeze --exclude phasecal | LC_ALL=C sort -f
} > constraints.txt
echo "wrote constraints.txt ($(grep -vc '^#' constraints.txt) packages)"

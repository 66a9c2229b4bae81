#!/usr/bin/env bash
# One entry point that does all set-up on a fresh machine with only Python 3.11:
#   bash tools/run.sh demo [ARGS...]   the main job end to end (scene -> fit -> atlas -> edit + pose -> render -> report)
#   bash tools/run.sh test [ARGS...]   the test suite
#   bash tools/run.sh pointgt ARGS...  any other `pointgt` subcommand
# The virtual environment lives in .venv next to this repository (override with POINTGT_VENV).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${POINTGT_VENV:-$here/.venv}"
py="${PYTHON:-python3.11}"
command -v "$py" >/dev/null 2>&1 || py=python3
stamp="$venv/.pointgt-installed"
if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating virtual environment in $venv" >&2
  "$py" -m venv "$venv"
fi
# Reinstall only when the project's dependency list changed.
want="$(sha1sum "$here/pyproject.toml" | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[setup] installing dependencies (torch 2.13.0 CPU, bpy 5.0.1, ...)" >&2
  "$venv/bin/python" -m pip install -q --disable-pip-version-check -e "$here" >&2
  echo "$want" > "$stamp"
fi
cmd="${1:-demo}"; shift || true
cd "$here"
case "$cmd" in
  test) exec "$venv/bin/python" -m pytest -q "$@" ;;
  demo) exec "$venv/bin/pointgt" demo "$@" ;;
  pointgt) exec "$venv/bin/pointgt" "$@" ;;
  *) echo "usage: bash tools/run.sh demo|test|pointgt [ARGS...]" >&2; exit 2 ;;
esac

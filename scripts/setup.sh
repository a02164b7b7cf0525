#!/usr/bin/env bash
# Creates ./.venv with everything codearcade needs, from the lock. Idempotent: a second run with an
# unchanged lock does nothing. Works offline from the PyPI mirror; needs Python 3.11.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$(command -v python3.11 || command -v python3)}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.codearcade-setup
want=$(cat requirements.txt requirements-nodeps.txt pyproject.toml | sha256sum | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "codearcade: installing into .venv (about 2 minutes the first time)..." >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.txt
  # ocatari pins numpy<2 in its metadata but runs on numpy 2 (we pass it int64 RAM): no-deps.
  .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps -r requirements-nodeps.txt
  .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps -e .
  echo "$want" > "$stamp"
fi

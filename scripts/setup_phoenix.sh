#!/usr/bin/env bash
# Creates ./.venv-phoenix with Arize Phoenix (requirements-phoenix.txt), the real OTLP receiver that
# tests/test_otlp_export.py starts on 127.0.0.1; without it that test skips. A venv of its own keeps
# Phoenix's ~140 packages out of codearcade's. Idempotent: a second run with an unchanged lock does nothing.
# Measured here: about 1 minute and 850 MB the first time.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$(command -v python3.11 || command -v python3)}
[ -x .venv-phoenix/bin/python ] || "$PY" -m venv .venv-phoenix
stamp=.venv-phoenix/.codearcade-setup
want=$(sha256sum requirements-phoenix.txt | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "codearcade: installing Arize Phoenix into .venv-phoenix (about a minute the first time)..." >&2
  .venv-phoenix/bin/python -m pip install -q --disable-pip-version-check -r requirements-phoenix.txt
  echo "$want" > "$stamp"
fi

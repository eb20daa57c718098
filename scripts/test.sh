#!/usr/bin/env bash
# The whole test suite: set-up, format and lint checks (Python and the viewer), type check, then every test
# (unit, api, e2e, browser, real data). .pre-commit-config.yaml runs the same checks before a commit.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
code=(api workers core gpu_kernels tests bench scripts)
.venv/bin/ruff format --check "${code[@]}"
.venv/bin/ruff check "${code[@]}"
.venv/bin/mypy
npm run --prefix web --silent lint
exec .venv/bin/python -m pytest "$@"

#!/usr/bin/env bash
# The whole test suite: set-up, lint, type check, then every test (unit, api, e2e, browser, real data).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
.venv/bin/ruff check api workers gpu_kernels tests bench
.venv/bin/mypy
exec .venv/bin/python -m pytest "$@"

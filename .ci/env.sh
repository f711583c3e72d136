# shellcheck shell=bash
# Source this file: creates (once) the project's virtual environment in .venv,
# installs the project and its pinned dependencies, and makes Dr.Jit's LLVM
# backend usable.
#
# Dr.Jit's LLVM backend (Mitsuba's fast CPU variants) crashes with Debian 12's
# default LLVM 15. It works with Debian's libllvm19: we install it when we can
# (root + apt) and point DRJIT_LIBLLVM_PATH at libLLVM.so.19.1. Where that is
# impossible, glossrig.twin falls back to Mitsuba's scalar variant with a warning.
set -e
GLOSSRIG_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${GLOSSRIG_VENV:-$GLOSSRIG_ROOT/.venv}"
PY="${PYTHON:-python3}"

find_llvm19() {
    for f in /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 /usr/lib/aarch64-linux-gnu/libLLVM.so.19.1 \
             /usr/lib/llvm-19/lib/libLLVM.so.19.1 /usr/lib/llvm-19/lib/libLLVM-19.so; do
        [ -e "$f" ] && { echo "$f"; return 0; }
    done
    return 1
}

if [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
    if ! find_llvm19 >/dev/null; then
        if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
            echo "[glossrig] installing libllvm19 for Dr.Jit's LLVM backend" >&2
            (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >/dev/null 2>&1 \
                || echo "[glossrig] WARNING: could not install libllvm19; Mitsuba will use the slow scalar variant" >&2
        else
            echo "[glossrig] WARNING: libllvm19 missing and cannot be installed here; Mitsuba will use the slow scalar variant" >&2
        fi
    fi
    if LLVM19="$(find_llvm19)"; then
        export DRJIT_LIBLLVM_PATH="$LLVM19"
    fi
fi

# Tools the tests use where a user would use them: headless Chromium opens the HTML
# report (tests/test_report.py) and glslangValidator compiles the exported BRDF
# Explorer shader (tests/test_exports.py). Installed when we can (root + apt); the
# tests that need them skip with the reason where they are missing.
want=()
command -v chromium >/dev/null || want+=(chromium)
command -v glslangValidator >/dev/null || want+=(glslang-tools)
if [ "${#want[@]}" -gt 0 ] && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "[glossrig] installing ${want[*]} for the report and export tests" >&2
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${want[@]}") >/dev/null 2>&1 \
        || echo "[glossrig] WARNING: could not install ${want[*]}; the tests that need them will skip" >&2
fi

STAMP="$VENV/.glossrig-installed"
if [ ! -x "$VENV/bin/python" ]; then
    echo "[glossrig] creating virtual environment $VENV" >&2
    "$PY" -m venv "$VENV"
fi
if [ ! -f "$STAMP" ] || [ "$GLOSSRIG_ROOT/pyproject.toml" -nt "$STAMP" ]; then
    echo "[glossrig] installing glossrig and its dependencies (first run takes a few minutes)" >&2
    "$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
    "$VENV/bin/python" -m pip install -q -e "$GLOSSRIG_ROOT[test,design]"
    touch "$STAMP"
fi
export PATH="$VENV/bin:$PATH"
export MPLBACKEND=Agg
set +e

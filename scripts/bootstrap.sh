#!/usr/bin/env bash
# Creates (or refreshes) the project's virtual environment in .venv.
# Sourced by ./capsule-sim and ./run-tests; prints nothing when the environment is current.
#
# Finds a Python >= 3.12 (the newest Drake wheels need it), in this order:
#   $CAPSULE_PYTHON, python3.12, python3.13, python3.14, python3, then every pyenv version.
set -euo pipefail

_repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
_venv="${CAPSULE_VENV:-$_repo/.venv}"

_is_new_enough() {
    "$1" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 12) else 1)' >/dev/null 2>&1
}

_find_python() {
    local c
    for c in "${CAPSULE_PYTHON:-}" python3.12 python3.13 python3.14 python3; do
        [ -n "$c" ] || continue
        if command -v "$c" >/dev/null 2>&1 && _is_new_enough "$c"; then
            command -v "$c"; return 0
        fi
    done
    local roots=()
    command -v pyenv >/dev/null 2>&1 && roots+=("$(pyenv root)")
    roots+=("${PYENV_ROOT:-$HOME/.pyenv}")
    for root in "${roots[@]}"; do
        for c in $(ls -d "$root"/versions/3.1[2-9]*/bin/python3 2>/dev/null | sort -V); do
            if _is_new_enough "$c"; then echo "$c"; return 0; fi
        done
    done
    return 1
}

_stamp() {
    # The environment is rebuilt whenever the declared dependencies or their pins change.
    cat "$_repo/pyproject.toml" "$_repo/constraints.txt" | sha256sum | cut -d' ' -f1
}

if [ ! -x "$_venv/bin/python" ] || [ "$(cat "$_venv/.capsule-stamp" 2>/dev/null)" != "$(_stamp)" ]; then
    if ! _py="$(_find_python)"; then
        echo "capsule_drake needs Python >= 3.12 (Drake's wheels require it) and none was found." >&2
        echo "  Ubuntu 24.04: sudo apt install python3 python3-venv" >&2
        echo "  elsewhere:    pyenv install 3.12 (or any 3.12+), or set CAPSULE_PYTHON=/path/to/python3.12" >&2
        exit 1
    fi
    echo "setting up $_venv with $_py ($("$_py" -c 'import sys; print(sys.version.split()[0])'))" >&2
    if ! "$_py" -m venv --clear "$_venv" >/dev/null 2>&1 || [ ! -x "$_venv/bin/pip" ]; then
        echo "'$_py -m venv' failed: its venv/ensurepip module is missing." >&2
        echo "  Ubuntu/Debian: sudo apt install python3-venv (or python3.12-venv), then run this again." >&2
        exit 1
    fi
    "$_venv/bin/python" -m pip install -qq --upgrade pip >&2
    # The versions the suite last passed with (constraints.txt), within pyproject's ranges.
    "$_venv/bin/python" -m pip install -qq -c "$_repo/constraints.txt" -e "$_repo[test]" >&2
    # Drake's wheels use a few libraries of the host system; a minimal image may lack them.
    if ! _err="$("$_venv/bin/python" -c 'import pydrake.all' 2>&1)"; then
        echo "Drake is installed but does not load: $(echo "$_err" | tail -n 1)" >&2
        echo "  Ubuntu/Debian: sudo apt-get install --no-install-recommends libx11-6 libsm6 libglib2.0-0" >&2
        exit 1
    fi
    _stamp > "$_venv/.capsule-stamp"
fi
# glibc's per-thread cache of freed memory blocks, enlarged (more blocks, and blocks up to
# 256 kB): a simulation step allocates and frees many blocks (the contact surfaces, the
# solver's problem, Python's objects), and the default cache sends most of them back to
# the shared allocator. Measured: the Default scenario ~10 % faster (docs/results/performance.md).
# A value the user sets is kept; other C libraries ignore it.
export GLIBC_TUNABLES="${GLIBC_TUNABLES:-glibc.malloc.tcache_count=65000:glibc.malloc.tcache_max=262144}"

#!/usr/bin/env bash
# Create or update .venv: pinned wheels, cmake path fix, drift_msgs build, editable packages.
# Idempotent; each step runs only when its inputs changed (hash stamps in .venv/.drift_setup/).
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
V=$ROOT/.venv
STAMPS=$V/.drift_setup
PYTHON=${PYTHON:-python3}
PY_PACKAGES=(drift_control drift_sim drift_vehicle_bridge drift_tools)
cd "$ROOT"

log() { printf '\033[1;34m[setup]\033[0m %s\n' "$*" >&2; }
hash_files() { cat "$@" | sha256sum | cut -c1-16; }
stamp_ok() { [[ -f $STAMPS/$1 && "$(cat "$STAMPS/$1")" == "$2" ]]; }
stamp_set() { echo "$2" >"$STAMPS/$1"; }

# 1. The venv. The ROS wheels are cp311 only.
if [[ ! -x $V/bin/python ]]; then
    ver=$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
    [[ $ver == 3.11 ]] || { log "need Python 3.11 for the ROS wheels, $PYTHON is $ver (set PYTHON=...)"; exit 1; }
    log "creating .venv with $PYTHON"
    "$PYTHON" -m venv "$V"
fi
mkdir -p "$STAMPS" build
PIP=("$V/bin/python" -m pip --disable-pip-version-check)
# pip warns once per package about the site's flat file:// indexes; keep the rest of its stderr.
pip_q() { "${PIP[@]}" "$@" 2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2); }

# 2. Pinned wheels, then point the ROS cmake exports at this machine's Python and numpy headers
#    (the wheels were built in manylinux and name /opt/python/cp311-cp311/...).
h=$(hash_files requirements.txt requirements-lock.txt)
if ! stamp_ok requirements "$h"; then
    log "installing pinned requirements"
    pip_q install -q $(grep -E '^(pip|setuptools|wheel)==' requirements.txt)
    pip_q install -q -r requirements.txt -c requirements-lock.txt
    py_inc=$("$V/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
    np_inc=$("$V/bin/python" -c 'import numpy; print(numpy.get_include())')
    mapfile -t files < <(grep -rlF --include='*.cmake' /opt/python/cp311-cp311 "$V/share" "$V/lib" || true)
    if ((${#files[@]})); then
        log "patching ${#files[@]} cmake files: python include -> $py_inc, numpy include -> $np_inc"
        sed -i -E -e "s#/opt/python/cp311-cp311/[^;\"]*numpy/_core/include#$np_inc#g" \
                  -e "s#/opt/python/cp311-cp311/include/python3\.11#$py_inc#g" "${files[@]}"
    fi
    if left=$(grep -rlF --include='*.cmake' /opt/python/cp311-cp311 "$V/share" "$V/lib"); then
        log "warning: unpatched /opt/python paths remain in: $left"
    fi
    rm -f "$STAMPS/drift_msgs"    # new wheels may need a rebuild of the interfaces
    stamp_set requirements "$h"
fi

# 3. drift_msgs: plain CMake into the venv prefix, only when the interface sources changed.
h=$(hash_files src/drift_msgs/CMakeLists.txt src/drift_msgs/package.xml src/drift_msgs/msg/*.msg)
if ! stamp_ok drift_msgs "$h" || [[ ! -d $V/lib/python3.11/site-packages/drift_msgs ]]; then
    log "building drift_msgs"
    t0=$SECONDS
    cmake -S src/drift_msgs -B build/drift_msgs -DCMAKE_PREFIX_PATH="$V" -DCMAKE_INSTALL_PREFIX="$V" \
        -DPython3_EXECUTABLE="$V/bin/python" -DBUILD_TESTING=OFF >build/drift_msgs.log 2>&1 \
        && cmake --build build/drift_msgs -j"$(nproc)" >>build/drift_msgs.log 2>&1 \
        && cmake --install build/drift_msgs >>build/drift_msgs.log 2>&1 \
        || { tail -40 build/drift_msgs.log >&2; log "drift_msgs build failed, full log: build/drift_msgs.log"; exit 1; }
    log "drift_msgs built in $((SECONDS - t0)) s"
    stamp_set drift_msgs "$h"
fi

# 4. The Python packages, editable (no build isolation: setuptools comes from the pins).
pkg_files=()
for p in "${PY_PACKAGES[@]}"; do pkg_files+=(src/$p/setup.py src/$p/setup.cfg src/$p/package.xml); done
h=$(hash_files "${pkg_files[@]}")
if ! stamp_ok packages "$h"; then
    log "installing ${PY_PACKAGES[*]} (editable)"
    args=()
    for p in "${PY_PACKAGES[@]}"; do args+=(-e "src/$p"); done
    "${PIP[@]}" install -q --no-build-isolation --no-deps "${args[@]}" >build/editable.log 2>&1 \
        || { cat build/editable.log >&2; exit 1; }
    stamp_set packages "$h"
fi

# 5. The NMPC's compiled QP functions (gcc, cached in .codegen/ by a hash of the problem): built
#    here so that no node compiles for ~20 s at start-up, while a lock-step or real-time run waits.
h=$(hash_files config/nmpc.yaml config/defaults.yaml config/vehicle/*.yaml src/drift_control/drift_control/{ocp,ocp_solvers,compiled,vehicle,tyre,params,assembly}.py)
if ! stamp_ok nmpc_codegen "$h" || [[ ! -d .codegen ]]; then
    log "compiling the NMPC solver of every vehicle in config/vehicle (.codegen/)"
    t0=$SECONDS
    # one process per vehicle, as many at once as there are cores (each compiles its OCPs)
    "$V/bin/python" -c 'from drift_control.params import vehicle_names
print("\n".join(vehicle_names()))' >build/vehicles.txt \
        && xargs -P "$(nproc)" -I{} "$V/bin/python" -c 'import sys
from drift_control.assembly import load_setup
load_setup(vehicle=sys.argv[1], with_map=False).build_nmpc()' {} <build/vehicles.txt \
        || { log "NMPC solver build failed"; exit 1; }
    log "NMPC solvers compiled in $((SECONDS - t0)) s"
    stamp_set nmpc_codegen "$h"
fi

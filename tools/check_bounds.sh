#!/usr/bin/env bash
# Checks the oldest versions o3dvis supports, together: a wheel of the package installed with the
# lowest torch and Open3D that pyproject.toml allows (and the newest numpy they take), on the oldest
# supported Python, in a fresh virtual environment, smoke-tested by .ci/smoke.py. Then, for each
# further interpreter given, that the wheel installs there and its C libraries are found and load.
# Not part of .ci/run: where PyTorch's CPU index is not reached, that torch comes from PyPI as the
# CUDA build, about 3 GB to download and a 6 GB environment (8 to 9 minutes on 2 busy cores).
# Usage: bash .ci/wheel dist && bash tools/check_bounds.sh dist/o3dvis-*.whl PYTHON3.10 [PYTHON...]
set -euo pipefail
cd "$(dirname "$0")/.."
wheel=$(realpath "$1")
oldest=$2
shift 2
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# "torch>=2.3" in pyproject.toml: "torch==2.3"
pins=$(grep -oE '"(torch|open3d)>=[0-9.]+"' pyproject.toml | tr -d '"' | sed 's/>=/==/')
"$oldest" -m venv "$tmp/venv"
pip="$tmp/venv/bin/python -m pip install -q --disable-pip-version-check"
$pip "pip>=22.3"
bash .ci/torch "$tmp/venv/bin/python" "$(grep torch <<<"$pins")"
$pip $(grep -v torch <<<"$pins") "o3dvis[demo] @ file://$wheel"
cp .ci/smoke.py "$tmp/smoke.py"
(cd "$tmp" && env -i HOME="$tmp" PATH="$tmp/venv/bin" "$tmp/venv/bin/python" smoke.py)
# without torch and Open3D: import o3dvis loads neither, and warns where a library is not found
check='
import ctypes, pathlib, platform, o3dvis
libraries = sorted(pathlib.Path(o3dvis.__file__).parent.rglob("_*_*.abi3.so"))
runnable = o3dvis.clib.runnable_variants()
for library in libraries:
    if library.stem.split(".")[0].rpartition("_")[2] in runnable:
        ctypes.CDLL(str(library))
print(f"Python {platform.python_version()}: the wheel installs, {len(libraries)} C libraries found, those this CPU runs load")
'
for python in "$@"; do
    rm -rf "$tmp/bare"
    "$python" -m venv "$tmp/bare"  # with its own pip: an older one may not run on a newer Python
    "$tmp/bare/bin/python" -m pip install -q --disable-pip-version-check --no-deps "$wheel"
    (cd "$tmp" && "$tmp/bare/bin/python" -W error -c "$check")
done

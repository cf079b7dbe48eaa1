#!/usr/bin/env bash
# The wheels bench/gpu.sh needs on a device machine that reaches no package index
# (/work/.library/device/README.md): this package's dependencies that the device image lacks, at the
# versions of this checkout's venv, for the device's Python (3.12, x86-64 manylinux), into .whl/
# (ignored by git; carry it with `run(carry=[".whl", ".gl"])`). The image already has numpy, scipy,
# pandas, xarray, pillow, tqdm, msgpack, toolz, cloudpickle, psutil, pyyaml, fsspec, jinja2,
# sortedcontainers, packaging, click. pvlib (19 MB, provenance layers only) is left out so that the
# working tree, the wheels and .gl/ stay under the 64 MiB a device call carries.
#
#   bench/gpu_wheels.sh            # then: run(command="bench/gpu.sh", carry=[".whl", ".gl"], timeout_s=540)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PKGS="pyproj dask distributed zarr numcodecs donfig crc32c rioxarray rasterio affine click-plugins cligj moderngl
glcontext starlette uvicorn jsonschema referencing rpds-py jsonschema-specifications shapely cql2 dask-jobqueue
tornado tblib zict locket partd typing-extensions"
# the newest of these (numcodecs 0.16's wheel is 9 MB, 0.17's 1.4 MB); pytz and tzdata come with the image's pandas
UNPINNED=" numcodecs "
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> .git/info/exclude
mkdir -p .whl
for p in $PKGS; do
    v=""
    [[ "$UNPINNED" == *" $p "* ]] || v=$("$VENV/bin/python" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$p" 2>/dev/null || true)
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
        --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
        --platform manylinux_2_5_x86_64 -d .whl "$p${v:+==$v}"
done
# the EGL/GL loaders a bare device machine lacks (unpacked by bench/gpu.sh)
if [ ! -d .gl ] || ! compgen -G ".gl/*.deb" >/dev/null; then
    grep -qx '/.gl/' .git/info/exclude || echo /.gl/ >> .git/info/exclude
    mkdir -p .gl /tmp/amd64/partial
    o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
    apt-get $o update -qq
    (cd .gl && apt-get $o download libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 >/dev/null)
fi
du -sh .whl .gl
echo "a device call carries at most 64 MiB: the wheels, .gl/ and the working tree ($(git ls-files -z | du -ch --files0-from=- | tail -1 | cut -f1)) together"

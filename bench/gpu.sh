#!/usr/bin/env bash
# Throughput on a GPU node (issues 20 and 29), one prepared command that fits a device lease:
#
#   bench/gpu.sh                      # on a machine with an NVIDIA GPU (at most BUDGET_S, default 450 s)
#   REQUIRE_GPU=0 CUBES=4 PASSES=2 BANDS=16 bench/gpu.sh     # dry run on a CPU machine (llvmpipe)
#
# 1. sets up what it needs: EGL/GL loader packages (Debian's, or the .deb files of .gl/ unpacked, for a
#    bare device machine: /work/.library/device/README.md), the package and its dependencies (a venv
#    $VENV with `pip install -e .`, or, where no index can be reached, the wheels of .whl/ that
#    bench/gpu_wheels.sh downloads, installed into /tmp/site), then `archive doctor` (the EGL devices,
#    the renderer a worker gets and why);
# 2. simulates the paper's flight, 40 cubes of 900 samples x 1000 lines x 300 bands over 5 lawn-mower
#    passes (21 GB of BIL), into RAM ($SHM, default /dev/shm/archive-gpu; reused while complete), on
#    all the machine's cores;
# 3. renders it at 4 cm, radiance, all bands, to each of $FORMATS with $WORKERS worker processes
#    (default: the node filled, one worker per 4 cores), once per band-pass method of $BAND_PASSES
#    (cpu: numpy gather; gl: fragment passes; compute: GL compute shader), through
#    bench/stage_profile.py (the command's own code and cluster, plus its task stream and stage
#    timers); the runs go in that order and a run is skipped when the time spent plus the estimate
#    for it (the last run of the same format, else the longest run so far) would pass BUDGET_S, so
#    that the whole script fits one device call;
# 4. prints, per run, lines/s end to end (process start to exit, Python and cluster start-up
#    included) and in the graph, the split of CPU-seconds: GL (lookup, band passes or compute gather:
#    the GL thread's own CPU; the GPU's time is not CPU time), CPU gather, everything else; the
#    renderer string; what was skipped and why; and writes it all to $RESULTS.
#
# Never part of CI (.ci/run runs ./dev.sh test only). Targets (issue 29): >= 3,640 lines/s (the seed's
# laptop), goal 7,300. Settings: CUBES PASSES BANDS SAMPLES LINES GSD WORKERS FORMATS BAND_PASSES SHM VENV
# REQUIRE_GPU BUDGET_S KEEP (keep the simulated flight; default yes) RESULTS (a JSON file to write).
set -euo pipefail
cd "$(dirname "$0")/.."
T0=$(date +%s)
CUBES=${CUBES:-40}
PASSES=${PASSES:-5}
BANDS=${BANDS:-300}
SAMPLES=${SAMPLES:-900}
LINES=${LINES:-1000}
GSD=${GSD:-0.04}
CORES=$(nproc)
WORKERS=${WORKERS:-$(( CORES / 4 > 0 ? CORES / 4 : 1 ))}
FORMATS=${FORMATS:-"zarr hdr"}
BAND_PASSES=${BAND_PASSES:-"compute cpu gl"}
SHM=${SHM:-/dev/shm/archive-gpu}
VENV=${VENV:-.venv}
PY=${PYTHON:-python3}
REQUIRE_GPU=${REQUIRE_GPU:-1}
BUDGET_S=${BUDGET_S:-450}
RESULTS=${RESULTS:-$SHM/results.json}

say() { echo "[gpu.sh +$(( $(date +%s) - T0 ))s load $(cut -d' ' -f1-3 /proc/loadavg)] $*"; }

# ---- 0. the GPU ---------------------------------------------------------------------------------
if command -v nvidia-smi >/dev/null 2>&1; then
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | sed 's/^/GPU: /'
elif [ "$REQUIRE_GPU" = 1 ]; then
    echo "gpu.sh: no nvidia-smi: this is not an NVIDIA GPU machine (REQUIRE_GPU=0 for a dry run on llvmpipe)" >&2
    exit 2
fi

# ---- 1. set-up -----------------------------------------------------------------------------------
if ! ldconfig -p 2>/dev/null | grep -q 'libEGL.so.1'; then
    if compgen -G ".gl/*.deb" >/dev/null; then
        say "unpacking the EGL/GL loaders of .gl/"
        for f in .gl/*.deb; do dpkg -x "$f" /; done
        ldconfig
    else
        sudo=""
        [ "$(id -u)" -eq 0 ] || sudo="sudo"
        say "installing libegl1 libgl1 libegl-mesa0"
        $sudo apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq libegl1 libgl1 libegl-mesa0 >/dev/null
    fi
fi
nv_vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
if [ -e "$nv_vendor" ] && [ ! -e /usr/share/glvnd/egl_vendor.d/10_nvidia.json ] && [ -z "${__EGL_VENDOR_LIBRARY_FILENAMES:-}" ]; then
    export __EGL_VENDOR_LIBRARY_FILENAMES=$nv_vendor   # the driver's own folder (a container mount)
fi
if compgen -G ".whl/*.whl" >/dev/null && ! "$PY" -c "import distributed, moderngl, zarr" 2>/dev/null; then
    say "installing the wheels of .whl/ into /tmp/site (no package index here)"
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    export PYTHONPATH="/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
    PYBIN=$PY
else
    if [ ! -x "$VENV/bin/python" ]; then
        say "creating $VENV"
        "$PY" -m venv "$VENV"
        "$VENV/bin/python" -m pip install -q --upgrade pip
    fi
    "$VENV/bin/python" -c "import archive, moderngl, distributed" 2>/dev/null || "$VENV/bin/python" -m pip install -q -e .
    PYBIN=$VENV/bin/python
fi
export PYTHONUNBUFFERED=1
# what a worker here renders with, and why (exit 1: it cannot render; a dry run goes on on llvmpipe)
"$PYBIN" -m archive doctor --workers "$WORKERS" || { [ "$REQUIRE_GPU" = 1 ] && exit 1; }

# ---- 2. the flight, in RAM -------------------------------------------------------------------------
mkdir -p "$SHM"
FLIGHT="$SHM/flight_c${CUBES}_p${PASSES}_b${BANDS}_s${SAMPLES}_l${LINES}"
need_gb=$(( CUBES * SAMPLES * LINES * BANDS * 2 / 1000000000 + 1 ))
free_gb=$(df -BG --output=avail "$SHM" | tail -1 | tr -dc 0-9)
say "flight needs ~${need_gb} GB, ${free_gb} GB free in $SHM"
if [ ! -e "$FLIGHT/.bench-complete" ]; then
    rm -rf "$FLIGHT"
    say "simulating $CUBES cubes over $PASSES passes into $FLIGHT"
    "$PYBIN" - "$FLIGHT" "$CUBES" "$PASSES" "$BANDS" "$SAMPLES" "$LINES" <<'EOF'
import sys, time
from archive.simulator.command import simulate_flight
d, cubes, passes, bands, samples, lines = sys.argv[1], *map(int, sys.argv[2:])
t = time.perf_counter()
simulate_flight(d, cubes=cubes, bands=bands, samples=samples, lines=lines, cubes_per_pass=-(-cubes // passes),
                seed=1, progress=True)
open(f"{d}/.bench-complete", "w").write(f"{time.perf_counter() - t:.1f} s\n")
EOF
fi
cat "$FLIGHT"/*.bil > /dev/null   # in RAM anyway; touch every page once

# ---- 3. renders --------------------------------------------------------------------------------------
runs=()
skipped=()
declare -A last_wall=()
longest=0
render() {  # render FORMAT WORKERS BAND_PASS
    local fmt=$1 n=$2 pass=$3 out="$SHM/mosaic.$1" json="$SHM/profile_${1}_w${2}_${3}.json"
    local spent=$(( $(date +%s) - T0 )) estimate=${last_wall[$1]:-$longest}
    if [ $(( spent + estimate )) -gt "$BUDGET_S" ]; then
        say "skip .$fmt with $pass band passes: ${spent} s spent + ~${estimate} s > BUDGET_S=$BUDGET_S"
        skipped+=("$fmt/$pass: ${spent} s spent + ~${estimate} s estimated > ${BUDGET_S} s")
        return 0
    fi
    rm -rf "$out" "${out%.*}" "$out.json"
    say "render -> .$fmt, $n worker(s), band passes: $pass"
    local t0 t1
    t0=$(date +%s.%N)
    if ARCHIVE_BAND_PASS=$pass "$PYBIN" bench/stage_profile.py "$json" --workers "$n" -- "$FLIGHT" \
        --fov 47.5 --gsd "$GSD" --ground-height 80 --mode radiance --bands all --out "$out" --overwrite; then
        t1=$(date +%s.%N)
        echo "$t0 $t1" > "$json.wall"
        [ -e "$out.json" ] && "$PYBIN" -c "import json,sys; p=json.load(open(sys.argv[1]))['properties']; \
print('renderers:', p.get('archive:recipe', {}).get('renderers'))" "$out.json" || true
        runs+=("$json")
    else
        t1=$(date +%s.%N)
        skipped+=("$fmt/$pass: failed (see above)")
    fi
    local wall
    wall=$("$PYBIN" -c "import sys; print(int(float(sys.argv[2]) - float(sys.argv[1])) + 1)" "$t0" "$t1")
    last_wall[$fmt]=$wall
    [ "$wall" -gt "$longest" ] && longest=$wall
    rm -rf "$out" "${out%.*}" "$out.json"
}
for fmt in $FORMATS; do
    for pass in $BAND_PASSES; do
        render "$fmt" "$WORKERS" "$pass"
    done
done

# ---- 4. summary ----------------------------------------------------------------------------------------
printf '%s\n' "${skipped[@]}" > "$SHM/skipped.txt"
"$PYBIN" - "$FLIGHT" "$RESULTS" "$SHM/skipped.txt" "${runs[@]}" <<'EOF'
import json, os, sys
from pathlib import Path
flight, results, skipped, runs = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4:]
skipped = [s for s in skipped.read_text().splitlines() if s.strip()]
lines = 0
for hdr in sorted(flight.glob("*.bil.hdr")):
    for row in hdr.read_text().splitlines():
        if row.replace(" ", "").lower().startswith("lines="):
            lines += int(row.split("=")[1])
cubes = len(list(flight.glob("*.bil")))
gl_stages = ("GL lookup", "GL band passes", "GL compute gather")
out = []
print()
print(f"{cubes} cubes, {lines} lines ({flight}); load {os.getloadavg()}")
print("| format | workers | band passes | end to end s | lines/s end to end | graph s | lines/s in the graph | "
      "GL CPU-s (GL thread + llvmpipe) | CPU band gather CPU-s | CPU-s outside GL and gather | per cube |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for path in runs:
    p = json.loads(Path(path).read_text())
    t0, t1 = map(float, Path(path + ".wall").read_text().split())
    wall = t1 - t0
    fmt = p["render"][p["render"].index("--out") + 1].rsplit(".", 1)[1]
    workers = len(p["cpu"]["workers"])
    cpu = p["cpu"]["client"] + sum(p["cpu"]["workers"].values())
    gl = sum(p["stages"].get(k, {}).get("cpu_s", 0.0) for k in gl_stages)
    gather = p["stages"].get("CPU band gather", {}).get("cpu_s", 0.0)
    outside = cpu - gl - gather
    mode = Path(path).stem.rsplit("_", 1)[1]
    row = {"format": fmt, "workers": workers, "band_pass": mode, "wall_s": wall, "graph_s": p["graph_s"],
           "lines_per_s": lines / wall, "graph_lines_per_s": lines / p["graph_s"], "gl_cpu_s": gl,
           "gather_cpu_s": gather, "outside_gl_cpu_s": outside, "stages": p["stages"], "tasks": p["tasks"]}
    out.append(row)
    print(f"| .{fmt} | {workers} | {mode} | {wall:.1f} | {lines / wall:.0f} | {p['graph_s']:.1f} | "
          f"{lines / p['graph_s']:.0f} | {gl:.1f} | {gather:.1f} | {outside:.1f} | {outside / cubes:.2f} |")
for s in skipped:
    print(f"skipped: {s}")
results.write_text(json.dumps({"cubes": cubes, "lines": lines, "runs": out, "skipped": skipped}, indent=1))
print(f"\nper-stage CPU-s and task streams: {results}; target >= 3640 lines/s (goal 7300)")
EOF
if [ "${KEEP:-1}" != 1 ]; then rm -rf "$FLIGHT"; fi

#!/usr/bin/env bash
# Throughput on a GPU node (issue 20), one command:
#
#   bench/gpu.sh                      # on a machine with an NVIDIA GPU
#   REQUIRE_GPU=0 CUBES=4 PASSES=2 BANDS=16 bench/gpu.sh     # dry run on a CPU machine (llvmpipe)
#
# 1. sets up what it needs: Debian's EGL/GL loader packages if missing (sudo when not root), a venv
#    ($VENV, default .venv) with the package installed;
# 2. simulates the paper's flight, 40 cubes of 900 samples x 1000 lines x 300 bands over 5 lawn-mower
#    passes (21 GB of BIL), into RAM ($SHM, default /dev/shm/archive-gpu; reused while complete);
# 3. renders it at 4 cm, radiance, all bands, to ENVI and Zarr in $SHM with 1, 2 and 4 worker
#    processes (`archive render ... --workers N`, through bench/stage_profile.py: the command's own
#    code and cluster, plus its task stream and stage timers) and prints, per run, lines/s end to end
#    (process start to exit, Python and cluster start-up included) and in the graph, and the split
#    of CPU-seconds: GL (lookup and band passes: the GL thread's own CPU; the GPU's time is not CPU
#    time) against everything else (reads, mosaic, compression, writes, the command's process).
#    BAND_PASS=cpu also renders once with the CPU band gather instead of the GL band passes.
#
# Never part of CI (.ci/run runs ./dev.sh test only). Targets (issue 20): >= 3,640 lines/s (the seed's
# laptop), goal 7,300. Settings: CUBES PASSES BANDS SAMPLES LINES GSD WORKERS FORMATS SHM VENV
# REQUIRE_GPU BAND_PASS KEEP (keep the simulated flight; default yes) RESULTS (a JSON file to write).
set -euo pipefail
cd "$(dirname "$0")/.."
CUBES=${CUBES:-40}
PASSES=${PASSES:-5}
BANDS=${BANDS:-300}
SAMPLES=${SAMPLES:-900}
LINES=${LINES:-1000}
GSD=${GSD:-0.04}
WORKERS=${WORKERS:-"1 2 4"}
FORMATS=${FORMATS:-"hdr zarr"}
SHM=${SHM:-/dev/shm/archive-gpu}
VENV=${VENV:-.venv}
PY=${PYTHON:-python3}
REQUIRE_GPU=${REQUIRE_GPU:-1}
BAND_PASS=${BAND_PASS:-}
RESULTS=${RESULTS:-$SHM/results.json}

say() { echo "[gpu.sh $(date +%H:%M:%S) load $(cut -d' ' -f1-3 /proc/loadavg)] $*"; }

# ---- 0. the GPU ---------------------------------------------------------------------------------
if command -v nvidia-smi >/dev/null 2>&1; then
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | sed 's/^/GPU: /'
elif [ "$REQUIRE_GPU" = 1 ]; then
    echo "gpu.sh: no nvidia-smi: this is not an NVIDIA GPU machine (REQUIRE_GPU=0 for a dry run on llvmpipe)" >&2
    exit 2
fi

# ---- 1. set-up -----------------------------------------------------------------------------------
missing=""
if command -v dpkg-query >/dev/null 2>&1; then
    for p in libegl1 libgl1 libegl-mesa0 python3-venv; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
    done
fi
if [ -n "$missing" ]; then
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    say "installing system packages:$missing"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq $missing >/dev/null
fi
if [ ! -x "$VENV/bin/python" ]; then
    say "creating $VENV"
    "$PY" -m venv "$VENV"
    "$VENV/bin/python" -m pip install -q --upgrade pip
fi
"$VENV/bin/python" -c "import archive, moderngl, distributed" 2>/dev/null || "$VENV/bin/python" -m pip install -q -e .
"$VENV/bin/python" - <<'EOF'
from archive.render.context import gl_info
from archive.render.gather import use_cpu_gather
info = gl_info()
print(f"GL: {info['renderer']} ({info['vendor']}, {info['version']}); band passes: "
      f"{'CPU gather' if use_cpu_gather(str(info['renderer'])) else 'GL'}")
EOF

# ---- 2. the flight, in RAM -------------------------------------------------------------------------
mkdir -p "$SHM"
FLIGHT="$SHM/flight_c${CUBES}_p${PASSES}_b${BANDS}_s${SAMPLES}_l${LINES}"
need_gb=$(( CUBES * SAMPLES * LINES * BANDS * 2 / 1000000000 + 1 ))
free_gb=$(df -BG --output=avail "$SHM" | tail -1 | tr -dc 0-9)
say "flight needs ~${need_gb} GB, ${free_gb} GB free in $SHM"
if [ ! -e "$FLIGHT/.bench-complete" ]; then
    rm -rf "$FLIGHT"
    say "simulating $CUBES cubes over $PASSES passes into $FLIGHT"
    "$VENV/bin/python" - "$FLIGHT" "$CUBES" "$PASSES" "$BANDS" "$SAMPLES" "$LINES" <<'EOF'
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
render() {  # render FORMAT WORKERS BAND_PASS
    local fmt=$1 n=$2 pass=$3 out="$SHM/mosaic.$1" json="$SHM/profile_${1}_w${2}_${3}.json"
    rm -rf "$out" "${out%.*}" "$out.json"
    say "render -> .$fmt, $n worker(s), band passes: $pass"
    local t0 t1
    t0=$(date +%s.%N)
    ARCHIVE_BAND_PASS=$pass "$VENV/bin/python" bench/stage_profile.py "$json" --workers "$n" -- "$FLIGHT" \
        --fov 47.5 --gsd "$GSD" --ground-height 80 --mode radiance --bands all --out "$out" --overwrite
    t1=$(date +%s.%N)
    echo "$t0 $t1" > "$json.wall"
    rm -rf "$out" "${out%.*}" "$out.json"
    runs+=("$json")
}
for fmt in $FORMATS; do
    for n in $WORKERS; do
        render "$fmt" "$n" auto
    done
done
if [ "$BAND_PASS" = cpu ]; then
    for fmt in $FORMATS; do render "$fmt" "${WORKERS##* }" cpu; done
fi

# ---- 4. summary ----------------------------------------------------------------------------------------
"$VENV/bin/python" - "$FLIGHT" "$RESULTS" "${runs[@]}" <<'EOF'
import json, os, sys
from pathlib import Path
flight, results, runs = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:]
lines = 0
for hdr in sorted(flight.glob("*.bil.hdr")):
    for row in hdr.read_text().splitlines():
        if row.replace(" ", "").lower().startswith("lines="):
            lines += int(row.split("=")[1])
cubes = len(list(flight.glob("*.bil")))
gl_stages = ("GL lookup", "GL band passes")
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
results.write_text(json.dumps({"cubes": cubes, "lines": lines, "runs": out}, indent=1))
print(f"\nper-stage CPU-s and task streams: {results}; target >= 3640 lines/s (goal 7300)")
EOF
if [ "${KEEP:-1}" != 1 ]; then rm -rf "$FLIGHT"; fi

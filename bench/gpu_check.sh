#!/usr/bin/env bash
# One device check of the `gpu` profile (docs/PERFORMANCE.md, "A step for the GPU"), under 8 minutes on one
# H100 / H200: the step's iterations and network samples per second in its forms (eager, compiled, compiled with
# CUDA graphs; bench/gpu_step.py), then scan24_idr with `--profile gpu --set run.device=cuda` to the end, printing
# its poses, held-out PSNR (aligned) and time.
#
#   bash bench/gpu_check.sh prepare   # here, once: writes shared/gpu_check/ (about 53 MB, see below)
#   bash bench/gpu_check.sh run       # on the device, from the repo root (the device call copies the tree)
#
# What `run` expects in the copied tree (the device machine reaches nothing outside it; the tree that travels
# holds at most 64 MiB, and the tracked files are about 9 MB):
#   shared/gpu_check/scan24_idr.tar  scan24_idr's image/ as lossless WebP (about 26 MB against 34 MB of PNG;
#                                    turned back into the same PNG pixels there), mask/, cameras_sphere.npz
#   shared/gpu_check/site.tar.xz     pycolmap, zarr, numcodecs, donfig, google-crc32c, trimesh and roma, their
#                                    wheels for CPython 3.12 manylinux x86_64 unpacked (about 27 MB); the device's
#                                    image has torch, triton, OpenCV, scipy and scikit-image already
# Without the scene (or the packages) the step is still measured on the synthetic scene, which needs no data.
#
# Limits (seconds, environment): STEP_S (the step's forms, 210), TOTAL_S (the whole check, 470). The end-to-end
# run gets what is left; its iteration counts are scaled down to fit it when the measured step is too slow,
# and the scale is printed (1 = the profile's own). Results are printed and copied to $OUT (when set).
# A check of the script on a CPU: DEVICE=cpu E2E=0 EXTRA_SET="train.batch_rays=128 ..." (section.key=value
# pairs for both parts, separated by spaces) bash bench/gpu_check.sh run
set -euo pipefail

MODE="${1:-run}"
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
CARRY="$ROOT/shared/gpu_check"
WORK="${GPU_CHECK_WORK:-/tmp/gpu_check}"
T0=$(date +%s)
log() { echo "[gpu_check +$(( $(date +%s) - T0 ))s] $*"; }

if [[ "$MODE" == "prepare" ]]; then
    PY="${PY:-$ROOT/.venv/bin/python}"
    [[ -x "$PY" ]] || PY="$(command -v python3)"
    DATA="${SCAN24_IDR:-${MANIFOLDNEUS_DATA:-$ROOT/../shared/data}/dtu/scan24_idr}"
    [[ -f "$DATA/cameras_sphere.npz" ]] || { echo "no scan24_idr at $DATA (set SCAN24_IDR)" >&2; exit 2; }
    mkdir -p "$CARRY" "$WORK/prep"
    rm -rf "$WORK/prep/scan24_idr" && mkdir -p "$WORK/prep/scan24_idr/image"
    cp -r "$DATA/mask" "$DATA/cameras_sphere.npz" "$WORK/prep/scan24_idr/"
    "$PY" - "$DATA/image" "$WORK/prep/scan24_idr/image" <<'EOF'
import sys
from pathlib import Path

import cv2

src, dst = map(Path, sys.argv[1:3])
for f in sorted(src.glob("*.png")):
    img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
    ok, buf = cv2.imencode(".webp", img, [cv2.IMWRITE_WEBP_QUALITY, 101])  # 101: lossless
    assert ok and (cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) == img).all(), f
    (dst / (f.stem + ".webp")).write_bytes(buf.tobytes())
EOF
    tar -cf "$CARRY/scan24_idr.tar" -C "$WORK/prep" scan24_idr
    # the venv's versions of the packages the device's image lacks, as wheels for its Python (3.12)
    pkgs=$("$PY" -c "import importlib.metadata as m; print(' '.join(f'{p}=={m.version(p)}' for p in
           ('pycolmap', 'zarr', 'numcodecs', 'donfig', 'google-crc32c', 'trimesh', 'roma')))")
    rm -rf "$WORK/prep/wheels" "$WORK/prep/site" && mkdir -p "$WORK/prep/wheels" "$WORK/prep/site"
    # shellcheck disable=SC2086
    "$PY" -m pip download --quiet --no-deps --only-binary=:all: --python-version "${DEVICE_PY:-3.12}" \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        --dest "$WORK/prep/wheels" $pkgs
    for w in "$WORK/prep/wheels"/*.whl; do "$PY" -m zipfile -e "$w" "$WORK/prep/site"; done
    tar -cJf "$CARRY/site.tar.xz" -C "$WORK/prep/site" .
    du -shc "$CARRY"/*
    echo "carry: the device call sends shared/ with the tree; keep the whole under 64 MiB"
    exit 0
fi
[[ "$MODE" == "run" ]] || { echo "usage: bash bench/gpu_check.sh [prepare|run]" >&2; exit 2; }

STEP_S="${STEP_S:-210}"
DEVICE="${DEVICE:-cuda}"
read -r -a EXTRA <<< "${EXTRA_SET:-}"
SETS=()
for kv in "${EXTRA[@]+"${EXTRA[@]}"}"; do SETS+=(--set "$kv"); done
TOTAL_S="${TOTAL_S:-470}"
OUTDIR="${OUT:-$WORK/out}"
mkdir -p "$WORK" "$OUTDIR"
PY="${PY:-$(command -v python3)}"  # the device image's python3 holds torch
log "machine: $(nvidia-smi -L 2>/dev/null | head -1 || echo 'no nvidia-smi')"
"$PY" -c "import torch, sys; print('python', sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.cuda.is_available())"
"$PY" -c "import triton; print('triton', triton.__version__)" || log "no triton: the compiled forms fall back to eager (warned)"

export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
if ! "$PY" -c "import pycolmap, zarr, trimesh, roma" 2>/dev/null; then
    if [[ -f "$CARRY/site.tar.xz" ]]; then
        mkdir -p "$WORK/site" && tar -xJf "$CARRY/site.tar.xz" -C "$WORK/site"
        export PYTHONPATH="$PYTHONPATH:$WORK/site"  # these packages only (no numpy: --no-deps), so the image keeps its own
        log "packages from $CARRY/site.tar.xz"
    else
        log "no $CARRY/site.tar.xz: the packages of the pipeline are missing (bash bench/gpu_check.sh prepare)"
    fi
fi
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-8}"

# 1. the step, in its forms, on the synthetic scene (no data needed)
log "the gpu profile's step (timeout ${STEP_S} s)"
set +e
timeout --kill-after=10 "$STEP_S" "$PY" -m bench.gpu_step --device "$DEVICE" \
    --forms "${FORMS:-eager,default,reduce-overhead}" --seconds "${STEP_SECONDS:-12}" --warm "${WARM:-20}" \
    "${SETS[@]+"${SETS[@]}"}" \
    --json "$OUTDIR/gpu_step.json" 2>&1 | tee "$OUTDIR/gpu_step.log" \
    | grep -v "^\s*$" | tail -n 40
step_rc=${PIPESTATUS[0]}
set -e
log "step rc=$step_rc"

# 2. scan24_idr end to end
if [[ "${E2E:-1}" == 0 ]]; then
    log "E2E=0: end-to-end run skipped"
    exit "$step_rc"
fi
if [[ ! -f "$CARRY/scan24_idr.tar" ]]; then
    log "no $CARRY/scan24_idr.tar: end-to-end run skipped"
    exit "$step_rc"
fi
mkdir -p "$WORK/data/dtu"
tar -xf "$CARRY/scan24_idr.tar" -C "$WORK/data/dtu"
"$PY" - "$WORK/data/dtu/scan24_idr/image" <<'EOF'
import sys
from pathlib import Path

import cv2

for f in sorted(Path(sys.argv[1]).glob("*.webp")):  # lossless WebP back to the PNG pixels the layout reads
    cv2.imwrite(str(f.with_suffix(".png")), cv2.imread(str(f), cv2.IMREAD_UNCHANGED))
    f.unlink()
EOF
log "scan24_idr: $(ls "$WORK/data/dtu/scan24_idr/image" | wc -l) images"
export MANIFOLDNEUS_DATA="$WORK/data"
LEFT=$(( TOTAL_S - ($(date +%s) - T0) ))
# iterations of the profile's neural stages (the GT-pose reference surface is off here: a yardstick, not the run)
SCALE=$("$PY" - "$OUTDIR/gpu_step.json" "$LEFT" <<'EOF'
import json, sys
try:
    runs = {r["form"]: r for r in json.load(open(sys.argv[1]))["runs"] if "its" in r}
    its = runs.get("default", runs.get("reduce-overhead", runs.get("eager")))["its"]
except Exception:
    its = None
iters = 2000 + 2 * 1000 + 2000 + 4000  # anchors, about two rounds, the last round, the surface
budget = max(int(sys.argv[2]) - 150, 30)  # front-end, compiling per stage, evaluation and mesh: about 150 s
print(1.0 if its is None else min(1.0, round(its * budget / iters, 3)))
EOF
)
iters() { "$PY" -c "print(max(int($1 * $SCALE), 20))"; }
log "end to end, ${LEFT} s left, iteration scale $SCALE"
set +e
timeout --kill-after=10 "$(( LEFT > 60 ? LEFT - 20 : 40 ))" "$PY" pipeline.py run --scene scan24_idr --profile gpu \
    --set run.device="$DEVICE" --set run.threads=16 --set reference_surface.enabled=false "${SETS[@]+"${SETS[@]}"}" \
    --set anchors.iters="$(iters 2000)" --set successors.iters="$(iters 1000)" \
    --set successors.final_iters="$(iters 2000)" --set surface.iters="$(iters 4000)" \
    --artifacts "$WORK/art" > "$OUTDIR/e2e.log" 2>&1
e2e_rc=$?
set -e
log "end to end rc=$e2e_rc, $(( $(date +%s) - T0 )) s since the start"
tail -n 30 "$OUTDIR/e2e.log"
for stage in evaluate_poses evaluate; do
    echo "== $stage"
    "$PY" pipeline.py show --scene scan24_idr --artifacts "$WORK/art" "$stage" 2>&1 | head -n 60 || true
done
exit $(( step_rc != 0 || e2e_rc != 0 ))

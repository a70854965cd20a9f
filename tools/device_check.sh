#!/usr/bin/env bash
# The GPU check (issue 32): one script that runs every CUDA path of the project on a GPU machine and writes what it
# measured as JSON and Markdown under one folder. About 4-5 minutes on one modern GPU, bounded by --budget (8 min).
#
#   tests   pytest tests/test_device_paths.py (each check on cpu and cuda, the cuda results against the cpu's)
#   data    a small seeded Matterport-Chair dataset (2 houses x 50 frames, ~35 MB): mpchair synth + generate
#           (or --data DIR)
#   bench   detector bench --device cuda: dense / sparse / sparse+exact head at the Matterport geometry (768 x 512,
#           20 test frames) and at the KITTI geometry (the kitti_car_* configs on tests/data/kitti's frames), the
#           paper's protocol (batch 1, interleaved, 10 trials)
#   train   detector train --max-steps: steps/s and peak GPU memory of each model, fp32 and bf16 autocast
#   eval    detector eval --device cuda of the dense fp32 run's checkpoint (val split)
#   ddp     torchrun --nproc-per-node=2 detector train (nccl), when the machine has two GPUs
#   report  OUT/summary.json + OUT/summary.md (the paper's Desktop numbers beside ours)
#
# Usage: tools/device_check.sh [--out DIR] [--dry-run] [--python PY] [--data DIR] [--steps LIST] [--budget S]
#   --out DIR     results folder (default out/device_check): summary.{json,md}, results/ (one file per step),
#                 work/ (dataset, configs, training runs: scratch)
#   --dry-run     the same steps on the CPU with tiny sizes (a few frames and steps, small grids, slim layers):
#                 tests the script itself in one to two minutes on 2 cores (tests/test_device_check.py runs it)
#   --python PY   use this interpreter (it must import torch and the project's dependencies; the tree is put on
#                 PYTHONPATH) instead of bootstrapping .venv with tools/bootstrap.sh (which needs the package
#                 registries; with nvidia-smi present it installs the CUDA build of torch)
#   --data DIR    an existing Matterport-Chair dataset (KITTI layout) instead of making one
#   --steps LIST  comma-separated subset of tests,data,bench,train,eval,ddp,report (default: all)
#   --budget S    seconds for the whole check (default 480); a step that would start later is skipped, a running
#                 one is stopped at it; the report is written all the same
# Exit status: 0 when every step that ran passed, 1 otherwise (summary.json's "failed" lists them).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
OUT=$ROOT/out/device_check
DRY=0
PY=""
DATA=""
STEPS="tests,data,bench,train,eval,ddp,report"
BUDGET=480
while [ $# -gt 0 ]; do
  case "$1" in
    --out) OUT=$2; shift 2 ;;
    --dry-run) DRY=1; shift ;;
    --python) PY=$2; shift 2 ;;
    --data) DATA=$2; shift 2 ;;
    --steps) STEPS=$2; shift 2 ;;
    --budget) BUDGET=$2; shift 2 ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "error: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
START=$(date +%s)
export DEVICE_CHECK_DEADLINE=$((START + BUDGET))
# paths given relative to the caller's folder stay so; everything below runs from the repository root
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
[ -z "$DATA" ] || DATA=$(cd "$DATA" && pwd)
case "$PY" in */*) PY=$(cd "$(dirname "$PY")" && pwd)/$(basename "$PY") ;; esac
cd "$ROOT"

# --- environment: the project's .venv (bootstrapped) or the interpreter given ---------------------------------------
if [ -z "$PY" ]; then
  tools/bootstrap.sh
  PY=$ROOT/.venv/bin/python
fi
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 MPLBACKEND=Agg
RES=$OUT/results
WORK=$OUT/work
rm -rf "$RES"  # results of an earlier check would mix with this one's; work/ is kept (the dataset is reused)
mkdir -p "$RES/train" "$WORK"
DC=("$PY" "$ROOT/tools/device_check.py")

# --- sizes ---------------------------------------------------------------------------------------------------------
if [ "$DRY" = 1 ]; then
  DEVICE=cpu
  HOUSES=1 FRAMES_PER_HOUSE=12 TRAIN_STEPS=3 DDP_STEPS=2
  BENCH=(--frames 2 --trials 1 --warmup 1)
  KITTI_BENCH=(--frames 2 --trials 1 --warmup 1)
  TESTS=(-k "cpu and (voxelizer or nms)")  # the full file runs in the suite itself
  TINY=(--tiny)
else
  DEVICE=cuda
  HOUSES=2 FRAMES_PER_HOUSE=50 TRAIN_STEPS=40 DDP_STEPS=5  # 100 frames: 60 train / 20 val / 20 test
  BENCH=(--frames 20 --trials 10 --warmup 5)
  KITTI_BENCH=(--frames 6 --trials 10 --warmup 3)
  TESTS=()
  TINY=()
fi

WORKERS=$(nproc 2>/dev/null || echo 2)
[ "$WORKERS" -le 8 ] || WORKERS=8

want() { [[ ",$STEPS," == *",$1,"* ]]; }
FAILED=0
# run_step NAME [--stdout FILE] [--timeout S] -- CMD...: run and record one step (RES/steps/NAME.json); a failure
# is noted and the check goes on, so one run of a lent GPU gathers every result it can
run_step() { local name=$1; shift; "${DC[@]}" step "$name" --results "$RES" "$@" || FAILED=1; }

MACHINE=(--device "$DEVICE")
[ "$DRY" = 0 ] || MACHINE+=(--dry-run)
"${DC[@]}" machine "${MACHINE[@]}" --out "$RES/machine.json"
# only the data step runs without the device (e.g. --steps data on a CPU machine, to carry the dataset to a GPU one)
if [ "$DEVICE" = cuda ] && { want tests || want bench || want train || want eval || want ddp; } \
    && ! "$PY" -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)'; then
  echo "error: no CUDA device is visible to $PY (torch.cuda.is_available() is False); use --dry-run on a CPU" >&2
  exit 2
fi
"${DC[@]}" configs --out "$WORK/configs" "${TINY[@]}"
CFG=$WORK/configs

if want tests; then
  run_step tests --timeout 300 -- "$PY" -m pytest -q -rs -p no:cacheprovider tests/test_device_paths.py \
    --junitxml "$WORK/tests.xml" "${TESTS[@]}"
  [ -f "$WORK/tests.xml" ] && { "${DC[@]}" tests --junit "$WORK/tests.xml" --out "$RES/tests.json" || true; }
fi

if [ -z "$DATA" ]; then
  DATA=$WORK/dataset
  if want data; then
    run_step synth --timeout 120 -- "$PY" -m mpchair.cli synth --out "$WORK/houses" --houses "$HOUSES" --seed 0
    HOUSE_ARGS=()
    for h in "$WORK"/houses/v1/scans/*/; do HOUSE_ARGS+=(--house "$(basename "$h")"); done
    run_step generate --timeout 180 -- "$PY" -m mpchair.cli generate --root "$WORK/houses" "${HOUSE_ARGS[@]}" \
      --frames "$FRAMES_PER_HOUSE" --out "$DATA" --seed 0 --workers "$WORKERS" --quiet
  fi
fi

if want bench; then
  run_step bench_mpchair --timeout 240 --stdout "$RES/bench_mpchair.md" -- "$PY" -m detector bench \
    --config "$CFG/mpchair_dense.yaml" --config "$CFG/mpchair_sparse.yaml" --config "$CFG/mpchair_sparse_exact.yaml" \
    --data "$DATA" --split test "${BENCH[@]}" --device "$DEVICE" --json-out "$RES/bench_mpchair.json" --markdown \
    --no-progress
  run_step bench_kitti --timeout 180 --stdout "$RES/bench_kitti.md" -- "$PY" -m detector bench \
    --config "$CFG/kitti_car_dense.yaml" --config "$CFG/kitti_car_sparse.yaml" \
    --config "$CFG/kitti_car_sparse_exact.yaml" --data "$ROOT/tests/data/kitti" --split val "${KITTI_BENCH[@]}" \
    --device "$DEVICE" --json-out "$RES/bench_kitti.json" --markdown --no-progress
fi

if want train; then
  for model in dense sparse sparse_exact; do
    for precision in fp32 autocast; do
      run_step "train_${model}_${precision}" --timeout 150 -- "${DC[@]}" train --name "$model" \
        --config "$CFG/mpchair_$model.yaml" --data "$DATA" --run "$WORK/runs/${model}_$precision" --device "$DEVICE" \
        --precision "$precision" --steps "$TRAIN_STEPS" --out "$RES/train/${model}_$precision.json"
    done
  done
fi

if want eval; then
  run_step eval --timeout 120 --stdout "$RES/eval.json" -- "$PY" -m detector eval --config "$CFG/mpchair_dense.yaml" \
    --data "$DATA" --checkpoint "$WORK/runs/dense_fp32/last.pt" --split val --out "$WORK/eval_dense" \
    --device "$DEVICE" --json
fi

if want ddp; then
  run_step ddp --timeout 180 -- "${DC[@]}" ddp --config "$CFG/mpchair_dense.yaml" --data "$DATA" \
    --run "$WORK/runs/ddp" --device "$DEVICE" --steps "$DDP_STEPS" --out "$RES/ddp.json"
fi

if want report; then
  "${DC[@]}" report --results "$RES" --out "$OUT"
fi
echo "device check: $(( $(date +%s) - START )) s; results in $OUT"
exit "$FAILED"

#!/usr/bin/env bash
# One GPU session's work (issue 26), step by step, on a lent machine that starts bare and is given back after
# 30 s idle: every call sets up what is missing, runs its steps and leaves what must come back under $OUT.
#
#   bash benchmarks/gpu_session.sh STEP [STEP ...]      # e.g. suite command, then generate
#   GPU_SESSION_DRY=1 bash benchmarks/gpu_session.sh all   # print the commands only
#   GPU_SESSION_SECONDS=540 bash benchmarks/gpu_session.sh …   # the call's time limit (default 570 s)
#   bash benchmarks/gpu_session.sh suite+command generate   # a step 'a+b' runs a and b at the same time
#   GPU_GENERATE_ROWS=1,2,3,6,8 bash benchmarks/gpu_session.sh generate   # gpu.py --rows: those rows only
#
# 'a+b' is for steps whose figures do not matter to the other: the suite beside the paper command (its wall time
# then shares the 16 cores with the suite's processes: say so where it is reported), never beside generate.
#
# A session has 15 minutes of device time, its machine's start included: two calls. On 2026-11-26 (an H100, main
# at c5ca12e) `suite` alone (~6 min with set-up) and then `command amx generate` with GPU_GENERATE_ROWS=8 (~5 min)
# used 789 s. Next (docs/CONTRIBUTING.md, "On a lent GPU"): `gt-data gt-train`, then `gt-eval` at once; then the
# generate rows not yet run at this main. Each step runs under what is left of
# GPU_SESSION_SECONDS (then SIGINT: pytest prints its summary, gpu.py keeps the rows it wrote), so $OUT gets the
# logs and docs/benchmarks.md whatever happens.
#
# Steps, in the order of what only a GPU can show (minutes on one H100; measured there on 2026-11-26 where a
# figure says so; set-up before the first step: 82 s on a fresh H100, gsplat's extension 69-76 s of it):
#   suite      python -m pytest, the whole suite with CUDA, in 8 processes (pytest-xdist, on the GPU image;
#              without it, serially, which ran past a 10-minute command before: 95 % in 500 s), the 30 slowest
#              tests listed (~5: 2290 passed in 268 s on an H100 alone)
#   command    benchmarks/gpu.py --part command --write: the README's paper-size command end to end, as a user
#              runs it (the random paper model initialised on the GPU since main after c895c0f; on the CPU's
#              one serial random-number stream it took minutes, and the command ran past 163 s on an H100)
#              (~2: 98 s on an H100, the command 89 s of it)
#   block      benchmarks/gpu.py --part block --write: one paper-size DiT block, op by op against ours, eager and
#              compiled: what the eager step's fewer passes over its tokens buy, on this card (32 s on an H100)
#   generate   benchmarks/gpu.py --part generate --write: the paper-size rows, goal <= 30 s and <= 25 GB; the
#              table is written after every row, the rows not run kept where the device is the same (rows 1,3:
#              104 s on an H100; row 8: 99 s; rows 1,2,3,6,8: 215 s on an H200)
#   amx        benchmarks/amx_nan_check.py: the host CPU's bf16 matmul with Intel AMX and without it (oneDNN#5717),
#              and the bf16 Wan backbone test that failed on the Xeon hosts (a CPU test), twice under each
#              (~2: 91 s on an H100's host)
#   cuda       python -m pytest -m cuda: only the CUDA cases, gsplat parity and the real_gpu ones included (~2)
#   suite-1    python -m pytest on the first half of the test files (test_a… to test_pi…), serially (~5)
#   suite-2    the second half (test_pr… to test_w…): the two halves are the whole suite
#   render     benchmarks/gpu.py --part render --write (~1)
#   train      benchmarks/gpu.py --part train --write (~2)
#   gt-data    benchmarks/gpu_training.py --part data: 324 scenes on every core (~1: 1.5 CPU-s a scene here)
#   gt-train   benchmarks/gpu_training.py --part train, bf16 from the shipped weights, 6000 steps (~6-9: the small
#              stage ran 11 steps/s on an H100; the base model is smaller). At the deadline's SIGINT the trainer
#              saves the step it is at, and gt-eval (next call) evaluates every checkpoint there is
#   gt-eval    benchmarks/gpu_training.py --part eval --write: the shipped model and the 6 checkpoints, one
#              evaluation per two cores at once (~2). One session: `gt-data gt-train`, then `gt-eval`
#   motion     benchmarks/gpu_motion.py: the LDRM's motion network (train_base_motion) from the shipped weights on
#              gt-data's scenes, GPU_MOTION_STEPS steps (default 1500); the last checkpoint's weights and metrics.csv
#              to $OUT (`gpu_motion.py --out DIR --unpack DIR` makes the model folder here). One call: `gt-data motion`
#   direction  benchmarks/gpu_motion.py --stage train_base_text_mover: the DiT and text encoder on 3000 one-mover
#              scenes it makes first (~1 on 16 cores), batch 16, GPU_DIRECTION_STEPS steps (default 8000), the
#              moving cells weighted; the weights to $OUT/direction (`gpu_motion.py --stage train_base_text_mover
#              --out DIR --unpack DIR` here; then `motion_path.py --direction` on data/synth_dir14). One call
#   all        every step above, in that order
#
# Set-up on this side, once (the wheels the GPU image lacks; 22 MB; .whl is ignored, name it in `carry`):
#   echo /.whl/ >> .git/info/exclude
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
#     --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl gsplat==1.5.3 kornia kornia_rs \
#     OpenEXR plyfile diffusers==0.42.1 ftfy wcwidth importlib_metadata
# What comes back: $OUT/<step>.log for each step, and $OUT/benchmarks.md after a step that wrote tables (copy it
# over docs/benchmarks.md here before the next call: the next call's tree is this side's).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/gpu_session_out}
mkdir -p "$OUT"
DRY=${GPU_SESSION_DRY:-}
WORK=runs/gpu_training  # ignored; kept between calls on a machine that stays warm

XDIST=""  # the whole suite in 8 processes where pytest-xdist is installed (the GPU image has it)
# -rfEs: the summary lists failures, errors and skips (-rs alone would list the skips only)
python -c "import xdist" 2>/dev/null && XDIST="-n 8"
declare -A COMMANDS=(
  [suite]="python -m pytest $XDIST -rfEs -p no:cacheprovider --durations=30"
  [generate]="python benchmarks/gpu.py --part generate --write${GPU_GENERATE_ROWS:+ --rows $GPU_GENERATE_ROWS}"
  [command]="python benchmarks/gpu.py --part command --write"
  [block]="python benchmarks/gpu.py --part block --write"
  [amx]="python benchmarks/amx_nan_check.py --repeats 2"
  [cuda]="python -m pytest -m cuda -rfEs -p no:cacheprovider"
  [suite-1]="python -m pytest -rfEs -p no:cacheprovider tests/test_[a-o]*.py tests/test_p[a-i]*.py"
  [suite-2]="python -m pytest -rfEs -p no:cacheprovider tests/test_p[j-z]*.py tests/test_[q-z]*.py"
  [render]="python benchmarks/gpu.py --part render --write"
  [train]="python benchmarks/gpu.py --part train --write"
  [gt-data]="python benchmarks/gpu_training.py --part data --work $WORK"
  [gt-train]="python benchmarks/gpu_training.py --part train --work $WORK"
  [gt-eval]="python benchmarks/gpu_training.py --part eval --work $WORK --write"
  [motion]="python benchmarks/gpu_motion.py --work $WORK --out $OUT --steps ${GPU_MOTION_STEPS:-1500}"
  [direction]="python benchmarks/gpu_motion.py --stage train_base_text_mover --data $WORK/train_mover --mover-scenes 3000 --batch-size 16 --work $WORK --out $OUT/direction --steps ${GPU_DIRECTION_STEPS:-8000}"
)
ORDER=(suite command block generate amx cuda suite-1 suite-2 render train gt-data gt-train gt-eval motion direction)

steps=()
for s in "$@"; do
  if [[ $s == all ]]; then steps+=("${ORDER[@]}"); continue; fi
  IFS=+ read -ra parts <<<"$s"
  for p in "${parts[@]}"; do
    [[ -n $p && -n ${COMMANDS[$p]+x} ]] \
      || { echo "gpu_session.sh: error: unknown step '$p' in '$s' (one of: ${ORDER[*]} all; a+b: both at once)" >&2
           exit 2; }
  done
  steps+=("$s")
done
if [[ ${#steps[@]} -eq 0 ]]; then echo "gpu_session.sh: error: name at least one step (one of: ${ORDER[*]} all)" >&2; exit 2; fi

if [[ -n $DRY ]]; then
  for s in "${steps[@]}"; do IFS=+ read -ra parts <<<"$s"; for p in "${parts[@]}"; do echo "${COMMANDS[$p]}"; done; done
  exit 0
fi

# --- set-up: only what is missing (a warm machine keeps /tmp/site, the editable install and gsplat's build)
DEADLINE=$(( $(date +%s) + ${GPU_SESSION_SECONDS:-570} ))
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
if ! python -c "import gsplat, kornia, diffusers, OpenEXR, plyfile, ftfy" 2>/dev/null; then
  ls .whl/*.whl >/dev/null 2>&1 || { echo "gpu_session.sh: error: no .whl/ here: carry it (see the header)" >&2; exit 2; }
  python -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
fi
if ! python -c "import importlib.metadata as m; m.distribution('diff4splat')" 2>/dev/null; then
  python -m pip install -q -e . --no-deps --no-build-isolation || exit 1
fi
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  python -c "import torch, gsplat; print('torch', torch.__version__, 'gsplat', gsplat.__version__)"
  t0=$(date +%s)
  python -c "from diff4splat.render.rasterize import gsplat_available as g; print('gsplat CUDA extension', g())"
  echo "gsplat extension ready in $(( $(date +%s) - t0 )) s"; } 2>&1 | tee -a "$OUT/setup.log"

# --- the steps
run_step() {  # STEP SECONDS: one command under its time limit, its output in $OUT/STEP.log; returns its exit code
  local s=$1 left=$2 t0 rc
  echo "=== $s: ${COMMANDS[$s]} (at most ${left} s)" | tee -a "$OUT/$s.log"
  t0=$(date +%s)
  # OMP_NUM_THREADS: the suite's 8 processes share the 16 cores (torch would start 16 threads in each)
  local threads=()
  [[ $s == suite && -n $XDIST ]] && threads=(env OMP_NUM_THREADS=2)
  timeout --signal=INT --kill-after=20 "$left" "${threads[@]}" ${COMMANDS[$s]} 2>&1 | tee -a "$OUT/$s.log"
  rc=$?
  echo "=== $s: exit $rc after $(( $(date +%s) - t0 )) s" | tee -a "$OUT/$s.log"
  return $rc
}
status=0
docs_sum=$(md5sum docs/benchmarks.md)
for s in "${steps[@]}"; do
  left=$(( DEADLINE - $(date +%s) ))
  if (( left < 30 )); then
    echo "=== $s: not run, ${left} s left of GPU_SESSION_SECONDS" | tee -a "$OUT/${s//+/_}.log"; status=124; continue
  fi
  IFS=+ read -ra parts <<<"$s"
  pids=()
  for p in "${parts[@]}"; do run_step "$p" "$left" & pids+=($!); done
  for pid in "${pids[@]}"; do wait "$pid" || status=$?; done
  [[ $(md5sum docs/benchmarks.md) == "$docs_sum" ]] || cp docs/benchmarks.md "$OUT/benchmarks.md"
done
exit $status

#!/usr/bin/env bash
# One prepared GPU check, run from the repo root on a CUDA machine (>= 8 cores), in under 8 minutes:
#   update rates eager / torch.compile / CUDA graphs / bf16 (Dubins and Fetch sizes), a Dubins db_ags
#   run on cuda to its first full-chain success (wall time), 8 seeds at once with the hydra joblib
#   launcher sharing the GPU (total env steps/s), and the Fetch env rate.
# Prints one `name: value unit` line per figure, also into $OUT/gpu_check.txt when OUT is set.
#
#   bash benchmarks/gpu_check.sh            # on the GPU machine
#   bash benchmarks/gpu_check.sh --dry-run  # the same steps on CPU with tiny budgets (CI runs this)
#
# Set-up: the machine's own python and torch are used, never a second torch. When torchrl is
# missing, the project's other pins are installed from wheels carried in .whl/ (made here by
# `bash benchmarks/gpu_wheels.sh`, cp312 manylinux) into /tmp/site.
set -uo pipefail
cd "$(dirname "$0")/.."
DRY=0
[ "${1:-}" = "--dry-run" ] && DRY=1
PY=${PYTHON:-python3}
REPORT=/dev/null
if [ -n "${OUT:-}" ]; then REPORT="$OUT/gpu_check.txt"; : > "$REPORT"; fi
emit() { echo "$1"; echo "$1" >> "$REPORT"; }
export OMP_NUM_THREADS=1 WANDB_MODE=disabled PYTHONUNBUFFERED=1 MPLBACKEND=Agg
WORK=$(mktemp -d)

if ! $PY -c "import torchrl, srdcil" 2>/dev/null; then
  if ls .whl/*.whl >/dev/null 2>&1; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
      || { emit "setup_failed: 1 (pip install of .whl/*.whl)"; exit 1; }
    export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
  fi
fi
$PY -c "import torchrl, srdcil, hydra_plugins.hydra_joblib_launcher" 2>/dev/null \
  || { emit "setup_failed: 1 (torchrl / srdcil / joblib launcher not importable: pip install -e '.[sweep]' or carry .whl/)"; exit 1; }

if [ $DRY = 1 ]; then
  DEV=cpu; BENCH="--seconds 1 --bf16"; DUB="collector.total_frames=300 collector.init_random_frames=100"
  SEEDS=2; SWEEP="collector.total_frames=200 collector.init_random_frames=100"; FSTEPS=20; T=300
else
  DEV=cuda; BENCH="--device cuda --compile --cudagraphs --bf16 --fetch --seconds 3"
  DUB="collector.total_frames=100000"; SEEDS=8; SWEEP="collector.total_frames=20000"; FSTEPS=300; T=240
fi
emit "cpu_cores: $(nproc --all) cores"
[ $DRY = 0 ] && emit "gpu: $(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | head -1 | tr ',' ';') (name; memory)"
emit "torch_version: $($PY -c 'import torch; print(torch.__version__)') (version)"

# 1. update rates: eager / compiled / CUDA graph / bf16, Dubins and Fetch sizes
timeout $((T + 60)) $PY benchmarks/bench_updates.py $BENCH 2>/dev/null | grep -E '^[a-z_0-9]+: ' | while read -r l; do emit "$l"; done

# 2. Dubins db_ags on the device to its first full-chain success
t0=$(date +%s.%N)
timeout $T $PY recipes/sr_dcil_dubins.py method=db_ags device=$DEV stop_on_chain_success=true progress=false \
  logger.backend= eval.plot=false $DUB hydra.run.dir=$WORK/db_ags > $WORK/db_ags.log 2>&1
rc=$?
$PY - "$WORK/db_ags/result.json" "$rc" "$t0" <<'PYEOF' | while read -r l; do emit "$l"; done
import json, sys, time
path, rc, t0 = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
try:
    r = json.load(open(path))
    s = r["first_chain_success_step"]
    print(f"dubins_db_ags_first_success: {s if s is not None else 'not_reached'} env steps")
    print(f"dubins_db_ags_wall: {r['wall_s']:.1f} s")
    print(f"dubins_db_ags_env_steps_per_s: {r['env_steps_per_s']:.1f} steps/s")
except (OSError, KeyError, ValueError):
    print(f"dubins_db_ags_wall: {time.time() - t0:.1f} s (stopped, rc {rc}, no result)")
PYEOF

# 3. several seeds at once on the one device (hydra joblib launcher)
t0=$(date +%s.%N)
timeout $T $PY recipes/sr_dcil_dubins.py -m method=db_ags "seed=range(0,$SEEDS)" device=$DEV hydra/launcher=joblib \
  hydra.launcher.n_jobs=$SEEDS progress=false logger.backend= eval.plot=false $SWEEP \
  hydra.sweep.dir=$WORK/sweep > $WORK/sweep.log 2>&1
rc=$?
$PY - "$WORK/sweep" "$rc" "$t0" "$SEEDS" <<'PYEOF' | while read -r l; do emit "$l"; done
import json, pathlib, sys, time
root, rc, t0, n = pathlib.Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
wall = time.time() - t0
steps = 0
for run in root.glob("*_s*"):
    res, met = run / "result.json", run / "metrics.jsonl"
    if res.exists():
        steps += json.loads(res.read_text())["env_steps"]
    elif met.exists() and met.read_text().strip():
        steps += json.loads(met.read_text().splitlines()[-1])["env_steps"]
done = len(list(root.glob("*/result.json")))
print(f"sweep_{n}_seeds_finished: {done} runs (rc {rc})")
print(f"sweep_{n}_seeds_total_env_steps_per_s: {steps / wall:.1f} steps/s")
print(f"sweep_{n}_seeds_wall: {wall:.1f} s")
PYEOF

# 4. Fetch env rate (MuJoCo on the CPU cores)
timeout 120 $PY benchmarks/bench_fetch_env.py --steps $FSTEPS --no-parallel 2>/dev/null | grep -E '^[a-z_0-9]+: ' \
  | while read -r l; do emit "$l"; done
rm -rf "$WORK"
emit "gpu_check_done: 1 (dry run: $DRY)"

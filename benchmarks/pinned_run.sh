#!/usr/bin/env bash
# A long series of runs at a fixed commit, safe from edits to your working tree.
#
#   benchmarks/pinned_run.sh setup DIR [COMMIT] [EXTRAS]  git worktree DIR/wt at COMMIT (default HEAD), its own
#                                                     venv DIR/venv (pip install -e "DIR/wt[EXTRAS]", default
#                                                     EXTRAS=sweep), the commit in DIR/COMMIT
#   benchmarks/pinned_run.sh run DIR CMD...           run CMD in DIR/wt with DIR/venv, one torch thread, wandb off
#                                                     (relative paths in CMD are relative to DIR/wt)
#   benchmarks/pinned_run.sh queue DIR QUEUE [OVERRIDES...]  one worker (one core): run the next 'method:seed' line
#                                                     of the file QUEUE that has no result.json yet and that no other
#                                                     worker of this leg has claimed (DIR/claimed.txt) and that is
#                                                     not committed beside QUEUE (QUEUE's dir/M_sS/result.json), as
#                                                     EXPERIMENT (default dubins_ablation) of RECIPE (default
#                                                     recipes/sr_dcil_dubins.py) in DIR/results/EXPERIMENT/M_sS
#                                                     (resume=auto continues its checkpoint); then the next line.
#                                                     Start one per core; a new leg: rm DIR/claimed.txt first.
#                                                     A line 'name:seed -- CMD' runs CMD instead (a baseline),
#                                                     with {seed} and {run} (the run's directory) filled in
#   benchmarks/pinned_run.sh status DIR QUEUE         where a queue stands: each line done / started (its last
#                                                     env step) / to do, then the counts (EXPERIMENT defaults
#                                                     to NAME for a QUEUE in results/NAME/)
#   benchmarks/pinned_run.sh sync RUNS DEST           copy the small files of every run directory under RUNS
#                                                     (config, metrics, result, pictures; never checkpoints) to
#                                                     DEST/<run>, and the series' COMMIT (found in RUNS or
#                                                     up to two levels above) to DEST/SERIES_COMMIT
#
# Example (the maze ablation, two runs at a time, in the background; start the same line again to resume):
#   benchmarks/pinned_run.sh setup ~/series
#   nohup benchmarks/pinned_run.sh run ~/series python recipes/sr_dcil_dubins.py -m experiment=dubins_ablation \
#       hydra/launcher=joblib hydra.launcher.n_jobs=2 hydra.sweep.dir=$HOME/series/results/dubins_ablation > series.log 2>&1 &
#   benchmarks/pinned_run.sh sync ~/series/results/dubins_ablation results/dubins_ablation
# or, with a list of the runs still to do (lines 'db_ags:1'), one worker per core, never an idle core at the tail:
#   for i in 1 2; do nohup benchmarks/pinned_run.sh queue ~/series todo.txt > ~/series/worker$i.log 2>&1 & done
set -euo pipefail
# The whole script is one function, read in full before it runs: editing this file while a queue worker
# runs it (for hours) cannot change or break that worker.
main() {
REPO="$(cd "$(dirname "$0")/.." && pwd)"
SELF="$(cd "$(dirname "$0")" && pwd)/$(basename "$0")"
usage() { sed -n '2,33p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
[ $# -ge 2 ] || usage
cmd=$1; dir=$2; shift 2
case "$cmd" in
  setup)
    commit=$(git -C "$REPO" rev-parse --verify "${1:-HEAD}^{commit}")
    extras=${2:-sweep}
    mkdir -p "$dir"
    if [ -d "$dir/wt" ]; then
      have=$(git -C "$dir/wt" rev-parse HEAD)
      [ "$have" = "$commit" ] || { echo "$dir/wt is at $have, not $commit: use another DIR" >&2; exit 1; }
    else
      git -C "$REPO" worktree add --detach "$dir/wt" "$commit"
    fi
    if [ ! -x "$dir/venv/bin/python" ]; then
      python3 -m venv "$dir/venv"
      "$dir/venv/bin/pip" install -q torch==2.13.0
      # the tested versions where the pinned commit has them (constraints.txt), else pyproject's ranges
      cons=(); [ -f "$dir/wt/constraints.txt" ] && cons=(-c "$dir/wt/constraints.txt")
      "$dir/venv/bin/pip" install -q "${cons[@]}" -e "$dir/wt[$extras]"
    fi
    echo "$commit" > "$dir/COMMIT"
    echo "pinned at $commit: $dir/wt, venv $dir/venv" ;;
  run)
    [ $# -ge 1 ] || usage
    [ -f "$dir/COMMIT" ] || { echo "$dir is not set up: run '$0 setup $dir' first" >&2; exit 1; }
    dir=$(cd "$dir" && pwd); cd "$dir/wt"
    export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 WANDB_MODE=${WANDB_MODE:-disabled} PYTHONUNBUFFERED=1
    export PATH="$(cd "$dir" && pwd)/venv/bin:$PATH" VIRTUAL_ENV="$(cd "$dir" && pwd)/venv"
    exec "$@" ;;
  queue)
    [ $# -ge 1 ] || usage
    [ -f "$dir/COMMIT" ] || { echo "$dir is not set up: run '$0 setup $dir' first" >&2; exit 1; }
    dir=$(cd "$dir" && pwd); queue=$(cd "$(dirname "$1")" && pwd)/$(basename "$1"); shift
    exp=${EXPERIMENT:-dubins_ablation}; recipe=${RECIPE:-recipes/sr_dcil_dubins.py}
    mkdir -p "$dir/results/$exp"
    while true; do
      item=$(  # the next line with no result.json and no claim, claimed under a lock
        exec 9>"$dir/queue.lock"; flock 9
        while read -r line; do
          line=${line%%#*}; key=${line%% -- *}; key=${key//[[:space:]]/}; [ -n "$key" ] || continue
          [ -f "$dir/results/$exp/${key%:*}_s${key#*:}/result.json" ] && continue
          [ -f "$(dirname "$queue")/${key%:*}_s${key#*:}/result.json" ] && continue  # committed beside the plan
          grep -qx "$key" "$dir/claimed.txt" 2>/dev/null && continue
          echo "$key" >> "$dir/claimed.txt"; echo "$line"; break
        done < "$queue")
      [ -n "$item" ] || { echo "$(date +%T) queue done"; break; }
      key=${item%% -- *}; key=${key//[[:space:]]/}; cmd=""; [ "$key" = "${item//[[:space:]]/}" ] || cmd=${item#* -- }
      m=${key%:*}; s=${key#*:}; run="$dir/results/$exp/${m}_s$s"
      echo "$(date +%T) start $m seed $s"
      rc=0
      if [ -n "$cmd" ]; then
        cmd=${cmd//\{seed\}/$s}; cmd=${cmd//\{run\}/$run}
        bash "$SELF" run "$dir" bash -c "$cmd" > "$dir/results/$exp/${m}_s$s.log" 2>&1 || rc=$?
      else
        bash "$SELF" run "$dir" python "$recipe" "experiment=$exp" "method=$m" "seed=$s" "hydra.run.dir=$run" "$@" \
          > "$dir/results/$exp/${m}_s$s.log" 2>&1 || rc=$?
      fi
      echo "$(date +%T) end $m seed $s rc=$rc"
    done ;;
  status)
    [ $# -ge 1 ] || usage
    plan_dir=$(cd "$(dirname "$1")" && pwd)  # a plan in results/NAME/ names its experiment
    [ "$(basename "$(dirname "$plan_dir")")" = results ] && dflt=$(basename "$plan_dir") || dflt=dubins_ablation
    exp=${EXPERIMENT:-$dflt}; nd=0; ns=0; nt=0
    while read -r line; do
      line=${line%%#*}; line=${line%% -- *}; line=${line//[[:space:]]/}; [ -n "$line" ] || continue
      run="$dir/results/$exp/${line%:*}_s${line#*:}"
      if [ -f "$run/result.json" ] || [ -f "$(dirname "$1")/${line%:*}_s${line#*:}/result.json" ]; then
        echo "done     $line"; nd=$((nd + 1))
      elif [ -f "$run/metrics.jsonl" ]; then
        last=$(grep -o '"env_steps": [0-9]*' "$run/metrics.jsonl" | tail -n 1 | grep -o '[0-9]*$' || true)
        echo "started  $line (at ${last:-0} env steps)"; ns=$((ns + 1))
      else echo "to do    $line"; nt=$((nt + 1)); fi
    done < "$1"
    echo "$nd done, $ns started, $nt to do" ;;
  sync)
    [ $# -ge 1 ] || usage
    src=$dir; dest=$1; n=0; mkdir -p "$dest"
    for d in "$src"/*/; do
      [ -f "$d/config.yaml" ] || [ -f "$d/config.json" ] || [ -f "$d/metrics.jsonl" ] || continue
      name=$(basename "$d"); mkdir -p "$dest/$name"
      for f in config.yaml config.json metrics.jsonl result.json "$d"/*.png; do
        f=$(basename "$f"); [ -f "$d/$f" ] && cp "$d/$f" "$dest/$name/"
      done
      n=$((n + 1))
    done
    for c in "$src/COMMIT" "$src/../COMMIT" "$src/../../COMMIT"; do  # the series' DIR/COMMIT
      if [ -f "$c" ]; then cp "$c" "$dest/SERIES_COMMIT"; break; fi
    done
    echo "copied the small files of $n runs to $dest" ;;
  *) usage ;;
esac
}
main "$@"; exit

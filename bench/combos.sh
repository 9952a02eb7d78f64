#!/usr/bin/env bash
# The claim matrix on the other three training combinations (csr, tfr, tsw) with today's
# defaults (issue 26, item 5): the approach check, the training data replayed, the prior.
#
# Eight to ten hours on one core of the 2-core CPU, so it is written to be stopped anywhere
# and started again: every step is skipped when its output exists, collections resume, and a
# benchmark is one process per (combination, primitive, method) of ~10-15 min, so a stop
# loses at most that. Run from the repository root:
#
#   bench/combos.sh            # all of it, one thing at a time
#   bench/combos.sh csr        # only what the csr rows need
#   bench/combos.sh csr tfr & bench/combos.sh tsw   # two at once on two cores (the table
#                                                    # models are trained once, under a lock)
#
# Models and data follow REPRODUCE steps 18 / 19 (the 2026-12-03 run of these combinations):
# csr explores with the shipped cabinet models (its similarity fitted on csr), tfr and tsw with
# one table model per primitive, each combination with its own Where2Act baseline. The
# collections live apart from data/train so that the replay and the calibration read only the
# 24-interaction data of step 18, not the 96-interaction research collections.
set -euo pipefail

W2E=${W2E:-.venv/bin/w2e}
COMBOS=${*:-csr tfr tsw}
TRAIN=data/combos/train          # cfw (linked) + table / switch / refrigerator
TEST=data/combos/test            # the novel test split of cfw (linked) + cabinet / faucet / window
RUNS=runs_combo
RES=results/combos_today
SEEDS="0 1 2"
METHODS="none random similarity nosim where2act"
log() { echo "[$(date +%H:%M:%S)] $*"; }

link_files() {  # link_files SRC DST: one link per shard (pathlib's rglob skips linked folders)
  mkdir -p "$2"
  for f in "$1"/*; do ln -sfn "$(realpath "$f")" "$2/$(basename "$f")"; done
}

# 1. data [~15 min on one worker]
link_files data/train/cfw $TRAIN/cfw
link_files data/testset/novel_cfw $TEST/novel_cfw
log "collections (resume if interrupted)"
$W2E collect --out $TRAIN/tsr --categories table switch refrigerator --observations 250 --seed 0 --workers 1
$W2E collect --out data/combos/val/table_heldout --split test --categories table --observations 20 \
    --interactions 16 --seed 5 --workers 1
$W2E collect --out $TEST/cfw_cats --split test --categories cabinet faucet window --observations 20 \
    --interactions 16 --seed 1 --workers 1
VAL="data/combos/val/table_heldout $TEST/cfw_cats data/testset/novel_cfw"

resume_flag() {  # --resume when RUN has a checkpoint to go on from; else start it afresh
  if [ -f "$1/state.pt" ]; then echo --resume; else rm -rf "$1"; fi
}

# 2. models [table w2e 25-35 min, Where2Act 13-20 min each]
model() {  # model COMBO PRIM: make $RUNS/w2e_COMBO_PRIM/model.pt and the Where2Act baseline
  local c=$1 p=$2 base
  # the baseline first: it needs no table model, so a second copy of this script trains it
  # while the first holds the table model's lock
  if [ ! -f $RUNS/where2act_${c}_$p/done ]; then
    log "train the Where2Act baseline ($c, $p)"
    local resume; resume=$(resume_flag $RUNS/where2act_${c}_$p)
    $W2E train --data $TRAIN --method where2act --combo "$c" --primitive "$p" --steps 1440 --val-every 240 \
        --patience 3 --threads 1 --no-progress --val-data $VAL $resume --out $RUNS/where2act_${c}_$p
    touch $RUNS/where2act_${c}_$p/done
  fi
  if [ "$c" = csr ]; then
    base=checkpoints/w2e_cfw_$p.pt
  else
    base=runs_table/w2e_tfr_$p/model.pt
    mkdir -p runs_table
    (  # tfr and tsw share it: a second copy of this script (bench/combos.sh tfr beside
       # bench/combos.sh tsw) waits for the first's training instead of training it again
      flock 9
      if [ ! -f runs_table/w2e_tfr_$p/done ]; then
        log "train the table model ($p)"
        resume=$(resume_flag runs_table/w2e_tfr_$p)
        $W2E train --data $TRAIN/tsr --method w2e --combo tfr --primitive $p --steps 2880 \
            --val-every 240 --patience 4 --val-data data/combos/val/table_heldout --threads 1 \
            --calibrate-steps 0 --no-progress $resume --out runs_table/w2e_tfr_$p
        touch runs_table/w2e_tfr_$p/done
      fi
    ) 9>runs_table/.lock_$p
  fi
  if [ ! -f $RUNS/w2e_${c}_$p/model.pt ]; then
    log "calibrate the similarity on $c ($p)"
    mkdir -p $RUNS/w2e_${c}_$p
    $W2E calibrate --model "$base" --combo "$c" --data $TRAIN --threads 1 --out $RUNS/w2e_${c}_$p/model.pt
  fi
}

# 3. the benchmark, one process per (combination, primitive, method) [~3 min a seed]
bench() {  # bench COMBO PRIM METHOD
  local out=$RES/$1_$2_$3
  [ -f "$out/benchmark.json" ] && return 0
  log "benchmark $1 $2 $3"
  rm -rf "$out"
  $W2E benchmark --runs $RUNS --train-data $TRAIN --test-data $TEST --combos "$1" --primitives "$2" \
      --methods "$3" --seeds $SEEDS --budgets 1 2 5 --check-approach --no-heatmaps --threads 1 --out "$out"
}

for c in $COMBOS; do
  for p in pull push; do
    model "$c" "$p"
    for m in $METHODS; do bench "$c" "$p" "$m"; done
  done
done

# 4. the tables: the three combinations beside cfw (its summary of 2026-12-05; the committed
# bench/results/benchmark.json holds all four already); only the finished runs (a second copy
# of this script may still be running one)
if ls $RES/*/benchmark.json >/dev/null 2>&1; then
  $W2E benchmark --summarize-only --combos $COMBOS --budgets 1 2 5 --methods $METHODS \
      --out $RES/summary --merge $(dirname $(ls $RES/*_*_*/benchmark.json) | grep -v summary) \
      --include-summary bench/results/cfw_2026-12-05/benchmark.json
fi
log "done"

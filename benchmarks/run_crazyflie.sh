#!/usr/bin/env bash
# The paper's Crazyflie experiment (Sec. V-C, Fig. 3 right) on the real NanoBench flights.
# Train on one flight, evaluate UKF / MHE / KNODE-UKF / KNODE-MHE on all the others of the family.
# Run from the repository root:  bash benchmarks/run_crazyflie.sh [circle|figure8]   (needs ../shared/data)
set -euo pipefail
DATA=../shared/data/nanobench
OUT=benchmarks/results/crazyflie
export LEARNEST_HOME=${LEARNEST_HOME:-.learnest}
mkdir -p "$OUT"
declare -A TRAIN=([circle]=B2_circle_medium_rep2 [figure8]=B3_figure8_medium_rep2)
families=("$@")
[ ${#families[@]} -eq 0 ] && families=(circle figure8)   # "${@:-a b}" would be the one word "a b"
for name in "${families[@]}"; do
  train=${TRAIN[$name]}
  start=$(date +%s)
  .venv/bin/learnest train "$DATA/$train.csv" --name "nanobench-$name" --json > "$OUT/train_$name.json"
  .venv/bin/learnest evaluate --model "nanobench-$name" $(ls $DATA/B*_${name}_*.csv) \
      --json --plot "$OUT/boxplot_$name.png" > "$OUT/evaluate_$name.json"
  echo "$name: $(( $(date +%s) - start )) s wall ($(nproc) cores, shared with other runs), $(date -u +%FT%TZ)" >> "$OUT/wall_time.txt"
done

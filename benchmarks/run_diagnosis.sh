#!/usr/bin/env bash
# Diagnosis of the real NanoBench flights (closing the loop) and its wall time for one 40-s flight.
# Run from the repository root:  bash benchmarks/run_diagnosis.sh   (needs ../shared/data)
set -euo pipefail
DATA=../shared/data/nanobench
OUT=benchmarks/results/diagnosis
mkdir -p "$OUT"
for family in circle figure8; do
  # the first flight of the list is the one the effects are fitted on; the others are scored
  files=$(ls $DATA/B*_${family}_medium_rep2.csv; ls $DATA/B*_${family}_*.csv | grep -v medium_rep2)
  .venv/bin/learnest diagnose $files --json --plot "$OUT/diagnosis_$family.png" > "$OUT/diagnosis_$family.json"
  .venv/bin/python -c "import json, sys; from learnest.workflows.diagnosis import format_diagnosis; print(format_diagnosis(json.load(open(sys.argv[1]))))" "$OUT/diagnosis_$family.json" > "$OUT/diagnosis_$family.txt"
done
# wall time of a diagnosis of one flight (the longest NanoBench recording, ~40 s of log, ~33 s flown)
start=$(date +%s.%N)
.venv/bin/learnest diagnose "$DATA/B3_figure8_fast_rep2.csv" --json > "$OUT/diagnosis_one_flight.json"
end=$(date +%s.%N)
.venv/bin/python -c "import json, sys; from learnest.workflows.diagnosis import format_diagnosis; print(format_diagnosis(json.load(open(sys.argv[1]))))" "$OUT/diagnosis_one_flight.json" > "$OUT/diagnosis_one_flight.txt"
echo "one-flight diagnosis (B3_figure8_fast_rep2, ukf + knode-ukf before/after): $(echo "$end - $start" | bc) s wall, $(nproc) cores shared with other runs, $(date -u +%FT%TZ)" > "$OUT/wall_time.txt"

#!/usr/bin/env bash
# Train variants of the shipped 3-6 model side by side on one lent GPU, from one render of the data.
#
#   experiments/shipped_variants.sh WORK RESULTS SECONDS NETWORK [NETWORK ...]
#
# The eager training step leaves the GPU mostly idle (bench/results/cuda-step.md), so one process per network
# trains at about the rate of one alone. The data (the medium recipe with 2400 training scenes, as the shipped
# models) is rendered once into WORK/data; each network trains in WORK/<network> (links to those splits, its
# own crop cache) with its epochs fitted to what is left of SECONDS counted from the start of this script,
# minus a minute for exports and copies. RESULTS receives each network's float ONNX model (<network>.onnx)
# and logs.tgz: every run's log, metrics, fitted epochs and run.json (machine, GPU, libraries, step seconds).
# Extra arguments for experiments.shipped_models come from $SHIPPED_ARGS (default: --scenes 2400 --group 3).
set -u -o pipefail
if [ $# -lt 4 ]; then
    echo "usage: $0 WORK RESULTS SECONDS NETWORK [NETWORK ...]" >&2
    exit 2
fi
work=$1 results=$2 seconds=$3
shift 3
args=${SHIPPED_ARGS:---scenes 2400 --group 3}
start=$(date +%s)
mkdir -p "$work/data" "$results"
# shellcheck disable=SC2086  # $args is a list of options
python3 -m experiments.shipped_models --out "$work/data" $args --render-only >"$work/render.log" 2>&1 ||
    { tail -5 "$work/render.log"; exit 1; }
minutes=$(python3 -c "print(max(1.0, ($seconds - 60 - ($(date +%s) - $start))) / 60)")
echo "rendered in $(($(date +%s) - start)) s; $minutes min for each network"
pids=()
for network in "$@"; do
    mkdir -p "$work/$network"
    for split in train train_scenes test; do ln -sfn "$work/data/$split" "$work/$network/$split"; done
    # shellcheck disable=SC2086
    OMP_NUM_THREADS=2 python3 -m experiments.shipped_models --out "$work/$network" $args --network "$network" \
        --minutes "$minutes" --copy-to "$work/copy/$network" >"$work/$network.log" 2>&1 &
    pids+=($!)
done
failed=0
index=0
for network in "$@"; do
    if wait "${pids[$index]}"; then
        cp "$work/copy/$network"/population_code_*/model.onnx "$results/$network.onnx" || failed=1
        grep -E "^[0-9]+ epochs|^done" "$work/$network.log" | sed "s/^/$network: /"
    else
        failed=1
        echo "$network: failed; the end of $work/$network.log:"
        tail -3 "$work/$network.log"
    fi
    index=$((index + 1))
done
mkdir -p "$work/copy"  # a run that failed before its first export copied nothing
(cd "$work" && tar czf "$results/logs.tgz" --exclude='*.onnx' ./*.log copy) || failed=1
echo "finished in $(($(date +%s) - start)) s"
exit $failed

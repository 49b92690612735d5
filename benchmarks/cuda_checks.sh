#!/usr/bin/env bash
# Issue 13's device checks in one call, for a session that is lent a GPU for a few minutes: the CUDA tests of the
# training step, the step profile (eager against the CUDA graph) and the benches of the goals, each under a timeout so
# that the whole fits one device command (~6 minutes on an H200, session 23). Prints what it measures and copies the
# bench tables to $OUT (the device tool's output folder) when set.
#
#   bash benchmarks/cuda_checks.sh LEGO_NPZ BLENDER_LEGO_DIR
#
# LEGO_NPZ: ../shared/data/lego_200x200/lego_200x200.npz (or a copy); BLENDER_LEGO_DIR: ../shared/data/blender_lego.
# Run it where torch sees CUDA and nerfpipe is installed (pip install -e .); benchmarks/gpu_bundle.sh prepares both
# for the device tool. LEGO800=DIR (the 800² stand-in, `python -m benchmarks.lego800`) adds issue 18's benches of the
# compact field against the dense `large` one on it; ONLY800=1 runs those alone. EAGER=1 adds eager steps to the step profile and the blender bench with eager steps (--cuda-graph False).
set -o pipefail
LEGO=${1:?lego_200x200.npz}
BLENDER=${2:?blender_lego folder}
OUT=${OUT:-/tmp/nerfpipe_cuda_checks}
mkdir -p "$OUT"
KEYS="budget_s iterations val_psnr graph_captures graph_replays graph_overflows graph_slots graph_window_most graph_failed aten_ops_per_step host_syncs_per_step gpu_busy_share kernel_launches_per_step samples_per_ray peak_gpu_mb"
rows() { python3 -c "import json,sys;ks=sys.argv[2].split();[print({k:r.get(k) for k in ks}) for r in json.load(open(sys.argv[1]))['rows']]" "$1" "$KEYS"; }
bench() {  # name, timeout, then nerfpipe bench arguments
    local name=$1 limit=$2; shift 2
    echo "== bench $name"
    timeout "$limit" nerfpipe bench "$@" --out "/tmp/bench_$name" 2>&1 | grep " s: "
    cp "/tmp/bench_$name/table.md" "$OUT/bench_$name.md" 2>/dev/null && rows "/tmp/bench_$name/table.json"
}
nvidia-smi -L
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
if [ -z "${ONLY800:-}" ]; then
echo "== every CUDA test (-m requires_cuda)"
timeout 150 python3 -m pytest -q -n 8 -p no:cacheprovider -W ignore --tb=short -m requires_cuda tests >"$OUT/pytest.log" 2>&1
tail -25 "$OUT/pytest.log"
echo "== step profile: the CUDA graph with the rays cached on the device and generated per batch (EAGER=1: eager steps too)"
timeout 100 python3 -m benchmarks.step_profile "$LEGO" --device cuda --rays 4096 16384 --modes graph ${EAGER:+fixed} --cache-rays True False \
    --warm 400 --steps 50 --profiled-steps 8 2>&1 | grep "^{"
bench blender_graph 120 "$BLENDER" --presets fast --budgets 10 30 60 --eval-views 5
bench lego_graph_4096 100 "$LEGO" --presets fast-small --budgets 10 20 60 --eval-views 0 --rays-per-step 4096
[ -n "${EAGER:-}" ] && bench blender_eager 120 "$BLENDER" --presets fast --budgets 10 30 60 --eval-views 5 --cuda-graph False
fi
if [ -n "${LEGO800:-}" ]; then
    bench lego800_compact 150 "$LEGO800" --presets fast --budgets 10 30 60 --eval-views 4
    bench lego800_dense 150 "$LEGO800" --presets fast-large:sparse_min_vertices=0 --budgets 10 30 60 --eval-views 4
fi

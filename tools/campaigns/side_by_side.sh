# Several confirm.sh benches side by side on one lent machine (they share its GPUs), each in its own folder
# /tmp/NAME (kept on a warm machine, so the same call repeated resumes every run from its checkpoint) and
# with its metrics and log in $OUT/NAME.tgz (confirm.tgz and log.txt: one file per bench, since a lent
# machine sends back at most 8 files, so a call runs at most 8 benches). BENCHES lists them, ';' between
# benches, '|' between fields:
#   NAME|SCENES|SCHEDULES|METHODS|JOBS_PER_GPU|BUDGETS[|RECIPE]
# GPU_DIR (default .gpu) holds the clean bases and the LPIPS weights for every bench of the call. Run as
#   BENCHES="ref3|llff_flower llff_fern|gaussian,descending|jsgs|6|300k|{\"method_options\": \
#     {\"base_noise_ref\": 3.0}};u|llff_flower|uniform|gsplat,jsgs|3|300k" GPU_DIR=.gpu6 TL=470 \
#     bash tools/campaigns/side_by_side.sh
# and gather the folders on the CPU with tools/results/build_report.py (after
#   mkdir -p .res/NAME && tar xzf NAME.tgz -O ./confirm.tgz | tar xz -C .res/NAME).
set -u
cd "$(dirname "$0")/../.."
bash scripts/gpu_run.sh true  # the CUDA builds, once, before the benches start side by side
IFS=';' read -ra BS <<< "$BENCHES"
if [ "${#BS[@]}" -gt 8 ]; then
  echo "error: BENCHES: ${#BS[@]} benches; a call sends back at most 8 files, one per bench" >&2
  exit 2
fi
for spec in "${BS[@]}"; do
  IFS='|' read -r name scenes schedules methods jobs budgets recipe <<< "$spec"
  mkdir -p "$OUT/$name"
  OUT=$OUT/$name OUT_DIR=/tmp/$name SCENES="$scenes" SCHEDULES=$schedules METHODS=$methods JOBS=$jobs \
    BUDGETS=$budgets RECIPE="${recipe:-}" TL=${TL:-470} GPU_DIR=${GPU_DIR:-.gpu} \
    bash scripts/gpu_run.sh bash tools/campaigns/confirm.sh > "$OUT/$name/log.txt" 2>&1 &
done
wait
for spec in "${BS[@]}"; do
  name=${spec%%|*}
  echo "== $name"; grep -E "^bench:|^error:" "$OUT/$name/log.txt"
  tar czf "$OUT/$name.tgz" -C "$OUT/$name" . && rm -r "${OUT:?}/$name"
done

# Equal-budget confirmation: gsplat vs JSGS vs the clean ceiling, gsplat's MCMCStrategy, three seeds,
# evaluations every 1,000 steps, on LLFF flower and fern (SCENES: others with clean bases in
# $GPU_DIR/bench/data, made by scripts/gpu_prepare.sh). Run on a lent 2-GPU machine as
#   BUDGETS=300k SCHEDULES=uniform,gaussian,descending,clean TL=470 bash scripts/gpu_run.sh bash tools/campaigns/confirm.sh
# repeated (the bench resumes its runs from their checkpoints) until every run is complete; metrics come back
# in $OUT/confirm.tgz and tools/results/build_report.py gathers them on the CPU. JSGS trains with the mcmc
# preset's recipe (jsgs.method.recipes.RECIPES); RECIPE (JSON) goes over it and OUT_DIR names the
# bench folder. confirm/ was made with the tables' noise bound at σ_ref = 4:
#   RECIPE='{"method_options": {"lambda_obs": 1.0, "base_by_view": true, "base_noise": "tables",
#     "base_noise_ref": 4.0}}' OUT_DIR=.res/tables4 ... bash tools/campaigns/confirm.sh
set -u
B=${OUT_DIR:-.res/confirm}
mkdir -p $B/data
for s in ${SCENES:-llff_flower llff_fern}; do [ -d $B/data/$s ] || cp -r ${GPU_DIR:-.gpu}/bench/data/$s $B/data/; done
J=""
if [ -n "${RECIPE:-}" ]; then printf '%s\n' "$RECIPE" > $B/recipe.json; J="--jsgs-config $B/recipe.json"; fi
python3 -m jsgs.cli bench ${SCENES:-llff_flower llff_fern} --out $B --strategy mcmc --budgets "${BUDGETS:-300k}" \
    --iterations 10000 \
    --schedules "${SCHEDULES:-uniform,gaussian,descending,clean}" --methods "${METHODS:-gsplat,jsgs}" --seeds 0,1,2 \
    --eval-at 1000,2000,3000,4000,5000,6000,7000,8000,9000,10000 --jobs-per-gpu "${JOBS:-11}" \
    $J --time-limit "${TL:-540}" --quiet 2>&1 | tail -25
cd $B && tar czf $OUT/confirm.tgz results.csv report.md bench.json \
    $(ls runs/*/*/*/*/*/metrics.json runs/*/*/*/*/*/config.json 2>/dev/null) 2>/dev/null
ls -la $OUT

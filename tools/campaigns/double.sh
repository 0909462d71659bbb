# Photos saved twice, at equal Gaussian budget: gsplat vs JSGS with the header tables (jsgs) vs JSGS with the
# effective tables the pixels reveal (jsgs_eff), on LLFF flower and fern whose gaussian-schedule JPEG training
# views were decoded and saved once more at quality 90 (`gaussian+r90`). Run on a lent GPU machine as
#   bash scripts/gpu_run.sh bash tools/campaigns/double.sh
# with the clean bases of `scripts/gpu_prepare.sh` in .gpu; metrics come back in $OUT/double.tgz and
# `jsgs bench --report-only` rebuilds the report on the CPU.
set -u
B=.res/double
mkdir -p $B/data
for s in llff_flower llff_fern; do [ -d $B/data/$s ] || cp -r .gpu/bench/data/$s $B/data/; done
echo '{"method_options": {"lambda_obs": 1.0, "base_by_view": true, "base_noise": "tables", "base_noise_ref": 4.0}}' > .res/recipe.json
python3 -m jsgs.cli bench llff_flower llff_fern --out $B --strategy mcmc --budgets 300k --iterations 10000 \
    --schedules gaussian+r90 --methods gsplat,jsgs,jsgs_eff --seeds "${SEEDS:-0,1}" \
    --jobs-per-gpu "${JOBS:-6}" --jsgs-config .res/recipe.json --time-limit "${TL:-430}" --quiet 2>&1 | tail -12
cd $B && tar czf $OUT/double.tgz results.csv report.md bench.json \
    $(ls runs/*/*/*/*/*/metrics.json runs/*/*/*/*/*/config.json 2>/dev/null) 2>/dev/null

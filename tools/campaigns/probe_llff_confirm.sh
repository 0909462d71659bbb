# budget probe 2: cap 300k, 10k steps, mcmc preset; clean ceilings, byview variants, schedules, seed 1
# Its JSGS runs trained with the options' own values over the mcmc settings; the mcmc preset gives JSGS a recipe
# (jsgs.method.recipes.RECIPES), so to repeat them run them with --preset paper and the mcmc values
# of the mcmc preset (`jsgs.train.config.PRESETS`) in their config files.
set -u
T0=$(date +%s)
R=/tmp/probe; mkdir -p $R
for s in llff_flower llff_fern; do
  for sch in clean:0 gaussian:0 uniform:0 descending:0 gaussian:1; do
    python3 -c "from jsgstools.derive import derive; derive('.gpu/bench/data/$s/clean_s0/manifest.json', '$R/data_${s}_${sch/:/_s}', '${sch%%:*}', seed=${sch##*:})" >/dev/null
  done
done
python3 -c "from gsplat.cuda._backend import _C; print('gsplat ready', flush=True)" 2>&1 | tail -1
python3 -c "from jsgs.kernels import extension; extension(); print('jsgs kernels ready')" 2>&1 | tail -1
echo "build done at $(( $(date +%s) - T0 )) s"
EV=1000,2000,3000,4000,5000,6000,7000,8000,9000,10000
run() { # gpu scene sched tag method seed settings-json
  echo "$7" > $R/cfg_$2_$3_$4.json
  CUDA_VISIBLE_DEVICES=$1 python3 -m jsgs.cli train $R/data_$2_$3/manifest.json --out $R/run_$2_$3_$4 --method $5 \
     --preset mcmc --config $R/cfg_$2_$3_$4.json --iterations 10000 --eval-at $EV --seed $6 --quiet \
     > $R/log_$2_$3_$4.txt 2>&1 &
}
C='"strategy": {"cap_max": 300000}'
BV='"method_options": {"lambda_obs": 1.0, "base_by_view": true'
g=0
for s in llff_flower llff_fern; do
  run $g $s clean_s0 clean gsplat 42 "{$C}"
  run $g $s gaussian_s0 byview4 jsgs 42 "{$C, $BV, \"base_noise_ref\": 4.0}}"
  run $g $s gaussian_s0 byview16 jsgs 42 "{$C, $BV, \"base_noise_ref\": 16.0}}"
  run $g $s gaussian_s0 byviewo2 jsgs 42 "{$C, \"method_options\": {\"lambda_obs\": 2.0, \"base_by_view\": true}}"
  for sch in uniform_s0 descending_s0; do
    run $g $s $sch gsplat gsplat 42 "{$C}"
    run $g $s $sch byview jsgs 42 "{$C, $BV}}"
  done
  run $g $s gaussian_s1 gsplat gsplat 43 "{$C}"
  run $g $s gaussian_s1 byview jsgs 43 "{$C, $BV}}"
  g=1
done
sleep 2
echo "runs started at $(( $(date +%s) - T0 )) s: $(jobs -r | wc -l)"
while [ $(jobs -r | wc -l) -gt 0 ] && [ $(( $(date +%s) - T0 )) -lt ${DEADLINE:-555} ]; do sleep 5; done
echo "runs still going: $(jobs -r | wc -l) at $(( $(date +%s) - T0 )) s"
for f in $R/log_*.txt; do echo "$(basename $f): $(tail -c 400 $f | tr '\r' '\n' | grep -E 'complete|error|stopped' | tail -1)"; done
cd $R && tar czf $OUT/probe2.tgz run_*/metrics.json run_*/config.json log_*.txt cfg_*.json 2>/dev/null

# Where JSGS's extra time per step goes, under both strategies on one machine: profile_step.py with Chrome
# traces (Python stacks) of a 40-step window after 1,500 steps of llff_flower's gaussian schedule, then
# trace_gaps.py (device idle time attributed to the host's Python frames, JSGS against gsplat).
# STRATEGIES (default "mcmc default"), each on its own GPU in that order: mcmc, the mcmc preset (cap
# 300,000; `--preset mcmc`); default, DefaultStrategy (the config's defaults).
# Prepared on the CPU as speed_profile.sh says; run on a lent 2-GPU machine carrying .whl and .gpu4:
#   bash tools/campaigns/speed_trace.sh
# or on one GPU: STRATEGIES=mcmc bash tools/campaigns/speed_trace.sh
# Tables in $OUT/trace_{mcmc,default}.txt and gaps_{mcmc,default}.txt, numbers in trace_*.json.
set -u
P=tools/diagnostics/profile_step.py; M=.gpu4/flower_gaussian/manifest.json; T=/tmp/traces
O='{"lambda_obs":1.0,"base_by_view":true,"base_noise_ref":4.0}'
bash scripts/gpu_run.sh true
g=0
for s in ${STRATEGIES:-mcmc default}; do
  c="--preset mcmc --cap-max 300000"; [ $s = default ] && c=""
  CUDA_VISIBLE_DEVICES=$g timeout 420 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda $c \
      --jsgs-options "$O" --warmup 1500 --steps 40 --python-top 40 --trace $T/$s --out $OUT/trace_$s.json \
      > $OUT/trace_$s.txt 2>&1 &
  g=$((g + 1))
done
wait
for s in ${STRATEGIES:-mcmc default}; do
  python3 tools/diagnostics/trace_gaps.py $T/$s/gsplat.trace.json $T/$s/jsgs.trace.json --steps 40 --top 30 \
      > $OUT/gaps_$s.txt 2>&1
done
ls -la $T/* $OUT

# JSGS's step with torch.compile (inductor) of JO, L_obs and DS against the default (the graphed JO/DS, no
# compile), each beside gsplat, in one call on a lent 2-GPU machine (one GPU each), carrying .whl and .gpu4
# (made as speed_profile.sh says): llff_flower, gaussian schedule, the mcmc preset, the window after 1,500 steps.
#   bash tools/campaigns/speed_compile.sh
set -u
P=tools/diagnostics/profile_step.py; M=.gpu4/flower_gaussian/manifest.json
O='{"lambda_obs":1.0,"base_by_view":true,"base_noise":"pixels","base_noise_ref":2.0'
bash scripts/gpu_run.sh true
CUDA_VISIBLE_DEVICES=0 timeout 290 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda \
    --preset mcmc --cap-max 300000 --jsgs-options "$O,\"speed\":{\"compile\":\"inductor\"}}" --warmup 1500 --steps 50 \
    --out $OUT/compile_inductor_1500.json > $OUT/compile_inductor_1500.txt 2>&1 &
CUDA_VISIBLE_DEVICES=1 timeout 290 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda \
    --preset mcmc --cap-max 300000 --jsgs-options "$O}" --warmup 1500 --steps 50 \
    --out $OUT/compile_off_1500.json > $OUT/compile_off_1500.txt 2>&1
wait

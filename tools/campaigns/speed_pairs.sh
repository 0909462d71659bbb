# Time per step at equal budget with the protocol: gsplat against JSGS (the mcmc preset's recipe),
# windows of 50 steps resumed from one checkpoint per method, three pairs interleaved in one call
# (profile_step.py --pairs 3: gsplat, jsgs / jsgs, gsplat / gsplat, jsgs), medians and the median ratio.
# llff_flower, gaussian schedule. On the CPU first, into a carried folder (as for speed_profile.sh):
#   .venv/bin/jsgstools compress ../shared/scenes/llff_flower --out .gpu4/flower_gaussian --schedule gaussian
# then on a lent 2-GPU machine, carrying .whl and .gpu4:
#   bash tools/campaigns/speed_pairs.sh
# GPU 0: the window after 1,500 steps (about 38,000 Gaussians); GPU 1: after 6,000 (the 300,000 budget
# reached). Tables in $OUT/pairs_*.txt (the interleaved table after the profile's), numbers in pairs_*.json.
set -u
P=tools/diagnostics/profile_step.py; M=.gpu4/flower_gaussian/manifest.json
O='{"lambda_obs":1.0,"base_by_view":true,"base_noise":"pixels","base_noise_ref":2.0,"base_noise_exponent":2.0}'
bash scripts/gpu_run.sh true
CUDA_VISIBLE_DEVICES=1 timeout 560 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda \
    --preset mcmc --cap-max 300000 --jsgs-options "$O" --warmup 6000 --steps 50 --pairs 3 \
    --out $OUT/pairs_6000.json > $OUT/pairs_6000.txt 2>&1 &
CUDA_VISIBLE_DEVICES=0 timeout 400 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda \
    --preset mcmc --cap-max 300000 --jsgs-options "$O" --warmup 1500 --steps 50 --pairs 3 \
    --out $OUT/pairs_1500.json > $OUT/pairs_1500.txt 2>&1
wait

# Kernel-level profile of one window of training steps, gsplat against JSGS at equal budget (the mcmc preset;
# JSGS with the base_by_view recipe, and with the paper's weights), on llff_flower's gaussian schedule.
# On the CPU first, into a carried folder:
#   .venv/bin/jsgstools compress ../shared/scenes/llff_flower --out .gpu4/flower_gaussian --schedule gaussian
# then on a lent 2-GPU machine, carrying .whl and .gpu4:
#   bash tools/campaigns/speed_profile.sh
# GPU 1: the window after 6,000 steps (the 300,000 budget reached); GPU 0: after 1,500 steps (about 38,000
# Gaussians), with the recipe and with the paper's weights. Tables in $OUT/prof_*.txt, numbers in prof_*.json.
set -u
P=tools/diagnostics/profile_step.py; M=.gpu4/flower_gaussian/manifest.json
O='{"lambda_obs":1.0,"base_by_view":true,"base_noise_ref":4.0}'
bash scripts/gpu_run.sh true
CUDA_VISIBLE_DEVICES=1 timeout 480 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda --preset mcmc \
    --cap-max 300000 --jsgs-options "$O" --warmup 6000 --steps 50 --out $OUT/prof_6000.json > $OUT/prof_6000.txt 2>&1 &
CUDA_VISIBLE_DEVICES=0 timeout 250 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda --preset mcmc \
    --cap-max 300000 --jsgs-options "$O" --warmup 1500 --steps 50 --python-top 30 --out $OUT/prof_1500.json > $OUT/prof_1500.txt 2>&1
CUDA_VISIBLE_DEVICES=0 timeout 200 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda --preset mcmc \
    --cap-max 300000 --warmup 1500 --steps 50 --out $OUT/prof_1500_paper.json > $OUT/prof_1500_paper.txt 2>&1
wait

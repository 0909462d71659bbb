# Kernel-level profile of one window of training steps at camera resolution: gsplat against JSGS (the mcmc
# preset's recipe) on jpeg_mouse, 1440×1920 camera JPEGs, where whole runs take 1.53× gsplat's time per step
# and the extra is device work (README, Speed at equal budget). On the CPU first, into the carried folder
# that holds the capture (`tools/campaigns/real.sh` made .gpu3; `--preset mcmc` gives both methods the
# mcmc preset):
# then on a lent GPU machine (one GPU), carrying .whl and .gpu3:
#   bash tools/campaigns/speed_profile_camera.sh
# One after the other: the window after 1,500 steps, then after 4,000 (more Gaussians), 30 steps each, then
# three interleaved pairs of windows (the protocol: medians and the median ratio). Tables in
# $OUT/cam_*.txt, numbers in $OUT/cam_*.json.
set -u
P=tools/diagnostics/profile_step.py; M=.gpu3/jpeg_mouse/manifest.json
O='{"lambda_obs":1.0,"base_by_view":true,"base_noise":"pixels","base_noise_ref":2.0,"base_noise_exponent":2.0}'
export CUDA_VISIBLE_DEVICES=0
bash scripts/gpu_run.sh true
timeout 200 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda --preset mcmc --cap-max 300000 \
    --jsgs-options "$O" --warmup 1500 --steps 30 --top 25 --pairs 3 --no-fresh \
    --out $OUT/cam_1500.json > $OUT/cam_1500.txt 2>&1
timeout 300 bash scripts/gpu_run.sh python3 $P --manifest $M --device cuda --preset mcmc --cap-max 300000 \
    --jsgs-options "$O" --warmup 4000 --steps 30 --top 25 --pairs 3 --no-fresh \
    --out $OUT/cam_4000.json > $OUT/cam_4000.txt 2>&1
tail -n 4 $OUT/cam_*.txt

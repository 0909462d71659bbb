# The demo's synthetic scene with the uniform schedule (64x48, q = 10 ... 90, 1,500 CPU steps, at most 2,000
# Gaussians), three seeds: gsplat, JSGS's default recipe (k2), with k = 1 (k1), and with base_ramp_steps 750
# (r750). Two runs at a time on a 2-core CPU, about 15 minutes; logs in .res/toy/s/. Run after
# `DEMO_SCHEDULE=uniform DEMO_README=0 make demo` (the data its numbers were measured on; the demo's own
# default is every view at q = 10).
set -u
cd "$(dirname "$0")/../.."
export OMP_NUM_THREADS=1
[ -z "${JSGS_LPIPS_WEIGHTS:-}" ] && [ -f ../shared/lpips/alexnet_features.pth ] && \
    export JSGS_LPIPS_WEIGHTS=$PWD/../shared/lpips/alexnet_features.pth
T=.res/toy; mkdir -p $T/s
echo '{"strategy": {"cap_max": 2000}}' > $T/v_base.json
echo '{"strategy": {"cap_max": 2000}, "method_options": {"base_noise_exponent": 1.0}}' > $T/v_k1.json
echo '{"strategy": {"cap_max": 2000}, "method_options": {"base_ramp_steps": 750}}' > $T/v_r750.json
job() { # name method settings seed
  .venv/bin/jsgs train demo_out/data/manifest.json --out $T/s/$1_s$4 --method $2 --preset mcmc \
    --config $T/$3.json --iterations 1500 --eval-at 500,1000,1500 --device cpu --quiet --force --seed $4 \
    > $T/s/$1_s$4.log 2>&1
}
for seed in 0 1 2; do
  job gsplat gsplat v_base $seed & job k2 jsgs v_base $seed & wait
  job k1 jsgs v_k1 $seed & job r750 jsgs v_r750 $seed & wait
done
grep -H "eval @" $T/s/*.log

# The Gaussian Controller's attribution (method_options.gc_attribution): the exact probe (two extra render
# channels, the default) against the footprint estimate (no extra channels; jsgs.method.pooling.footprint_sums)
# and against no controller, for speed and for quality at equal budget.
#
# PART=toy (on the CPU, one core): the demo's synthetic scene (make demo's data: 64x48, every training view
#   at quality 10), $ITERS (1,500) steps of the mcmc preset at 2,000 Gaussians, seeds 0,1,2, JSGS with
#   gc_attribution probe, footprint and without the controller (gc false), one run at a time; logs and
#   metrics in .res/gc_attribution_toy/. About 10 minutes on one free core.
# PART=cpu_speed (on the CPU, one core): profile_step.py on its synthetic scene (160x120), gsplat against JSGS
#   with each attribution, 5 interleaved pairs of 50-step windows after 600 steps; .res/gc_attribution_cpu/.
# PART=speed (GPU): profile_step.py --pairs 6 --preset mcmc, gsplat against JSGS with each attribution (the
#   mcmc recipe's options), one job at a time on GPU 0: llff_flower (gaussian schedule) after 1,500 steps and
#   jpeg_mouse (1440x1920) after 1,500, as gc_every.sh PART=speed (carry .whl, .gpu3 and .gpu4):
#     PART=speed bash tools/campaigns/gc_attribution.sh
# PART=quality (GPU): jsgs bench --strategy mcmc on llff_flower, gaussian schedule, seeds 0,1,2, 10,000
#   steps, JSGS with gc_attribution footprint (.res/gc_attr_footprint); the probe's is gc_every.sh's K = 1
#   bench (.res/gc_every1), the same recipe:
#     PART=quality TL=540 bash scripts/gpu_run.sh bash tools/campaigns/gc_attribution.sh
#   (repeat until every run is complete; metrics come back in $OUT/gc_attr_footprint.tgz).
set -u
R='"lambda_obs":1.0,"base_by_view":true,"base_noise":"pixels","base_noise_ref":2.0,"base_noise_exponent":2.0'
PY=${PY:-.venv/bin/python}
ATTRS=${ATTRS:-probe footprint off}
if [ "${PART:-speed}" = toy ]; then
    export OMP_NUM_THREADS=1
    [ -z "${JSGS_LPIPS_WEIGHTS:-}" ] && [ -f ../shared/lpips/alexnet_features.pth ] && \
        export JSGS_LPIPS_WEIGHTS=$PWD/../shared/lpips/alexnet_features.pth
    ITERS=${ITERS:-1500}
    T=.res/gc_attribution_toy; mkdir -p $T
    for seed in ${SEEDS:-0 1 2}; do
        for a in $ATTRS; do
            if [ $a = off ]; then o='"gc": false'; else o="\"gc_attribution\": \"$a\""; fi
            echo "{\"method_options\": {$o}}" > $T/$a.json
            /usr/bin/time -f "%e s wall, %U s user" -o $T/${a}_s$seed.time \
                $PY -m jsgs.cli train demo_out/data/manifest.json --out $T/${a}_s$seed --method jsgs \
                --preset mcmc --cap-max 2000 --config $T/$a.json --iterations $ITERS \
                --eval-at $((ITERS / 2)),$ITERS --device cpu --quiet --force --seed $seed > $T/${a}_s$seed.log 2>&1
        done
    done
    grep -H "eval @ $ITERS" $T/*.log
    # per variant: the final evaluation's mean and spread over the seeds, the train time per step, the
    # controller's logged statistics and the final Gaussians' opacity and projected-size proxies
    $PY - "$T" "$ITERS" $ATTRS <<'PY'
import json, statistics as st, sys
from pathlib import Path
import torch
from jsgs.train import checkpoint as ckpt
T, iters, names = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3:]
rows = {}
for a in names:
    runs = sorted(T.glob(f"{a}_s*/metrics.json"))
    vals: dict[str, list[float]] = {}
    for m in runs:
        ev = json.loads(m.read_text())["evals"][-1]
        sp = ckpt.load_checkpoint(m.parent / "checkpoints" / f"step_{iters:06d}.pt")["splats"]
        o = torch.sigmoid(sp["opacities"])
        s = torch.exp(sp["scales"]).max(dim=-1).values
        got = {"psnr": ev["psnr"], "ssim": ev["ssim"], "lpips": ev["lpips"], "fps": ev["fps"],
               "ms_per_step": 1000 * ev["time_per_iteration_s"],
               "gc_damped": ev["train"]["stats"].get("gc_damped", 0.0),
               "opacity_mean": o.mean().item(), "opacity_gt_0.5": (o > 0.5).float().mean().item(),
               "scale_max_median": s.median().item()}
        for k, v in got.items():
            vals.setdefault(k, []).append(v)
    rows[a] = {k: {"mean": st.mean(v), "sd": st.stdev(v) if len(v) > 1 else 0.0, "runs": v}
               for k, v in vals.items()}
(T / "summary.json").write_text(json.dumps({"iterations": iters, "variants": rows}, indent=1) + "\n")
keys = ["psnr", "ssim", "lpips", "ms_per_step", "fps", "gc_damped", "opacity_mean", "opacity_gt_0.5",
        "scale_max_median"]
print("| variant | " + " | ".join(keys) + " |")
print("|---" * (len(keys) + 1) + "|")
for a, r in rows.items():
    print(f"| {a} | " + " | ".join(f"{r[k]['mean']:.4g} ± {r[k]['sd']:.2g}" for k in keys) + " |")
PY
elif [ "${PART:-speed}" = cpu_speed ]; then
    export OMP_NUM_THREADS=1
    T=.res/gc_attribution_cpu; mkdir -p $T
    for a in probe footprint; do
        $PY tools/diagnostics/profile_step.py --device cpu --threads 1 --preset mcmc --cap-max 300000 \
            --jsgs-options "{$R,\"gc_attribution\":\"$a\"}" --warmup 600 --steps 50 --pairs 5 --no-fresh \
            --out $T/cpu_$a.json > $T/cpu_$a.txt 2>&1
    done
    grep -h -A4 "each window" $T/cpu_*.txt
elif [ "${PART:-speed}" = speed ]; then
    P=tools/diagnostics/profile_step.py
    export CUDA_VISIBLE_DEVICES=0
    bash scripts/gpu_run.sh true
    for a in probe footprint; do
        for job in flower_gaussian:.gpu4:1500 jpeg_mouse:.gpu3:1500; do
            s=${job%%:*}; rest=${job#*:}; d=${rest%%:*}; w=${rest#*:}
            timeout 560 bash scripts/gpu_run.sh python3 $P --manifest $d/$s/manifest.json --device cuda \
                --preset mcmc --cap-max 300000 --jsgs-options "{$R,\"gc_attribution\":\"$a\"}" --warmup $w \
                --steps 100 \
                --pairs 6 --no-fresh --out $OUT/speed_${a}_${s}_$w.json > $OUT/speed_${a}_${s}_$w.txt 2>&1
        done
    done
    grep -h -A4 "each window" $OUT/speed_*.txt
else
    B=.res/gc_attr_footprint
    mkdir -p $B/data
    [ -d $B/data/llff_flower ] || cp -r ${GPU_DIR:-.gpu}/bench/data/llff_flower $B/data/
    printf '{"method_options": {%s, "gc_attribution": "footprint"}}\n' "$R" > $B/recipe.json
    python3 -m jsgs.cli bench llff_flower --out $B --strategy mcmc --budgets 300k --iterations 10000 \
        --schedules gaussian --methods jsgs --seeds 0,1,2 --eval-at 7000,10000 \
        --jobs-per-gpu "${JOBS:-3}" --jsgs-config $B/recipe.json --time-limit "${TL:-540}" --quiet 2>&1 | tail -8
    (cd $B && tar czf $OUT/gc_attr_footprint.tgz results.csv report.md bench.json \
        $(ls runs/*/*/*/*/*/metrics.json runs/*/*/*/*/*/config.json 2>/dev/null) 2>/dev/null)
    ls -la $OUT
fi

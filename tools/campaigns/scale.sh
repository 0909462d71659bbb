# One scene on several GPUs against one GPU (`jsgs train --gpus N`, the Gaussians sharded over the GPUs):
# throughput in training views per second and the test metrics at equal views seen, for gsplat and JSGS, on the
# mcmc preset.
#   SCENES="jpeg_mouse:300000" GPUS="1 2" bash scripts/gpu_run.sh bash tools/campaigns/scale.sh
#   SCENES="llff_flower:1000000:random" METHODS="gsplat gsplat:gsplat jsgs" bash scripts/gpu_run.sh \
#       bash tools/campaigns/scale.sh
# Each scene is name:cap_max[:random], its manifest .gpu3/<name>/manifest.json (jpeg_mouse at camera resolution:
# its manifest as `jsgstools manifest --analyze` writes it, no downscale); `random` starts from cap_max random
# Gaussians (init.type random), so the run holds cap_max Gaussians from its first step (a 1,000,000-Gaussian
# scene). METHODS (default "gsplat jsgs") picks the methods, each on the torch exchange (`speed.exchange`'s
# default); METHOD:gsplat trains METHOD with `speed.exchange: gsplat` (gsplat's distributed rasterisation
# where it renders every training view) into METHOD_gsplat, METHOD:torch names the default. GPUS (default
# "1 2"; add 4 on a machine with four GPUs: `--gpus N` takes the first N of CUDA_VISIBLE_DEVICES) picks the
# runs; ITERS (default 6000) is the one-GPU length: N GPUs run ITERS/N steps with every step-counted setting
# (the strategy's refine_*, the SH degree's interval) divided by N, as gsplat's steps_scaler, so every run
# sees ITERS views. Each run is evaluated after a fifth of its steps and at its end, so the table gives the
# views per second over the whole run and after the first evaluation (kernels loaded, collectives connected,
# memory pools grown) and the first steps' extra seconds (tools/results/scale_table.py). TL (default 560) is
# the seconds a run may take. The runs go one at a time (each uses all the GPUs it names) into
# RES/SCENE/METHOD/gN (RES: default .res/scale; one per concurrent invocation from one tree); the table covers
# every run found there, so scenes and methods can be run by separate commands. It is printed and saved as
# $OUT/scale.md; metrics, settings and logs go to $OUT/scale.tgz.
set -u
R=${RES:-.res/scale}
mkdir -p $R
ITERS=${ITERS:-6000}
for e in ${SCENES:-jpeg_mouse:300000}; do
    IFS=: read -r scene cap init <<<"$e"
    for m in ${METHODS:-gsplat jsgs}; do
        IFS=: read -r method exchange <<<"$m"
        for n in ${GPUS:-1 2}; do
            run=$R/$scene/$method${exchange:+_$exchange}/g$n
            mkdir -p "$(dirname "$run")"
            steps=$((ITERS / n))
            # the mcmc preset's step settings, divided by n
            python3 - "$n" "$cap" "${init:-sfm}" "${exchange:-}" > "$run.settings.json" <<'PY'
import json, sys
from jsgs.train.config import TrainConfig, to_dict
n, cap, init, exchange = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4] or None
d = to_dict(TrainConfig.from_preset("mcmc"))
s = d["strategy"]
out = {"strategy": {**{k: max(1, s[k] // n) for k in ("refine_start_iter", "refine_stop_iter", "refine_every")},
                    "cap_max": cap},
       "render": {"sh_degree_interval": max(1, d["render"]["sh_degree_interval"] // n)},
       "speed": {"exchange": exchange or d["speed"]["exchange"]}, "eval": {"save_renders": False}}
if init == "random":
    out["init"] = {"type": "random", "num_points": cap}
print(json.dumps(out))
PY
            timeout "${TL:-560}" python3 -m jsgs.cli train .gpu3/$scene/manifest.json --out "$run" --force \
                --method $method --config "$run.settings.json" --iterations $steps \
                --eval-at $((steps >= 10 ? steps / 5 : 1)),$steps --seed 0 --quiet --gpus "$n" >"$run.log" 2>&1
            tail -n 2 "$run.log"
        done
    done
done
mkdir -p "${OUT:-.res}" && out=$(cd "${OUT:-.res}" && pwd)
python3 tools/results/scale_table.py "$R" | tee "$out/scale.md"
cd $R && tar czf "$out/scale.tgz" */*/*/metrics.json */*/*/config.json */*/*.log */*/*.settings.json 2>/dev/null

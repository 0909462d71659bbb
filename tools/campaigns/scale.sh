# One scene on several GPUs against one GPU (`jsgs train --gpus N`, the Gaussians sharded over the GPUs):
# throughput in training views per second and the test metrics at equal views seen, for gsplat and JSGS, on the
# mcmc preset.
#   SCENES="jpeg_mouse:300000" GPUS="1 2" bash scripts/gpu_run.sh bash tools/campaigns/scale.sh
#   SCENES="llff_flower:1000000:random" METHODS=gsplat bash scripts/gpu_run.sh bash tools/campaigns/scale.sh
# Each scene is name:cap_max[:random], its manifest .gpu3/<name>/manifest.json (jpeg_mouse at camera resolution:
# its manifest as `jsgstools manifest --analyze` writes it, no downscale); `random` starts from cap_max random
# Gaussians (init.type random), so the run holds cap_max Gaussians from its first step (a 1,000,000-Gaussian
# scene). METHODS (default "gsplat jsgs") and GPUS (default "1 2"; add 4 on a machine with four GPUs) pick the
# runs; ITERS (default 6000) is the one-GPU length: N GPUs run ITERS/N steps with every step-counted setting
# (the strategy's refine_*, the SH degree's interval) divided by N, as gsplat's steps_scaler, so every run sees
# ITERS views. TL (default 560) is the seconds a run may take. The runs go one at a time (each uses all the GPUs
# it names) into .res/scale/SCENE/METHOD/gN; the summary (views/s, speed-up over one GPU, PSNR, SSIM, LPIPS,
# Gaussians, the exchange) covers every run found there, so scenes and methods can be run by separate commands.
# It is printed and saved as $OUT/scale.md; metrics, settings and logs go to $OUT/scale.tgz.
set -u
R=.res/scale
mkdir -p $R
ITERS=${ITERS:-6000}
for e in ${SCENES:-jpeg_mouse:300000}; do
    IFS=: read -r scene cap init <<<"$e"
    for method in ${METHODS:-gsplat jsgs}; do
        for n in ${GPUS:-1 2}; do
            run=$R/$scene/$method/g$n
            mkdir -p "$(dirname "$run")"
            steps=$((ITERS / n))
            # the mcmc preset's step settings, divided by n
            python3 - "$n" "$cap" "${init:-sfm}" > "$run.settings.json" <<'PY'
import json, sys
from jsgs.train.config import TrainConfig, to_dict
n, cap, init = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
d = to_dict(TrainConfig.from_preset("mcmc"))
s = d["strategy"]
out = {"strategy": {**{k: max(1, s[k] // n) for k in ("refine_start_iter", "refine_stop_iter", "refine_every")},
                    "cap_max": cap},
       "render": {"sh_degree_interval": max(1, d["render"]["sh_degree_interval"] // n)}}
if init == "random":
    out["init"] = {"type": "random", "num_points": cap}
print(json.dumps(out))
PY
            timeout "${TL:-560}" python3 -m jsgs.cli train .gpu3/$scene/manifest.json --out "$run" --force \
                --method $method --config "$run.settings.json" --iterations $steps --eval-at $steps --seed 0 \
                --quiet --gpus "$n" >"$run.log" 2>&1
            tail -n 2 "$run.log"
        done
    done
done
mkdir -p "${OUT:-.res}"
python3 - "$R" <<'PY' | tee "${OUT:-.res}/scale.md"
import json, sys
from pathlib import Path
root = Path(sys.argv[1])
print("| scene | method | GPUs | steps | views seen | views/s | speed-up | PSNR | SSIM | LPIPS | Gaussians | exchange |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|")
for scene in sorted(p for p in root.iterdir() if p.is_dir()):
    for method in sorted(p for p in scene.iterdir() if p.is_dir()):
        base = None
        for run in sorted(method.glob("g*/metrics.json"), key=lambda p: int(p.parent.name[1:])):
            m = json.loads(run.read_text())
            if m["status"] != "complete" or not m["evals"]:
                print(f"| {scene.name} | {method.name} | {run.parent.name[1:]} | {m['step']} | | {m['status']} |")
                continue
            n = m.get("world_size", 1)
            derived = json.loads((run.parent / "config.json").read_text())["derived"]
            vps = n / m["time_per_iteration_s"]
            base = vps if n == 1 else base
            e = m["evals"][-1]
            up = f"{vps / base:.2f}" if base else "n/a"
            f = lambda x, d: "n/a" if x is None else f"{x:.{d}f}"  # noqa: E731
            print(f"| {scene.name} | {method.name} | {n} | {m['step']} | {n * m['step']} | {vps:.1f} | {up} | "
                  f"{f(e['psnr'], 3)} | {f(e['ssim'], 4)} | {f(e['lpips'], 4)} | {m['num_gaussians']} | "
                  f"{derived.get('exchange', '-')} |")
PY
cd $R && tar czf "${OUT:-..}/scale.tgz" */*/*/metrics.json */*/*/config.json */*/*.log */*/*.settings.json 2>/dev/null

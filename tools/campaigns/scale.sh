# One scene on several GPUs against one GPU (`jsgs train --gpus N`): throughput in training views per second
# and the test metrics at equal views seen, for gsplat and JSGS, on the mcmc preset.
#   SCENES="jpeg_mouse:300000 llff_flower:1000000" GPUS="1 2" bash scripts/gpu_run.sh bash tools/campaigns/scale.sh
# Each scene is name:cap_max, its manifest .gpu3/<name>/manifest.json (jpeg_mouse at camera resolution: its
# manifest as `jsgstools manifest --analyze` writes it, no downscale). GPUS lists the process counts (add 4
# on a machine with four GPUs); ITERS (default 6000) is the one-GPU length: N GPUs run ITERS/N steps with every
# step-counted strategy setting divided by N (gsplat's steps_scaler), so every run sees ITERS views. TL (default
# 560) is the seconds a run may take. The runs go one at a time (each uses all the GPUs it names). Metrics,
# settings and logs come back in $OUT/scale.tgz; the summary table (views/s, speed-up, PSNR, SSIM, LPIPS,
# Gaussians) is printed and saved as $OUT/scale.md.
set -u
R=.res/scale
mkdir -p $R
ITERS=${ITERS:-6000}
for e in ${SCENES:-jpeg_mouse:300000}; do
    IFS=: read -r scene cap <<<"$e"
    for method in gsplat jsgs; do
        for n in ${GPUS:-1 2}; do
            run=$R/$scene/$method/g$n
            mkdir -p "$(dirname "$run")"
            steps=$((ITERS / n))
            # the mcmc preset's step settings, divided by n
            python3 - "$n" "$cap" > "$run.settings.json" <<'PY'
import json, sys
from jsgs.train.config import preset, to_dict
n, cap = int(sys.argv[1]), int(sys.argv[2])
s = to_dict(preset("mcmc"))["strategy"]
out = {k: max(1, s[k] // n) for k in ("refine_start_iter", "refine_stop_iter", "refine_every")}
print(json.dumps({"strategy": {**out, "cap_max": cap}}))
PY
            timeout "${TL:-560}" python3 -m jsgs.cli train .gpu3/$scene/manifest.json --out "$run" --force \
                --method $method --config "$run.settings.json" --iterations $steps --eval-at $steps --seed 0 \
                --quiet --gpus "$n" >"$run.log" 2>&1
            tail -n 2 "$run.log"
        done
    done
done
python3 - "$R" <<'PY' | tee $OUT/scale.md
import json, sys
from pathlib import Path
root = Path(sys.argv[1])
print("| scene | method | GPUs | steps | views/s | speed-up | PSNR | SSIM | LPIPS | Gaussians |")
print("|---|---|---|---|---|---|---|---|---|---|")
for scene in sorted(p for p in root.iterdir() if p.is_dir()):
    for method in sorted(p for p in scene.iterdir() if p.is_dir()):
        base = None
        for run in sorted(method.glob("g*/metrics.json"), key=lambda p: int(p.parent.name[1:])):
            m = json.loads(run.read_text())
            if m["status"] != "complete" or not m["evals"]:
                print(f"| {scene.name} | {method.name} | {run.parent.name[1:]} | {m['step']} | {m['status']} |")
                continue
            n = m.get("world_size", 1)
            vps = n / m["time_per_iteration_s"]
            base = vps if n == 1 else base
            e = m["evals"][-1]
            up = f"{vps / base:.2f}" if base else "n/a"
            f = lambda x, d: "n/a" if x is None else f"{x:.{d}f}"  # noqa: E731
            print(f"| {scene.name} | {method.name} | {n} | {m['step']} | {vps:.1f} | {up} | {f(e['psnr'], 3)} | "
                  f"{f(e['ssim'], 4)} | {f(e['lpips'], 4)} | {m['num_gaussians']} |")
PY
cd $R && tar czf $OUT/scale.tgz */*/*/metrics.json */*/*/config.json */*/*.log */*/*.settings.json 2>/dev/null

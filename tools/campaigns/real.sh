# The two JPEG-only captures as a user gets them (the authors' files, their COLMAP models; manifests written by
# `jsgstools manifest SCENE --out SCENE/manifest.json --analyze` into .gpu3/<scene>): gsplat and JSGS with
# the mcmc preset (300,000 Gaussians), test views evaluated against their JPEGs. JSGS trains at the paper's
# weights (PAPER.json below, over the preset's JSGS recipe; PAPER=0: the recipe, `jsgs train`'s default).
#   RUNS="jpeg_cup:gsplat:0 jpeg_cup:jsgs:1" bash scripts/gpu_run.sh bash tools/campaigns/real.sh
# Each entry is scene:method[+effective]:gpu; ITERS sets the steps (default 10000), TL the seconds a run may
# take (default 500): `timeout` stops a run with SIGTERM, which `jsgs train` answers with a checkpoint, and the
# same command on the still-warm machine resumes it. Metrics, settings and the first test view's last render of
# every run come back in $OUT/real.tgz.
set -u
R=.res/real
pids=()
for e in ${RUNS:-jpeg_cup:gsplat:0 jpeg_cup:jsgs:1}; do
    IFS=: read -r scene method gpu <<<"$e"
    extra=()
    [ "${method#*+}" = effective ] && extra=(--tables effective)
    m=${method%+*}
    mkdir -p $R/$scene
    again=--force
    ls $R/$scene/$method/checkpoints/*.pt >/dev/null 2>&1 && again=--resume
    [ $again = --force ] && extra+=(--cap-max 300000)  # the published runs' fixed budget; a resumed run keeps its own
    if [ "$m" = jsgs ] && [ "${PAPER:-1}" = 1 ] && [ $again = --force ]; then  # a resumed run keeps its own
        echo '{"method_options": {"lambda_obs": 0.2, "base_by_view": false}}' > $R/PAPER.json
        extra+=(--config $R/PAPER.json)
    fi
    CUDA_VISIBLE_DEVICES=$gpu timeout "${TL:-500}" python3 -m jsgs.cli train .gpu3/$scene/manifest.json --out $R/$scene/$method \
        --method "$m" "${extra[@]}" --iterations "${ITERS:-10000}" --eval-at "${EVAL_AT:-3000,7000,10000}" \
        --seed 0 --quiet $again \
        >>$R/$scene/$method.log 2>&1 &
    pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
tail -n 2 $R/*/*.log
cd $R && tar czf $OUT/real.tgz */*.log */*/metrics.json */*/config.json \
    $(for d in */*/; do s=$(ls -d "$d"renders/step_* 2>/dev/null | tail -1); [ -n "$s" ] && ls "$s"/* | head -1
      done) 2>/dev/null

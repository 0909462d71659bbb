# The operating point: gsplat's MCMC recipe at simple_trainer's length (30,000 steps) with the scene-sized
# budget (--budgets auto), on the four shared scenes, in two benches (PART):
#   time  gsplat, JSGS (the default recipe) and the clean ceiling, gaussian schedule (SCHEDULES), seeds 0,1
#         (SEEDS), JOBS (1) runs per GPU (the training seconds are compared), gsplat trained GSPLAT_STEPS (2) times
#         as long on its 30,000-step recipe so that its evaluations pass JSGS's end (the equal-time table);
#   rule  JSGS seed 0 (SEEDS) at the fixed budgets 100k, 300k and 1M (RULE_BUDGETS), gaussian schedule, JOBS (2) per
#         GPU, to set beside PART=time's auto runs (the auto rule's target).
# On a lent 2-GPU machine, with the clean bases of scripts/gpu_prepare.sh in $GPU_DIR (default .gpu) and the
# wheels in .whl (carry [".whl", ".gpu"]):
#   PART=time TL=400 bash scripts/gpu_run.sh bash tools/campaigns/operating_point.sh
# Each call is self-contained: it trains for at most TL seconds (--time-limit: no run starts that like runs
# say would not finish; runs still going are stopped at their last evaluation's checkpoint), writes the
# bench's results.csv, report.md and bench.json, and sends back $OUT/op_<PART>.tgz with those and each run's
# metrics.json and config.json (never checkpoints). Repeat the same call on the warm machine (the bench
# folder $OUT_DIR, default .res/op_<PART>, stays there) until its log says every run is complete; a run cut
# on a machine that went cold starts again. Scenes: SCENES (default all four); e.g. SCENES=llff_flower.
# ITERS and EVAL_AT replace the 30,000 steps and the bench's evaluation steps (tiny values make a CPU dry run of
# a campaign that calls this script). REPORT_ONLY=1 (on the CPU, SCENE_DIR the scenes' folders, default
# ../shared/scenes) collects the runs already in OUT_DIR into its results.csv and report.md. On the CPU:
# extract each op_<PART>.tgz into .res/op_<PART> and gather them with
#   .venv/bin/python tools/results/build_report.py docs/results/operating_point .res/op_time .res/op_rule
set -u
cd "$(dirname "$0")/../.."
P=${PART:?set PART=time or PART=rule}
B=${OUT_DIR:-.res/op_$P}
SCENES=${SCENES:-llff_flower llff_fern custom_kwrous_cup custom_myhan_mouse}
if [ -n "${REPORT_ONLY:-}" ]; then
    # on the CPU, the runs copied back into $B (of a bench cut before its report) collected into its results.csv
    # and report.md (--report-only): the scenes' folders in SCENE_DIR name them; nothing trains or is archived
    WHERE=(); for s in $SCENES; do WHERE+=("${SCENE_DIR:-../shared/scenes}/$s"); done
else
    mkdir -p "$B/data"
    for s in $SCENES; do [ -d "$B/data/$s" ] || cp -r "${GPU_DIR:-.gpu}/bench/data/$s" "$B/data/"; done
    WHERE=($SCENES)
fi
case $P in
  time) ARGS=(--budgets auto --schedules "${SCHEDULES:-gaussian,clean}" --methods gsplat,jsgs
              --seeds "${SEEDS:-0,1}" --gsplat-steps "${GSPLAT_STEPS:-2}" --jobs-per-gpu "${JOBS:-1}") ;;
  rule) ARGS=(--budgets "${RULE_BUDGETS:-100k,300k,1m}" --schedules gaussian --methods jsgs --seeds "${SEEDS:-0}"
              --jobs-per-gpu "${JOBS:-2}") ;;
  *) echo "error: PART=$P: choose time or rule" >&2; exit 2 ;;
esac
# 30,000 steps (the mcmc preset's length), evaluations at 3000, 7000, 10000, 15000, ..., 30000 (the bench's)
python3 -m jsgs.cli bench "${WHERE[@]}" --out "$B" --strategy mcmc "${ARGS[@]}" --time-limit "${TL:-400}" \
    ${ITERS:+--iterations "$ITERS"} ${EVAL_AT:+--eval-at "$EVAL_AT"} ${REPORT_ONLY:+--report-only} --quiet 2>&1 \
    | tail -30
[ -z "${REPORT_ONLY:-}" ] || exit 0
cd "$B" && tar czf "$OUT/op_$P.tgz" results.csv report.md bench.json \
    $(ls runs/*/*/*/*/*/metrics.json runs/*/*/*/*/*/config.json 2>/dev/null) 2>/dev/null
ls -la "$OUT"

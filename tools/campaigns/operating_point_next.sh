# What the operating point (docs/results/operating_point/README.md) still lacks, on one machine of 4 GPUs
# over three chained calls, in order of priority (flower's and fern's (a) benches ran, and the cup's and the
# mouse's seed 0 with A_CLEAN=1: auto30/README.md):
#   (a) the equal-time table at the retuned auto budgets (--budgets auto, 30 training pixels per Gaussian:
#       cup 222k, mouse 107k; flower 184k and fern 108k are done) for the cup and the mouse: gsplat (trained
#       GSPLAT_STEPS = 1.5 x the 30,000 steps, so the table interpolates) and JSGS (the mcmc preset's recipe,
#       gc_every 4), gaussian schedule, seeds 0 and 1 (operating_point.sh PART=time): one bench per scene and
#       seed, jobs a_<scene>_s<seed>; their clean ceilings, whose budgets did not change with the rule, are
#       the queued jobs ac_cup and ac_mouse (a_flower_s<i> and a_fern_s<i> train theirs in the bench);
#   (b) a second seed (B_SEEDS, 1) at fixed budgets, JSGS (operating_point.sh PART=rule): b_fern (100k),
#       b_mouse100 and b_mouse300 (custom_myhan_mouse), to tell the mouse's +0.0065 LPIPS miss from seed noise.
#       The fixed budgets' seed 0 trained with gc_every 1; these runs, like (a)'s, with the preset's gc_every
#       4, so the mouse's seed 1 at 100k compares with (a)'s mouse seed 1 under one recipe;
#   (c) the uniform and descending schedules: gsplat (1.5x) and JSGS at the auto budgets, c_<scene>_s<seed>.
# Each GPU is a lane, run detached (setsid) from a copy of the tree in /tmp/src, so it goes on between calls:
# first its pinned (a) benches, side by side with all their runs at once where a lane has two, so that each
# gsplat run shares its GPU with its JSGS pair the whole time (LANES, GPU:job,job):
#   GPU 0: cup s0   GPU 1: cup s1   GPU 2: mouse s0   GPU 3: mouse s1
# (2 runs per GPU; a row's runs_per_device counts its own bench's runs only), then, one at a time, the first
# job of QUEUE (ac_cup ac_mouse b_fern b_mouse100 b_mouse300, then c_* seed 0, then 1) whose estimate fits before
# STOP_AT (1200), the seconds after PHASE 1 began at which every bench stops (--time-limit: runs still going
# stop at their last evaluation, which comes back), once its data has come. A lane ends when none fits.
# What fits: a GPU trains about 230 steps/s of flower, 245 of fern, 155 of the mouse and 140 of the cup,
# however many runs share it (the H100/H200 runs in docs/results/operating_point, 2 to 5 per GPU, at the
# earlier rule's larger flower and fern budgets); on 2 H200s with 6 runs per GPU, flower's and fern's (a)
# benches (about 890 s a GPU by these rates) took 711-719 s. With the lanes starting about 110 s after PHASE 1
# began: the mouse's benches end near 600 s and take ac_cup and ac_mouse, the cup's near 650 s and take b_fern
# and b_mouse100; b_mouse300 and (c) do not fit. The lanes end about 1,000 s after PHASE 1 began, about 20-21
# minutes of device time with the machine's start and the last call (STOP_AT caps it at about 23). The rest
# needs a machine of its own, with LANES="0: 1: 2: 3:" (no pinned jobs): QUEUE="b_mouse300 c_fern_s0
# c_flower_s0 c_mouse_s0 c_cup_s0" STOP_AT=1250 (about 23 minutes).
#
# THE RUN, step by step (about 21 minutes of a session's 30, 23 at most; every call timeout_s 600; the machine
# goes back after 30 s idle, and the lanes with it, so each call starts right after the last one's reply):
#   0. On the CPU, in /work/main (the checkout the device tool sends; `git status --porcelain` prints nothing),
#      check that each call's tree and carries stay under 64 MiB (67,108,864 bytes):
#        t=$(git ls-files -z | xargs -0 du -cb | tail -1 | cut -f1); du -sb .whl .gpuOP3 .gpuOP4
#      the first call = t + .whl + .gpuOP3, the second = t + .gpuOP4. Measured: t 27,505,816, .whl
#      7,030,231, .gpuOP3 29,725,804 (the cup, the mouse, the LPIPS weights), .gpuOP4 22,954,072 (fern,
#      flower): 64,261,851 (61.3 MiB) and 50,459,888 (48.1 MiB), so the tree may grow by 2.8 MB at most.
#      Should the folders be missing (they are made from ../shared; or copied from .gpuOP1 and .gpuOP2):
#        bash scripts/gpu_prepare.sh      # the wheels in .whl
#        GPU_DIR=.gpuOP3 GPU_SCENES="custom_kwrous_cup custom_myhan_mouse" bash scripts/gpu_prepare.sh
#        GPU_DIR=.gpuOP4 GPU_SCENES="llff_fern llff_flower" bash scripts/gpu_prepare.sh && \
#            rm .gpuOP4/alexnet_features.pth
#   1. run kind nvidia-h100-x4, carry [".whl", ".gpuOP3"]: PHASE=1 bash tools/campaigns/operating_point_next.sh
#      (copies the tree and the data, builds, ~110 s, starts the lanes: its reply shows lanes.log with the
#      "start a_cup_s<i>/a_mouse_s<i>" lines; "build failed" there: give the machine back, build.log says why)
#   2. run, carry [".gpuOP4"]: PHASE=2 bash tools/campaigns/operating_point_next.sh (its data, then 480 s)
#   3. run: PHASE=3 bash tools/campaigns/operating_point_next.sh  (waits up to 540 s, until every lane is done)
#      and again while its status.txt says "lanes done: k of 4" with k < 4 (the stop, STOP_AT, is 20 minutes
#      after PHASE 1 began); then give_back.
#   After each reply, copy its archive at once: cp <files_at>/opn_<PHASE>.tgz /work/main/.res/ (the last
#   call's holds every bench as it stood, and thumbs/<job>/: each ended bench's test renders at its runs' first
#   and last evaluation, 1/4 size, tools/results/thumbs.py). A call answered "error: no lanes on this machine" got a fresh
#   machine (the last one went back): start again at 1 only if 23 minutes are left, else gather what came.
#   Fewer GPUs lent (a refusal of nvidia-h100-x4): nvidia-h100-x2 (or nvidia-h200-x2) with, at step 1,
#   LANES="0:a_cup_s0,a_mouse_s0 1:a_cup_s1,a_mouse_s1" STOP_AT=1300 PHASE=1 ... (the cup and the mouse, both
#   seeds, 4 runs per GPU, about 1,030 s a GPU by the rates above, so the lanes end 950-1,150 s after PHASE 1
#   began and nothing queued fits: the same three calls, the second may carry nothing, about 21-24 minutes);
#   one GPU: LANES="0:a_cup_s0,a_mouse_s0" (seed 0).
#   A shorter call (about 15 minutes: one seed, each bench with its clean ceiling in it, nothing queued):
#   A_CLEAN=1 LANES="0:a_cup_s0 1:a_mouse_s0" QUEUE="" STOP_AT=1000 (A_CLEAN: a_cup_s<i>/a_mouse_s<i> train the
#   clean schedule at the seed beside gsplat and JSGS, 3 runs on the GPU, as flower's and fern's benches do).
#   4. On the CPU, in /work/main:
#        ARCHIVE=.res/opn_3.tgz GATHER=.res/opn2 PHASE=gather bash tools/campaigns/operating_point_next.sh
#      puts each bench in GATHER/<job> (a new folder), collects the runs of a bench that the calls ended
#      before its report (operating_point.sh REPORT_ONLY=1, the scenes from ../shared/scenes), and adds them to
#      docs/results/operating_point/auto30 (TARGET) with tools/results/build_report.py (add STEP=auto where runs
#      stopped early: each scene at its last common evaluation): results.csv (budget column `auto`), report.md
#      (the equal-time table; its header names the auto budgets, the rule's 30 pixels per Gaussian and
#      gc_every; "Per test view"), configs.json, views.json, plots/. Then update auto30/README.md (its
#      `**Status: ...**` line, the targets over the scenes that ran, how the GPUs were shared: a row's
#      runs_per_device counts its own bench's).
#      The runs of (b) at fixed budgets (budget column 100000, 300000) beside auto30's auto runs are the auto
#      rule's check at seed 1 with gc_every 4 (operating_point/'s seed 0 ran gc_every 1).
# A CPU dry run (about 3 minutes of 2 cores): tiny scenes (`jsgstools synth OUT --size 48x36 --views 8
# --point-density 0.3`, then the clean base as gpu_prepare.sh makes it) in two carry folders, the LPIPS weights
# in the first; GPU_RUN a stand-in for scripts/gpu_run.sh that puts the venv's python3 first on PATH and the
# cwd on PYTHONPATH; FLOWER, FERN, CUP and MOUSE their names; ITERS=40 EVAL_AT=20,40 EST_PCT=5 OVERHEAD=10;
# SRC, DATA, LOGS, BENCHES, CARRY1, CARRY2 and OUT (one per call) in a folder of your own; PHASE 1, 2, 3, then
# PHASE=gather with SCENE_DIR the scenes and VENV the venv. tests/test_tools/test_operating_point_next.py runs
# the lanes, the queue and the archive with a stand-in that fakes the benches, and (slow) two real lanes and
# the gather.
set -u
cd "$(dirname "$0")/../.."
PHASE=${PHASE:?set PHASE=1, 2 or 3 (on the GPU machine) or gather (on the CPU)}
export S=${SRC:-/tmp/src} D=${DATA:-/tmp/opn_data} L=${LOGS:-/tmp/opn_logs} B=${BENCHES:-/tmp/opn}
export GPU_RUN=${GPU_RUN:-scripts/gpu_run.sh} GS=${GSPLAT_STEPS:-1.5} BS=${B_SEEDS:-1}
export FLOWER=${FLOWER:-llff_flower} FERN=${FERN:-llff_fern}
export CUP=${CUP:-custom_kwrous_cup} MOUSE=${MOUSE:-custom_myhan_mouse}
export EST_PCT=${EST_PCT:-100} OVERHEAD=${OVERHEAD:-40} POLL=${POLL:-5}
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-/tmp/torch_ext} JSGS_LPIPS_WEIGHTS=$D/alexnet_features.pth
LANES=${LANES:-0:a_cup_s0 1:a_cup_s1 2:a_mouse_s0 3:a_mouse_s1}
QUEUE=${QUEUE-ac_cup ac_mouse b_fern b_mouse100 b_mouse300 c_fern_s0 c_flower_s0 c_mouse_s0 c_cup_s0 \
c_fern_s1 c_flower_s1 c_mouse_s1 c_cup_s1}

spec() {  # spec JOB: its operating_point.sh settings (J_*) and J_EST, its seconds on a GPU of its own
    J_PART=time J_SCHED=gaussian J_BUDGETS=100k J_SEEDS=${1##*_s} J_JOBS=2
    case $1 in
        a_flower_s[01]) J_SCENE=$FLOWER J_SCHED=gaussian,clean J_JOBS=3 J_EST=460 ;;
        a_fern_s[01]) J_SCENE=$FERN J_SCHED=gaussian,clean J_JOBS=3 J_EST=430 ;;
        a_cup_s[01]) J_SCENE=$CUP J_EST=540 ;;&
        a_mouse_s[01]) J_SCENE=$MOUSE J_EST=490 ;;&
        a_cup_s[01] | a_mouse_s[01]) [ -z "${A_CLEAN:-}" ] || { J_SCHED=gaussian,clean J_JOBS=3; J_EST=$((J_EST * 7 / 5)); } ;;
        ac_cup) J_SCENE=$CUP J_SCHED=clean J_SEEDS=0,1 J_EST=400 ;;
        ac_mouse) J_SCENE=$MOUSE J_SCHED=clean J_SEEDS=0,1 J_EST=360 ;;
        b_fern) J_PART=rule J_SCENE=$FERN J_SEEDS=$BS J_JOBS=1 J_EST=200 ;;
        b_mouse100) J_PART=rule J_SCENE=$MOUSE J_SEEDS=$BS J_JOBS=1 J_EST=290 ;;
        b_mouse300) J_PART=rule J_SCENE=$MOUSE J_BUDGETS=300k J_SEEDS=$BS J_JOBS=1 J_EST=450 ;;
        c_flower_s[01]) J_SCENE=$FLOWER J_SCHED=uniform,descending J_JOBS=4 J_EST=650 ;;
        c_fern_s[01]) J_SCENE=$FERN J_SCHED=uniform,descending J_JOBS=4 J_EST=610 ;;
        c_cup_s[01]) J_SCENE=$CUP J_SCHED=uniform,descending J_JOBS=4 J_EST=1070 ;;
        c_mouse_s[01]) J_SCENE=$MOUSE J_SCHED=uniform,descending J_JOBS=4 J_EST=970 ;;
        *) echo "error: job $1: not one of a_*, ac_*, b_*, c_*" >&2; return 2 ;;
    esac
}
left() { echo $(($(cat $L/t_stop) - $(date +%s))); }
ready() { [ -f "$D/bench/data/$1/.ready" ]; }
bench() {  # bench JOB GPU: operating_point.sh for JOB on GPU, with the time left as its --time-limit
    spec "$1" || return
    local tl; tl=$(left)
    if [ "$tl" -lt $((OVERHEAD + 20)) ]; then echo "$(date +%T) $1: not started, ${tl} s left" >> $L/lanes.log; return; fi
    echo "$(date +%T) start $1 on GPU $2 (time limit $tl s, estimate $((J_EST * EST_PCT / 100)) s)" >> $L/lanes.log
    mkdir -p $B/out_$1
    (cd $S && CUDA_VISIBLE_DEVICES=$2 PART=$J_PART SCENES=$J_SCENE SEEDS=$J_SEEDS SCHEDULES=$J_SCHED \
        RULE_BUDGETS=$J_BUDGETS JOBS=$J_JOBS GSPLAT_STEPS=$GS TL=$tl GPU_DIR=$D OUT_DIR=$B/$1 OUT=$B/out_$1 \
        timeout $((tl + 150)) bash $GPU_RUN bash tools/campaigns/operating_point.sh > $L/$1.log 2>&1 < /dev/null)
    echo "$(date +%T) end $1 on GPU $2 (rc $?)" >> $L/lanes.log
    # its test renders at the first and last evaluation, 1/4 size (tools/results/thumbs.py), in the archive
    (cd $S && bash $GPU_RUN python3 tools/results/thumbs.py $B/$1 $L/thumbs/$1) >> $L/$1.log 2>&1
}
take() {  # the first queued job whose estimate fits the time left and whose data is here (taken off the
    # queue); status 3: one fits but its data has not come yet; 1: none fits
    exec 9> $L/queue.lock && flock 9
    local j tl rc=1; tl=$(left)
    for j in $(cat $L/queue); do
        spec "$j" 2> /dev/null || continue
        [ $((J_EST * EST_PCT / 100 + OVERHEAD)) -le "$tl" ] || continue
        if ready "$J_SCENE"; then
            grep -vx "$j" $L/queue > $L/queue.new; mv $L/queue.new $L/queue
            echo "$j"; return 0
        fi
        rc=3
    done
    return $rc
}
lane() {  # lane GPU JOBS: the pinned JOBS (comma-separated) side by side, each once its data is here; then the queue
    local g=$1 j
    for j in ${2//,/ }; do
        spec "$j" || continue
        (while ! ready "$J_SCENE" && [ "$(left)" -gt 0 ]; do sleep $POLL; done; bench "$j" "$g") &
    done
    wait
    while true; do
        j=$(take) && { bench "$j" "$g"; continue; }
        [ $? -eq 3 ] || break
        sleep "$POLL"
    done
    echo "$(date +%T) lane $g done" >> $L/lanes.log
    touch $L/lane_$g.done
}
carry() {  # carry FOLDER: its LPIPS weights and clean bases into $D, each scene marked ready once whole (a
    # scene already here is kept; no FOLDER: nothing this call)
    [ -d "$1" ] || { echo "carry $1: not on this machine (not carried): no data this call"; return 0; }
    [ -f "$1/alexnet_features.pth" ] && cp "$1/alexnet_features.pth" $D/
    local s
    for s in "$1"/bench/data/*/; do
        [ -d "$s" ] || continue
        s=$(basename "$s")
        ready "$s" && continue
        rm -rf "$D/bench/data/.$s" && cp -r "$1/bench/data/$s" "$D/bench/data/.$s" \
            && mv "$D/bench/data/.$s" "$D/bench/data/$s" && touch "$D/bench/data/$s/.ready"
    done
}
wait_lanes() {  # wait_lanes SECONDS: until every lane is done or SECONDS have passed
    local end=$((SECONDS + $1)) n
    n=$(cat $L/lanes_n)
    while [ $SECONDS -lt $end ] && [ "$(ls $L/lane_*.done 2> /dev/null | wc -l)" -lt "$n" ]; do sleep $POLL; done
}
gather() {  # on the CPU: the benches of ARCHIVE (the last call's opn_<PHASE>.tgz) into GATHER (a new folder),
    # each one cut before its report collected from its runs (operating_point.sh REPORT_ONLY=1), then TARGET
    local a=${ARCHIVE:?set ARCHIVE to the opn_PHASE.tgz of the last call} g=${GATHER:-.res/opn} t j
    local target=${TARGET:-docs/results/operating_point/auto30} benches=()
    [ ! -e "$g" ] || { echo "error: GATHER=$g: already there; name a new folder" >&2; return 2; }
    mkdir -p "$g/archive" && tar xzf "$a" -C "$g/archive" || { echo "error: ARCHIVE=$a: not a .tgz" >&2; return 2; }
    for t in "$g"/archive/bench_*.tar; do
        [ -e "$t" ] || continue
        j=$(basename "$t" .tar) && j=${j#bench_}
        mkdir -p "$g/$j" && tar xf "$t" -C "$g/$j" && spec "$j" || return 2
        if [ ! -f "$g/$j/results.csv" ]; then
            echo "$j: no results.csv (the calls ended before its report): collected from its runs"
            PART=$J_PART SCENES=$J_SCENE SEEDS=$J_SEEDS SCHEDULES=$J_SCHED RULE_BUDGETS=$J_BUDGETS JOBS=$J_JOBS \
                GSPLAT_STEPS=$GS OUT_DIR=$g/$j REPORT_ONLY=1 bash tools/campaigns/operating_point.sh
        fi
        if [ -f "$g/$j/results.csv" ]; then benches+=("$g/$j"); else echo "$j: left out (no run to collect)"; fi
    done
    [ ${#benches[@]} -gt 0 ] || { echo "error: ARCHIVE=$a: no bench in it" >&2; return 2; }
    python3 tools/results/build_report.py ${STEP:+--step "$STEP"} "$target" "${benches[@]}"
}
case $PHASE in
    gather) PATH=$(cd "${VENV:-.venv}/bin" && pwd):$PATH; gather; exit ;;
    lane) echo $$ >> $L/lane_pids; lane "$LANE_GPU" "$LANE_JOBS"; exit ;;
    1)
        for j in $(printf '%s\n' $LANES | cut -d: -f2- | tr ',' ' ') $QUEUE; do spec "$j" || exit 2; done
        # without them every run would stop at its first evaluation (the campaign's measure is LPIPS)
        [ -f "${CARRY1:-.gpuOP3}/alexnet_features.pth" ] || {
            echo "error: ${CARRY1:-.gpuOP3}/alexnet_features.pth: no LPIPS weights in the first carry" >&2; exit 2; }
        # lanes of an earlier PHASE 1 on this machine (each leads its own process group: setsid) would take the
        # new queue
        for p in $(cat $L/lane_pids 2> /dev/null); do kill -- -"$p" 2> /dev/null; done
        rm -rf $S $D $L $B && mkdir -p $S $D/bench/data $L $B
        echo $(($(date +%s) + ${STOP_AT:-1200})) > $L/t_stop
        tar cf - --exclude='./.gpu*' --exclude=./.res --exclude=./.torch_ext --exclude=./.venv . | tar xf - -C $S
        carry "${CARRY1:-.gpuOP3}"
        printf '%s\n' $QUEUE > $L/queue
        (cd $S && timeout 300 bash $GPU_RUN true) > $L/build.log 2>&1 || { echo "build failed:"; tail -20 $L/build.log; }
        n=0
        for l in $LANES; do
            n=$((n + 1))
            # the command alone in the background (not the subshell): nothing of the call waits for the lane
            (cd $S || exit; LANE_GPU=${l%%:*} LANE_JOBS=${l#*:} PHASE=lane setsid nohup \
                bash tools/campaigns/operating_point_next.sh > $L/lane_${l%%:*}.log 2>&1 < /dev/null &)
        done
        echo $n > $L/lanes_n
        ;;
    *) [ -f "$L/lanes_n" ] || { echo "error: no lanes on this machine ($L/lanes_n): the machine of PHASE=1 went" \
        "back (more than 30 s idle?) and this call got a fresh one; start again with PHASE=1" >&2; exit 3; } ;;&
    2)
        carry "${CARRY2:-.gpuOP4}"
        wait_lanes "${WAIT:-480}"
        ;;
    *) wait_lanes "${WAIT:-540}" ;;
esac
{
    echo "phase $PHASE at $(date +%T): $(left) s to the stop; lanes done: $(ls $L/lane_*.done 2> /dev/null | wc -l) of $(cat $L/lanes_n)"
    echo "queue left: $(tr '\n' ' ' < $L/queue)"
    for b in "$B"/*/; do
        [ -d "$b/runs" ] || continue
        echo "$(basename "$b"): $(grep -l '"status": "complete"' "$b"/runs/*/*/*/*/*/metrics.json 2> /dev/null \
            | wc -l) runs complete, $(ls "$b"/runs/*/*/*/*/*/metrics.json 2> /dev/null | wc -l) started"
    done
} > $L/status.txt
command -v nvidia-smi > /dev/null && nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv \
    > $L/smi_$PHASE.txt 2>&1
for b in "$B"/*/; do
    [ -d "$b/runs" ] || continue
    (cd "$b" && tar cf - $(ls results.csv report.md bench.json runs/*/*/*/*/*/metrics.json \
        runs/*/*/*/*/*/config.json 2> /dev/null)) > $L/bench_$(basename "$b").tar
done
tar czf "$OUT/opn_$PHASE.tgz" -C $L --exclude=./queue.lock .
cat $L/status.txt $L/lanes.log 2> /dev/null
ls -la "$OUT"

#!/usr/bin/env bash
# A cluster on one machine: one learner and N trainer actors (plus an evaluator) as separate
# processes from the release binaries, configured by the same file as the Compose stack and the
# Kubernetes manifests (deploy/hac.toml). For each actor count it runs the config's run to its
# end (stop_at or the episode budget) and reads the learner's run directory (summary.json,
# curve.csv); then one more run scales the trainers up and down while it trains. Prints a table.
#
#   cargo build --release -p hac-learner-service -p hac-actor-service
#   deploy/local-cluster.sh                        # 1, 2, 4, 8 actors, then scaling 1 -> 4 -> 8 -> 2
#   deploy/local-cluster.sh --short                # 1 and 2 actors, tiny budget (the test's form)
#   deploy/local-cluster.sh --seeds "0 1 2 3 4" --updates "40 20 10" --scale ""
#                                                  # the grid: actors x updates per episode x seeds
#
# Options:
#   --config FILE        config file for every process [deploy/hac.toml]
#   --actors "1 2 4 8"   trainer counts, one run each (per seed and updates per episode)
#   --seeds "0 1 ..."    seeds, one run each [the config's seed]; with more than one, or with
#                        --updates, a summary table of the medians per actor count follows
#   --updates "40 20"    the learner's updates per level per training episode
#                        (updates_per_episode, the rate limiter's ratio), one run each [the
#                        config's]
#   --scale "1 4 8 2"    trainer counts of the phases of the scaling run ("" to skip it)
#   --phase-seconds S    length of each scaling phase [20]
#   --episodes N         the learner's episode budget [the config's]
#   --eval-every N       the evaluator's period in trained episodes [50; the scaling run: 10, for
#                        enough points per phase]
#   --set KEY=VALUE      a hyperparameter for the learner (repeatable), as for `hac learner`
#   --timeout S          give up on a run after S seconds [900]
#   --out DIR            where the runs and logs go [runs/local-cluster]
#   --short              --actors "1 2" --scale "1 2 1" --phase-seconds 4 --episodes 20
#                        --eval-every 10 --set test_episodes=10
#
# Binaries: $HAC_BIN (the `hac` command: `hac learner`, `hac actor`), else $HAC_LEARNER_BIN and
# $HAC_ACTOR_BIN, else hac-learner and hac-actor in ${CARGO_TARGET_DIR:-target}/release.
#
# Every process reads the config through HAC_CONFIG, as in the containers. Local overrides of the
# shared config: --listen/--learner on loopback, a run directory per run, status and metrics
# listeners on ephemeral loopback ports (HAC_STATUS_LISTEN, HAC_METRICS_LISTEN) and a fresh token
# (HAC_TOKEN_FILE), as a deployment would set them.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
config="$repo/deploy/hac.toml"
actor_counts="1 2 4 8"
scale_counts="1 4 8 2"
phase_seconds=20
episodes=""
eval_every=50
seeds=""
updates=""
sets=()
timeout=900
out="runs/local-cluster"

while [[ $# -gt 0 ]]; do
  case "$1" in
    --config) config=$2; shift 2 ;;
    --actors) actor_counts=$2; shift 2 ;;
    --seeds) seeds=$2; shift 2 ;;
    --updates) updates=$2; shift 2 ;;
    --scale) scale_counts=$2; shift 2 ;;
    --phase-seconds) phase_seconds=$2; shift 2 ;;
    --episodes) episodes=$2; shift 2 ;;
    --eval-every) eval_every=$2; shift 2 ;;
    --set) sets+=(--set "$2"); shift 2 ;;
    --timeout) timeout=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --short)
      actor_counts="1 2"; scale_counts="1 2 1"; phase_seconds=4; episodes=20; eval_every=10
      sets+=(--set test_episodes=10); shift ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "local-cluster.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done

if [[ -n "${HAC_BIN:-}" ]]; then
  learner_cmd=("$HAC_BIN" learner)
  actor_cmd=("$HAC_BIN" actor)
else
  bin_dir="${CARGO_TARGET_DIR:-$repo/target}/release"
  learner_cmd=("${HAC_LEARNER_BIN:-$bin_dir/hac-learner}")
  actor_cmd=("${HAC_ACTOR_BIN:-$bin_dir/hac-actor}")
fi
for bin in "${learner_cmd[0]}" "${actor_cmd[0]}"; do
  [[ -x "$bin" ]] || { echo "local-cluster.sh: $bin is not an executable (build the release binaries first)" >&2; exit 2; }
done
[[ -f "$config" ]] || { echo "local-cluster.sh: no config file $config" >&2; exit 2; }

mkdir -p "$out"
out=$(cd "$out" && pwd)
token_file="$out/token"
head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n' > "$token_file"
chmod 600 "$token_file"

# What every process gets in place of the deployment's settings.
export HAC_CONFIG="$config"
export HAC_TOKEN_FILE="$token_file"
export HAC_STATUS_LISTEN=127.0.0.1:0
export HAC_METRICS_LISTEN=127.0.0.1:0
unset HAC_LISTEN HAC_LEARNER HAC_OUT

pids=()
cleanup() {
  for pid in "${pids[@]}"; do
    kill -KILL "$pid" 2>/dev/null || true
  done
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# start_learner DIR EPISODES [FLAGS...]: starts the learner with its run directory DIR/run (and
# the episode budget EPISODES, if not empty); sets learner_pid, learner_url, learner_started.
start_learner() {
  local dir=$1 budget=$2; shift 2
  rm -rf "$dir"; mkdir -p "$dir"
  local flags=(--listen 127.0.0.1:0 --out "$dir/run")
  [[ -n "$budget" ]] && flags+=(--episodes "$budget")
  "${learner_cmd[@]}" "${flags[@]}" "${sets[@]}" "$@" > "$dir/learner.out" 2> "$dir/learner.log" &
  learner_pid=$!
  pids+=("$learner_pid")
  learner_started=$(date +%s.%N)
  local waited=0
  until grep -q '^listening on ' "$dir/learner.out" 2>/dev/null; do
    if ! kill -0 "$learner_pid" 2>/dev/null; then
      echo "local-cluster.sh: the learner exited at start:" >&2; tail -5 "$dir/learner.log" >&2; exit 1
    fi
    sleep 0.1; waited=$((waited + 1))
    (( waited < 600 )) || { echo "local-cluster.sh: the learner did not listen within 60 s" >&2; exit 1; }
  done
  learner_url="http://$(sed -n 's/^listening on //p' "$dir/learner.out" | head -1)"
}

# start_actor DIR ID [FLAGS...]: sets actor_pid.
start_actor() {
  local dir=$1 id=$2; shift 2
  "${actor_cmd[@]}" --learner "$learner_url" --id "$id" "$@" \
    > /dev/null 2> "$dir/$id.log" &
  actor_pid=$!
  pids+=("$actor_pid")
}

# wait_for PID SECONDS: waits for a process to exit; returns its status (124 on timeout).
wait_for() {
  local pid=$1 deadline=$(( $(date +%s) + $2 ))
  while kill -0 "$pid" 2>/dev/null; do
    (( $(date +%s) < deadline )) || return 124
    sleep 0.2
  done
  wait "$pid"
}

# watch_run DIR SECONDS PID...: waits for the learner to finish the run; fails at once if one of
# the actors PID... exits with an error first.
watch_run() {
  local dir=$1 deadline=$(( $(date +%s) + $2 )) pid status
  shift 2
  while kill -0 "$learner_pid" 2>/dev/null; do
    for pid in "$@"; do
      if ! kill -0 "$pid" 2>/dev/null; then
        status=0; wait "$pid" || status=$?
        if (( status != 0 )); then
          echo "local-cluster.sh: an actor exited with status $status before the run ended:" >&2
          grep -l . "$dir"/*.log | while read -r log; do echo "--- $log" >&2; tail -5 "$log" >&2; done
          exit 1
        fi
      fi
    done
    (( $(date +%s) < deadline )) || { echo "local-cluster.sh: the run did not end within $2 s" >&2; exit 1; }
    sleep 0.2
  done
  status=0; wait "$learner_pid" || status=$?
  (( status == 0 )) || { echo "local-cluster.sh: the learner ended with status $status:" >&2; tail -5 "$dir/learner.log" >&2; exit 1; }
}

# json_number FILE KEY: a top-level number of a pretty-printed JSON file ("-" if absent or null).
json_number() {
  awk -v key="\"$2\":" '$1 == key { v = $2; sub(/,$/, "", v); print (v == "null" ? "-" : v); found = 1 }
    END { if (!found) print "-" }' "$1"
}

# curve_stats CSV T0 T1: env steps/s and updates/s (all levels) between the first evaluation at
# or after T0 s and the last at or before T1 s (learner clock; T0 = 0 counts from the learner's
# start), and the time of the first evaluation with success >= 0.9.
curve_stats() {
  awk -F, -v t0="$2" -v t1="$3" '
    BEGIN { if (t0 <= 0) { first = 0; s0 = 0; u0 = 0 } }
    NR == 1 { for (i = 1; i <= NF; i++) { col[$i] = i; if ($i ~ /^level[0-9]+_updates$/) upd[i] = 1 }; next }
    {
      t = $col["elapsed_s"]; u = 0; for (i in upd) u += $i
      if (t >= t0 && first == "") { first = t; s0 = $col["env_steps"]; u0 = u }
      if (t <= t1) { last = t; s1 = $col["env_steps"]; u1 = u }
      if (t90 == "" && $col["success_rate"] >= 0.9) t90 = t
    }
    END {
      if (first != "" && last > first) printf "%.0f %.0f", (s1 - s0) / (last - first), (u1 - u0) / (last - first)
      else printf "- -"
      printf " %s\n", (t90 == "" ? "-" : sprintf("%.1f", t90))
    }' "$1"
}

# median TOTAL VALUE...: the median of TOTAL values of which those given are the ones that exist;
# the missing ones (runs that never reached 90%) count as the largest, so the median is "never"
# once half of them are missing.
median() {
  local total=$1; shift
  printf '%s\n' "$@" | awk -v total="$total" '
    NF { v[++k] = $1 } END {
      for (i = k + 1; i <= total; i++) v[i] = 1e300
      for (i = 1; i <= total; i++) for (j = i + 1; j <= total; j++) if (v[j] + 0 < v[i] + 0) { t = v[i]; v[i] = v[j]; v[j] = t }
      m = v[int((total + 1) / 2)]; print (m + 0 >= 1e300 ? "never" : m) }'
}

# The grid: every updates-per-episode value x actor count x seed ("" keeps the config's).
grid=$([[ -n "$seeds$updates" ]] && echo 1 || true)
rows=()
summary_rows=()
for u in ${updates:-config}; do
  for n in $actor_counts; do
    reached=0; e90s=(); t90s=(); walls=()
    for seed in ${seeds:-config}; do
      name="actors-$n"
      run_flags=()
      what=""
      [[ $u != config ]] && { name+="-upe$u"; run_flags+=(--set "updates_per_episode=$u"); what+=", $u updates per episode"; }
      [[ $seed != config ]] && { name+="-seed$seed"; run_flags+=(--seed "$seed"); what+=", seed $seed"; }
      dir="$out/$name"
      echo "== $n trainer(s)$what: $dir" >&2
      start_learner "$dir" "$episodes" "${run_flags[@]}"
      start_actor "$dir" evaluator --role evaluator --eval-every "$eval_every"
      run_pids=("$actor_pid")
      for ((i = 0; i < n; i++)); do
        start_actor "$dir" "trainer-$i" --role trainer
        run_pids+=("$actor_pid")
      done
      watch_run "$dir" "$timeout" "${run_pids[@]}"
      for pid in "${run_pids[@]}"; do
        status=0; wait_for "$pid" 60 || status=$?
        [[ $status -eq 0 ]] || { echo "local-cluster.sh: an actor of the $n-trainer run ended with status $status" >&2; exit 1; }
      done
      summary="$dir/run/summary.json"
      wall=$(json_number "$summary" wall_time_s)
      steps=$(json_number "$summary" env_steps)
      transitions=$(json_number "$summary" transitions)
      e90=$(json_number "$summary" episodes_to_90)
      read -r _ updates_per_s t90 < <(curve_stats "$dir/run/curve.csv" 0 1e18)
      row=$(awk -v n="$n" -v e="$(json_number "$summary" episodes_ingested)" -v s="$steps" -v tr="$transitions" \
        -v w="$wall" -v u="$updates_per_s" -v t90="$t90" -v e90="$e90" \
        'BEGIN { printf "| %d | %s | %.0f | %.0f | %s | %s | %s | %.1f |", n, e, s / w, tr / w, u, t90, e90, w }')
      [[ -n "$grid" ]] && row="| $u | $seed $row"
      rows+=("$row")
      walls+=("$wall")
      if [[ "$e90" != "-" ]]; then
        reached=$((reached + 1)); e90s+=("$e90"); t90s+=("$t90")
      fi
    done
    count=$(wc -w <<< "${seeds:-x}")
    summary_rows+=("| $u | $n | $(median "$count" "${e90s[@]+"${e90s[@]}"}") | $(median "$count" "${t90s[@]+"${t90s[@]}"}") | $reached of $count | $(printf '%s\n' "${walls[@]}" | awk '{ s += $1 } END { printf "%.0f", s }') |")
  done
done

scale_rows=()
if [[ -n "${scale_counts// /}" ]]; then
  dir="$out/scaling"
  echo "== scaling $scale_counts, ${phase_seconds} s each: $dir" >&2
  # Runs until stopped: a budget it cannot reach in the phases and no early finish (the config
  # without its stop_at: even stop_at 1 ends a run that learns the task within the phases).
  mkdir -p "$out/scaling-config"
  sed '/^[[:space:]]*stop_at[[:space:]]*=/d' "$config" > "$out/scaling-config/hac.toml"
  HAC_CONFIG="$out/scaling-config/hac.toml" start_learner "$dir" 1000000000
  start_actor "$dir" evaluator --role evaluator --eval-every $(( eval_every < 10 ? eval_every : 10 ))
  trainers=()
  next_id=0
  phase_starts=()
  for count in $scale_counts; do
    while (( ${#trainers[@]} < count )); do
      start_actor "$dir" "trainer-$next_id" --role trainer
      trainers+=("$actor_pid")
      next_id=$((next_id + 1))
    done
    while (( ${#trainers[@]} > count )); do
      # SIGTERM: the actor finishes its episode, flushes what is unacknowledged and exits 0.
      kill -TERM "${trainers[-1]}" 2>/dev/null \
        || echo "local-cluster.sh: trainer pid ${trainers[-1]} had already exited (see $dir/*.log)" >&2
      unset 'trainers[-1]'
    done
    phase_starts+=("$(awk -v now="$(date +%s.%N)" -v t0="$learner_started" 'BEGIN { printf "%.3f", now - t0 }')")
    sleep "$phase_seconds"
  done
  phase_end=$(awk -v now="$(date +%s.%N)" -v t0="$learner_started" 'BEGIN { printf "%.3f", now - t0 }')
  kill -TERM "$learner_pid"
  status=0; wait_for "$learner_pid" 120 || status=$?
  [[ $status -eq 0 ]] || { echo "local-cluster.sh: the scaling run's learner ended with status $status" >&2; exit 1; }
  i=0
  for count in $scale_counts; do
    t0=${phase_starts[$i]}
    t1=${phase_starts[$((i + 1))]:-$phase_end}
    read -r steps_per_s updates_per_s _ < <(curve_stats "$dir/run/curve.csv" "$t0" "$t1")
    scale_rows+=("| $((i + 1)) | $count | $t0 - $t1 | $steps_per_s | $updates_per_s |")
    i=$((i + 1))
  done
  registered=$(grep -c 'actor registered' "$dir/learner.log" || true)
fi

echo
echo "Each run to the config's end (stop_at or episode budget); rates over the whole run."
echo
if [[ -n "$grid" ]]; then
  echo "| updates per episode | seed | trainers | episodes | env steps/s | transitions/s ingested | updates/s | time to 90% (s) | episodes to 90% | wall time (s) |"
  echo "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"
else
  echo "| trainers | episodes | env steps/s | transitions/s ingested | updates/s | time to 90% (s) | episodes to 90% | wall time (s) |"
  echo "| --- | --- | --- | --- | --- | --- | --- | --- |"
fi
printf '%s\n' "${rows[@]}"
if [[ -n "$grid" ]]; then
  echo
  echo "Per updates-per-episode value and trainer count, over the seeds: the median of episodes and"
  echo "of seconds to the first test round >= 90% (a run that never got there counts as the slowest)."
  echo
  echo "| updates per episode | trainers | episodes to 90% (median) | time to 90% (s, median) | runs that reached 90% | wall time of the runs (s, sum) |"
  echo "| --- | --- | --- | --- | --- | --- |"
  printf '%s\n' "${summary_rows[@]}"
fi
if (( ${#scale_rows[@]} > 0 )); then
  echo
  echo "One run, trainers scaled while it trains (rates between the evaluations inside each phase,"
  echo "\"-\" if fewer than two fell in it); $registered actor registrations in the learner's log."
  echo
  echo "| phase | trainers | seconds (learner clock) | env steps/s | updates/s |"
  echo "| --- | --- | --- | --- | --- |"
  printf '%s\n' "${scale_rows[@]}"
fi

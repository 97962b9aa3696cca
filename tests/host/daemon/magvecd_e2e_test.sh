#!/usr/bin/env bash
# End-to-end test of magvecd over real LCM udpm inside a private network namespace
# (loopback with multicast, ttl=0: nothing leaves the namespace):
#   1. lcm-logger records while `magvecd --sim` runs ~4 s: message rates as configured, the
#      calibration applies and is persisted, `magvec ctl status` answers, `magvec ctl watch --once`
#      draws the state (and without a daemon exits 4 after its timeout), SIGTERM -> exit 0 < 1 s;
#   2. `magvec replay --lcm-log` reproduces the live outputs in the log bit for bit, and so does a
#      subscriber fed by the file:// provider (speed=0); with lcm.raw_batch = 10 at 1 kHz too (raw
#      samples in mag_sample_batch messages), and raw_batch = 0 is a configuration error;
#   3. a restart loads the persisted calibration; SIGHUP starts a new session; replay of that log
#      (two sessions) is bit-identical too;
#   4. a corrupt config (2), a missing device (3) and a corrupt calibration file (4) each give a
#      clear message and their exit code, and the last good calibration file is never touched.
# usage: magvecd_e2e_test.sh MAGVECD MAGVEC LCM_PROBE      (exit 77 = skipped)
set -u

if [ -z "${MAGVEC_IN_NETNS:-}" ]; then
  if ! unshare -n true 2>/dev/null; then
    echo "SKIP: 'unshare -n' is not permitted here (needs root or user namespaces);" \
         "the udpm test must not run on the machine's real interfaces"
    exit 77
  fi
  exec unshare -n env MAGVEC_IN_NETNS=1 bash -c \
    'ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && exec bash "$0" "$@"' \
    "$0" "$@"
fi

MAGVECD=$1
MAGVEC=$2
PROBE=$3
URL='udpm://239.255.76.67:7667?ttl=0'
W=$(mktemp -d /tmp/magvecd_e2e.XXXXXX)
STATE=$W/state
FAILS=0
PIDS=()

cleanup() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null; done
  wait 2>/dev/null
  if [ "$FAILS" -eq 0 ]; then rm -rf "$W"; else echo "(work directory kept: $W)"; fi
}
trap cleanup EXIT

pass() { echo "PASS: $*"; }
fail() { echo "FAIL: $*"; FAILS=$((FAILS + 1)); }
check() { local what=$1; shift; if "$@"; then pass "$what"; else fail "$what"; fi; }
now_ns() { date +%s%N; }

# Fast-calibrating configuration: 100 Hz magnetometer and INS, a new random attitude per sample,
# li fit after 100 decimated samples, 100 held-out validation samples.
cat > "$W/magvecd.toml" <<EOF
[daemon]
log_level = "info"
realtime = true
health_period_s = 0.5
status_period_s = 0.5
[lcm]
url = "$URL"
[devices.magnetometer]
rate_hz = 100.0
[devices.ins]
rate_hz = 100.0
[calibration]
mode = "li"
li_min_samples = 100
validation_samples = 100
[sim]
samples_per_attitude = 1
EOF

start_logger() {  # $1 = log file
  lcm-logger --lcm-url="$URL" --quiet "$1" >"$1.out" 2>&1 &
  LOGGER=$!
  PIDS+=("$LOGGER")
  sleep 0.5
}
stop_logger() {
  sleep 0.3
  kill -INT "$LOGGER"
  wait "$LOGGER" 2>/dev/null
}
# Sends SIGTERM to $1 and measures the time until it exited; sets STOP_RC and STOP_MS.
stop_daemon() {
  local t0 t1
  t0=$(now_ns)
  kill -TERM "$1"
  wait "$1"
  STOP_RC=$?
  t1=$(now_ns)
  STOP_MS=$(((t1 - t0) / 1000000))
}
data_rows() { grep -v '^#' "$1"; }

# ------------------------------------------------------------------ 1. live run
start_logger "$W/run1.lcm"
"$MAGVECD" --config "$W/magvecd.toml" --sim --state-dir "$STATE" 2>"$W/run1.err" &
D=$!
PIDS+=("$D")
for _ in $(seq 1 60); do [ -f "$STATE/cal.json" ] && break; sleep 0.1; done
sleep 1.0
"$MAGVEC" ctl status --lcm-url "$URL" >"$W/ctl_status1.out" 2>&1
CTL_RC=$?
check "magvec ctl status answers (rc $CTL_RC)" [ "$CTL_RC" -eq 0 ]
check "ctl status reports an applied calibration" grep -q "state applied, .*cal_id 1, persisted cal_id 1" "$W/ctl_status1.out"
cat "$W/ctl_status1.out"
"$MAGVEC" ctl watch --once --url "$URL" --timeout 5 >"$W/watch1.out" 2>&1
check "ctl watch --once draws the verdict" grep -q "^verdict: applied: cal_id 1, validation rms" "$W/watch1.out"
check "ctl watch draws the 4 x 8 coverage map" [ "$(grep -c '^  z .*[#.]$' "$W/watch1.out")" -eq 4 ]
cat "$W/watch1.out"
stop_daemon "$D"
stop_logger
"$MAGVEC" ctl watch --once --url "$URL" --timeout 0.5 >"$W/watch_none.out" 2>&1
WATCH_RC=$?
check "ctl watch without a daemon exits 4 after --timeout (rc $WATCH_RC)" [ "$WATCH_RC" -eq 4 ]
check "ctl watch without a daemon says so" grep -qF "no calibration state from magvecd on $URL" "$W/watch_none.out"
echo "SIGTERM -> exit $STOP_RC after $STOP_MS ms"
check "SIGTERM exits 0" [ "$STOP_RC" -eq 0 ]
check "SIGTERM exit within 1 s ($STOP_MS ms)" [ "$STOP_MS" -lt 1000 ]
check "calibration persisted to state_dir/cal.json" grep -q '"cal_id"' "$STATE/cal.json"
check "daemon logged the application" grep -q "calibration applied: cal_id 1" "$W/run1.err"
check "real-time hints attempted and logged" grep -Eq "SCHED_FIFO|mlockall|memory locked" "$W/run1.err"
cp "$STATE/cal.json" "$W/good_cal.json"

"$PROBE" rate "$W/run1.lcm" MAGVEC_OUTPUT MAGVEC_RAW_MAG MAGVEC_ATTITUDE MAGVEC_HEALTH \
  MAGVEC_PIPELINE MAGVEC_CMD MAGVEC_CMD_REPLY >"$W/rates.out"
cat "$W/rates.out"
rate_ok() {  # channel expected_hz tolerance_fraction
  awk -v c="$1" -v e="$2" -v t="$3" '$1 == c { ok = ($3 > e * (1 - t) && $3 < e * (1 + t)) } END { exit !ok }' "$W/rates.out"
}
check "MAGVEC_OUTPUT at 100 Hz (+-3 %)" rate_ok MAGVEC_OUTPUT 100 0.03
check "MAGVEC_RAW_MAG at 100 Hz (+-3 %)" rate_ok MAGVEC_RAW_MAG 100 0.03
check "MAGVEC_ATTITUDE at 100 Hz (+-3 %)" rate_ok MAGVEC_ATTITUDE 100 0.03
check "MAGVEC_HEALTH at 2 Hz (+-25 %)" rate_ok MAGVEC_HEALTH 2 0.25
check "ctl command and reply in the log" awk '$1 == "MAGVEC_CMD_REPLY" && $2 >= 1 { f = 1 } END { exit !f }' "$W/rates.out"
N_OUT=$(awk '$1 == "MAGVEC_OUTPUT" { print $2 }' "$W/rates.out")
check "the live run produced outputs ($N_OUT)" [ "${N_OUT:-0}" -gt 300 ]

# ------------------------------------------------------------------ 2. replay
"$MAGVEC" replay --lcm-log "$W/run1.lcm" --out "$W/replay1.csv" --logged-out "$W/live1.csv" \
  --check >"$W/replay1.out" 2>&1
RP_RC=$?
cat "$W/replay1.out"
check "magvec replay --check: bit-identical (rc $RP_RC)" [ "$RP_RC" -eq 0 ]
check "replay CSV equals the live outputs' CSV" cmp -s <(data_rows "$W/replay1.csv") <(data_rows "$W/live1.csv")
check "replay CSV has one row per live output" [ "$(data_rows "$W/replay1.csv" | tail -n +2 | wc -l)" -eq "$N_OUT" ]
check "replay reaches cal_id 1 like the live run" grep -q "state applied, cal_id 1" "$W/replay1.out"
"$PROBE" subscribe "file://$W/run1.lcm?speed=0" MAGVEC_OUTPUT "$W/file_sub.csv" 1.0 >"$W/file_sub.out"
cat "$W/file_sub.out"
check "file:// replay into a subscriber gives the same outputs" cmp -s <(data_rows "$W/file_sub.csv") <(data_rows "$W/replay1.csv")

# ------------------------------------------------------------------ 2b. batched raw samples
# lcm.raw_batch = 10 at 1 kHz (INS 100 Hz), the simulated devices read every 10 ms
# (sim.wake_period_us): the raw samples travel as mag_sample_batch on their own channel, the
# outputs stay one per sample, and the replay is bit-identical.
cat > "$W/batch.toml" <<EOF
[daemon]
realtime = true
[lcm]
url = "$URL"
raw_batch = 10
[devices.magnetometer]
rate_hz = 1000.0
[devices.ins]
rate_hz = 100.0
[sim]
wake_period_us = 10000
EOF
start_logger "$W/batch.lcm"
"$MAGVECD" --config "$W/batch.toml" --sim --state-dir "$W/state_batch" 2>"$W/batch.err" &
D=$!
PIDS+=("$D")
sleep 2.0
stop_daemon "$D"
stop_logger
check "raw_batch = 10: SIGTERM exits 0 ($STOP_RC)" [ "$STOP_RC" -eq 0 ]
"$PROBE" rate "$W/batch.lcm" MAGVEC_OUTPUT MAGVEC_RAW_MAG MAGVEC_RAW_MAG_BATCH MAGVEC_ATTITUDE \
  >"$W/batch_rates.out"
cat "$W/batch_rates.out"
check "raw_batch: MAGVEC_OUTPUT at 1 kHz (+-3 %)" awk '$1 == "MAGVEC_OUTPUT" { ok = ($3 > 970 && $3 < 1030) } END { exit !ok }' "$W/batch_rates.out"
check "raw_batch: no per-sample raw messages" awk '$1 == "MAGVEC_RAW_MAG" { ok = ($2 == 0) } END { exit !ok }' "$W/batch_rates.out"
check "raw_batch: about one batch per INS period (100 Hz +-10 %)" awk '$1 == "MAGVEC_RAW_MAG_BATCH" { ok = ($3 > 90 && $3 < 110) } END { exit !ok }' "$W/batch_rates.out"
"$MAGVEC" replay --lcm-log "$W/batch.lcm" --out "$W/replay_batch.csv" --logged-out "$W/live_batch.csv" \
  --check >"$W/replay_batch.out" 2>&1
RP_RC=$?
cat "$W/replay_batch.out"
check "raw_batch: magvec replay --check bit-identical (rc $RP_RC)" [ "$RP_RC" -eq 0 ]
check "raw_batch: replay CSV equals the live outputs' CSV" cmp -s <(data_rows "$W/replay_batch.csv") <(data_rows "$W/live_batch.csv")
N_BATCH_OUT=$(awk '$1 == "MAGVEC_OUTPUT" { print $2 }' "$W/batch_rates.out")
N_BATCH_SAMPLES=$(sed -n 's/.* \([0-9]*\) magnetometer samples.*/\1/p' "$W/replay_batch.out")
check "raw_batch: one output per sample ($N_BATCH_OUT outputs, $N_BATCH_SAMPLES samples)" \
  [ "${N_BATCH_OUT:-0}" -gt 1000 ] && [ "$N_BATCH_OUT" = "$N_BATCH_SAMPLES" ]
printf '[lcm]\nraw_batch = 0\n' >"$W/bad_batch.toml"
"$MAGVECD" --config "$W/bad_batch.toml" --check-config >"$W/bad_batch.out" 2>&1
BB_RC=$?
cat "$W/bad_batch.out"
check "raw_batch = 0: --check-config exits 2 (got $BB_RC)" [ "$BB_RC" -eq 2 ]
check "raw_batch = 0: the message names the key and its range" \
  grep -q "lcm.raw_batch: out of range \[1, 1000\]" "$W/bad_batch.out"

# ------------------------------------------------------------------ 3. restart, SIGHUP
start_logger "$W/run2.lcm"
# systemd's side of sd_notify: a datagram socket recording every notification.
python3 -c '
import socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
s.bind(sys.argv[1])
with open(sys.argv[2], "w", buffering=1) as out:
    while True:
        out.write(s.recv(4096).decode().replace("\n", " ") + "\n")
' "$W/notify.sock" "$W/notify.log" &
PIDS+=("$!")
for _ in $(seq 1 50); do [ -S "$W/notify.sock" ] && break; sleep 0.02; done
cp "$W/magvecd.toml" "$W/run2.toml"
NOTIFY_SOCKET="$W/notify.sock" WATCHDOG_USEC=200000 \
  "$MAGVECD" --config "$W/run2.toml" --sim --state-dir "$STATE" 2>"$W/run2.err" &
D=$!
PIDS+=("$D")
sleep 0.6
"$MAGVEC" ctl status --lcm-url "$URL" >"$W/ctl_status2.out" 2>&1
cat "$W/ctl_status2.out"
check "restart loads the persisted calibration (log)" grep -q "loaded persisted calibration .*cal_id 1" "$W/run2.err"
check "restart: active cal_id 1 before any new calibration" grep -q "cal_id 1, persisted cal_id 1" "$W/ctl_status2.out"
kill -HUP "$D"
sleep 0.6
check "SIGHUP: configuration reloaded, new session" grep -q "configuration reloaded" "$W/run2.err"
check "SIGHUP: the calibration in progress starts again" grep -q "calibration in progress restarted" "$W/run2.err"
"$MAGVEC" ctl revert --lcm-url "$URL" >"$W/ctl_revert.out" 2>&1
check "ctl revert answers" grep -q "ok: reverted to the persisted calibration 1" "$W/ctl_revert.out"
"$MAGVEC" ctl accept --lcm-url "$URL" >"$W/ctl_accept.out" 2>&1
check "ctl accept answers (already persisted)" grep -q "ok: calibration 1 is already persisted" "$W/ctl_accept.out"
printf '[calibration]\nmode = "magic"\n' >"$W/run2.toml"
kill -HUP "$D"
sleep 0.4
check "SIGHUP with an invalid file: reload refused, old configuration kept" \
  grep -q "reload refused, keeping the running configuration: .*calibration.mode" "$W/run2.err"
"$MAGVEC" ctl status --lcm-url "$URL" >"$W/ctl_status3.out" 2>&1
check "still running after a refused reload" grep -q "^ok: running" "$W/ctl_status3.out"
stop_daemon "$D"
stop_logger
check "second SIGTERM exits 0 within 1 s ($STOP_MS ms)" [ "$STOP_RC" -eq 0 ] && [ "$STOP_MS" -lt 1000 ]
cat "$W/notify.log" | sort | uniq -c | sort -rn | head -8
check "sd_notify READY=1 (start, reload, refused reload)" [ "$(grep -c "READY=1" "$W/notify.log")" -eq 3 ]
check "sd_notify RELOADING=1 on SIGHUP" grep -q "RELOADING=1" "$W/notify.log"
check "sd_notify WATCHDOG=1 at half of WATCHDOG_USEC (>= 8 in ~1.2 s)" [ "$(grep -c 'WATCHDOG=1' "$W/notify.log")" -ge 8 ]
check "sd_notify STATUS= with the calibration state" grep -q "STATUS=collecting, cal_id 1" "$W/notify.log"
check "sd_notify STOPPING=1" grep -q "STOPPING=1" "$W/notify.log"
check "calibration file unchanged by a run without a new calibration" cmp -s "$STATE/cal.json" "$W/good_cal.json"
"$MAGVEC" replay --lcm-log "$W/run2.lcm" --out "$W/replay2.csv" --check >"$W/replay2.out" 2>&1
RP_RC=$?
cat "$W/replay2.out"
check "replay across SIGHUP (2 sessions) bit-identical (rc $RP_RC)" [ "$RP_RC" -eq 0 ]
check "replay saw both sessions" grep -q " 2 session(s)" "$W/replay2.out"
check "replay: calibrating again after the reload" grep -Eq "state (collecting|solving|validating), cal_id 1" "$W/replay2.out"
check "replayed outputs start with cal_id 1" awk -F, '/^#/ { next } !hdr { hdr = 1; next } { exit !($13 == 1) }' "$W/replay2.csv"

# ------------------------------------------------------------------ 3b. manual start and accept
# auto_accept = false, start_on_boot = false: nothing calibrates until `ctl start`, nothing is
# persisted until `ctl accept`.
sed -e 's/^mode = "li"/mode = "li"\nstart_on_boot = false\nauto_accept = false/' \
  "$W/magvecd.toml" >"$W/manual.toml"
"$MAGVECD" --config "$W/manual.toml" --sim --state-dir "$W/state_manual" 2>"$W/run3.err" &
D=$!
PIDS+=("$D")
sleep 0.5
"$MAGVEC" ctl accept --lcm-url "$URL" >"$W/ctl_accept0.out" 2>&1
ACC_RC=$?
check "ctl accept with nothing to accept is refused (exit 3, got $ACC_RC)" [ "$ACC_RC" -eq 3 ]
check "ctl accept refusal message" grep -q "refused: no calibration is active" "$W/ctl_accept0.out"
check "idle without start_on_boot" grep -q "state idle" "$W/ctl_accept0.out"
"$MAGVEC" ctl start --lcm-url "$URL" >"$W/ctl_start.out" 2>&1
check "ctl start answers" grep -q "ok: calibration started (li)" "$W/ctl_start.out"
for _ in $(seq 1 60); do grep -q "calibration applied: cal_id 1" "$W/run3.err" && break; sleep 0.1; done
check "calibration applied after ctl start" grep -q "calibration applied: cal_id 1" "$W/run3.err"
check "not persisted without accept" [ ! -e "$W/state_manual/cal.json" ]
"$MAGVEC" ctl accept --lcm-url "$URL" >"$W/ctl_accept1.out" 2>&1
check "ctl accept persists" grep -q "ok: calibration 1 persisted to" "$W/ctl_accept1.out"
check "accepted calibration file written" grep -q '"cal_id"' "$W/state_manual/cal.json"
stop_daemon "$D"
check "third SIGTERM exits 0 within 1 s ($STOP_MS ms)" [ "$STOP_RC" -eq 0 ] && [ "$STOP_MS" -lt 1000 ]

# ------------------------------------------------------------------ 4. error exit codes
expect_exit() {  # name expected_code message_regex command...
  local name=$1 code=$2 re=$3
  shift 3
  "$@" >"$W/$name.out" 2>&1
  local rc=$?
  echo "$name: exit $rc: $(grep -E -e "$re" "$W/$name.out" | head -1)"
  check "$name: exit code $code (got $rc)" [ "$rc" -eq "$code" ]
  check "$name: clear message" grep -Eq -e "$re" "$W/$name.out"
  check "$name: last good calibration untouched" cmp -s "$STATE/cal.json" "$W/good_cal.json"
}
printf '[calibration]\nmode = 42\n' >"$W/bad.toml"
expect_exit corrupt_config 2 "configuration error: .*calibration.mode" \
  "$MAGVECD" --config "$W/bad.toml" --sim --state-dir "$STATE"
printf '[daemon\nstate_dir = \n' >"$W/syntax.toml"
expect_exit syntax_config 2 "configuration error: .*syntax.toml:[0-9]+:[0-9]+: " \
  "$MAGVECD" --config "$W/syntax.toml" --sim --state-dir "$STATE"
expect_exit bad_usage 2 "--bogus" "$MAGVECD" --bogus
sed "s|^\[devices.magnetometer\]|[devices.magnetometer]\nspi_device = \"$W/no-such-spidev\"|" \
  "$W/magvecd.toml" >"$W/real.toml"
expect_exit missing_device 3 "magnetometer SPI: .*no-such-spidev.*No such file" \
  "$MAGVECD" --config "$W/real.toml" --state-dir "$STATE"
expect_exit lcm_unavailable 5 "LCM provider nosuchprovider://x is not available" \
  "$MAGVECD" --config "$W/magvecd.toml" --sim --state-dir "$STATE" --lcm-url "nosuchprovider://x"
mkdir -p "$W/state_corrupt"
printf '{"schema": "magvec-calibration/1", "W": [[1, 0' >"$W/state_corrupt/cal.json"
cp "$W/state_corrupt/cal.json" "$W/corrupt_copy.json"
expect_exit corrupt_params 4 "corrupt calibration file: .*cal.json" \
  "$MAGVECD" --config "$W/magvecd.toml" --sim --state-dir "$W/state_corrupt"
check "corrupt parameter file left byte for byte" cmp -s "$W/state_corrupt/cal.json" "$W/corrupt_copy.json"

echo "magvecd e2e: $FAILS failure(s)"
[ "$FAILS" -eq 0 ]

#!/usr/bin/env bash
# excavator-rtd against the real-time HIL, step by step (docs/daemon.md, "Running the daemon
# against the real-time HIL", quotes this file; tests/test_daemon_docs.py runs it with
# MAX_DIGS=1). Needs the project installed (make test, or pip install -e .) and its .venv/bin
# on PATH (python, excavator-rtd, excavator-rt).
#
#   scripts/daemon-on-hil.sh                         # task A to the end, files in a new temp dir
#   MAX_DIGS=1 PORT=54702 WORK=/tmp/rtd scripts/daemon-on-hil.sh
set -euo pipefail

WORK=${WORK:-$(mktemp -d)}   # configuration, job store, control socket, trace, logs
PORT=${PORT:-54701}          # the HIL's bridge on 127.0.0.1
MAX_DIGS=${MAX_DIGS:-}       # end the job after this many digs (empty: the whole task)
mkdir -p "$WORK"
cd "$WORK"
echo "files in $WORK"

# 1. The real-time HIL in its own process: the scale model's three drives and arm behind
#    python-can-remote's protocol on 127.0.0.1:$PORT, the arm at rest in the home pose (the spoil zone's point nearest the machine)
#    (boom, stick, bucket in rad), SCHED_FIFO 30 (below the daemon's loop), stopping by itself
#    after an hour. It also stops when its standard input closes: this shell holds it open on
#    file descriptor 3 until step 5 (or until this script exits, however it exits).
mkfifo hil.stdin
python -m hil_sim.harness.realtime --rig scale_model --q0 0.9588 -2.7806 0.0765 \
    --port "$PORT" --rt-priority 30 --max-wall-s 3600 < hil.stdin > hil.out 2> hil.err &
HIL=$!
exec 3> hil.stdin
until grep -q '^READY' hil.out; do
    kill -0 "$HIL" || { cat hil.err; exit 1; }
    sleep 0.2
done
cat hil.out    # READY <port>

# 2. The daemon's configuration: the shipped example with the bus (python-can's "remote"
#    interface to the HIL) and the paths changed; --check validates it without the bus and
#    changes no file.
EXAMPLE=$(python -c 'import os, rt_runtime.service as s; print(os.path.dirname(s.__file__))')
sed -e 's|^interface = "socketcan"|interface = "remote"|' \
    -e "s|^channel = \"can0\"|channel = \"ws://127.0.0.1:$PORT/\"|" \
    -e "s|^state_dir = \"[^\"]*\"|state_dir = \"$WORK/state\"|" \
    -e "s|^socket = \"[^\"]*\"|socket = \"$WORK/run/control.sock\"|" \
    -e "s|^# trace = \"[^\"]*\"|trace = \"$WORK/can.blf\"|" \
    "$EXAMPLE/excavator-rtd.example.toml" > rtd.toml
excavator-rtd --config rtd.toml --check

# 3. The daemon (under systemd it runs in the foreground; here in the background, its log in
#    rtd.log). It boots and enables the drives, then holds the arm; the control socket answers
#    once the drives are enabled.
export EXCAVATOR_RTD_SOCKET=$WORK/run/control.sock
excavator-rtd --config rtd.toml 2> rtd.log &
RTD=$!
trap 'kill "$RTD" 2> /dev/null || true' EXIT
until excavator-rt job status > /dev/null 2>&1; do
    kill -0 "$RTD" || { cat rtd.log; exit 1; }
    sleep 0.5
done
excavator-rt job status

# 4. A job: Yao's task A (a 0.6 m trench, 0.15 m deep), followed until it ends.
excavator-rt job submit --task A ${MAX_DIGS:+--max-digs "$MAX_DIGS"}
until excavator-rt job status 1 | grep -Eq '^job 1: (done|failed|cancelled)'; do
    kill -0 "$RTD" || { cat rtd.log; exit 1; }
    sleep 2
done
excavator-rt job status 1 | tee job.txt

# 5. Stop: SIGTERM to the daemon (a running job stops jerk-limited and stays resumable, the
#    drives are disabled), then close the HIL's standard input: it exits. The script's exit
#    status says whether the job was done.
kill -TERM "$RTD"
wait "$RTD"
exec 3>&-
wait "$HIL"
grep -q '^job 1: done' job.txt

#!/usr/bin/env bash
# A three-host cell on this machine, in network namespaces, and a partition that heals.
# Run as root from the workspace root after `cargo build --bins`:
#   sudo deploy/netns/partition.sh
# Each host runs `cell up deploy/cells/factory --host <a|b|c>` on a copy of the
# manifest (its data and logs stay in the run's directory, printed at the start). It
# prints what happens step by step. When it ends, fails or is interrupted (Ctrl-C,
# SIGTERM) it stops every process it started and deletes its namespaces and files
# (see hosts.sh); the last line says so.
# No pipefail: `cell ... | grep -q` and `| head -1` close the pipe early on purpose, and a
# check's verdict is the last command's.
set -eu
cd "$(dirname "$0")/../.."
BIN=${BIN:-$PWD/target/debug}
ORDERS=${ORDERS:-10}
HOSTS="a b c"
P=hlx$$            # namespace and link prefix, unique per run
source deploy/netns/hosts.sh

[ "$(id -u)" = 0 ] || { echo "needs root (ip netns)"; exit 1; }
[ -x "$BIN/cell" ] || { echo "build first: cargo build --bins"; exit 1; }

RUN=$(mktemp -d "/tmp/holarchy-$P.XXXX")
RUN_FILES=("$RUN")
CELL_DIR=$RUN/factory
cp -r deploy/cells/factory deploy/cells/demo "$RUN/"
cellc() { ns c "$BIN/cell" "$@" --cell factory --connect tcp/10.213.77.3:7447; }

step "three hosts a, b, c (network namespaces) on a bridge; 10.213.77.1-3/24; files in $RUN"
make_hosts

step "cell up on every host (its router and its holons; logs in $CELL_DIR/logs)"
for h in $HOSTS; do
  start "$h" "$RUN/up-$h.log" "$BIN/cell" up "$CELL_DIR" --host "$h"
done
for _ in $(seq 60); do
  if cellc status 2>/dev/null | grep -q "5 live holons"; then break; fi
  sleep 0.5
done
cellc status

step "submit $ORDERS orders from host c"
cellc submit breaker --count "$ORDERS" | tr '\n' ' '; echo
for _ in $(seq 120); do
  if cellc orders | grep running | grep -q robot2; then break; fi
  sleep 0.5
done
cellc orders | head -1
echo "orders booked on host b:"; cellc orders | grep robot2 || true

step "cut host b off (link down); its holons vanish after the 2 s lease"
ns b ip link set "${P}b0" down
start=$(date +%s%N)
for _ in $(seq 120); do
  if ! cellc orders | grep running | grep -q robot2; then break; fi
  sleep 0.25
done
echo "no order left on host b after $(( ($(date +%s%N) - start) / 1000000 )) ms"
cellc status
for _ in $(seq 240); do
  if cellc orders | head -1 | grep -q ", 0 running"; then break; fi
  sleep 0.5
done
cellc orders | head -1

step "heal: host b's link up; its router reconnects and robot2 rejoins"
ns b ip link set "${P}b0" up
for _ in $(seq 120); do
  if cellc status | grep -q robot2; then break; fi
  sleep 0.5
done
cellc status
before=$(grep -o '"pick":[0-9]*' "$CELL_DIR/robot2.counts.json" 2>/dev/null | cut -d: -f2 || echo 0)

step "submit $ORDERS more orders: host b takes work again"
cellc submit breaker --count "$ORDERS" | tr '\n' ' '; echo
for _ in $(seq 240); do
  if cellc orders | head -1 | grep -q ", 0 running"; then break; fi
  sleep 0.5
done
cellc orders | head -1
after=$(grep -o '"pick":[0-9]*' "$CELL_DIR/robot2.counts.json" | cut -d: -f2)
echo "robot2 picks: ${before:-0} before the heal, $after after"

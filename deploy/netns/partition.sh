#!/usr/bin/env bash
# A three-host cell on this machine, in network namespaces, and a partition that heals.
# Run as root from the workspace root after `cargo build --bins`:
#   sudo deploy/netns/partition.sh
# It prints what happens step by step and removes everything it made when it ends.
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${BIN:-$PWD/target/debug}
CELL_DIR=$PWD/deploy/cells/factory
P=hlx$$            # namespace and link prefix, unique per run
ORDERS=${ORDERS:-10}

step() { printf '\n== %s\n' "$*"; }
ns() { ip netns exec "$P$1" "${@:2}"; }
cellc() { ns c "$BIN/cell" "$@" --cell factory --connect tcp/10.213.77.3:7447; }

cleanup() {
  step "cleaning up"
  for h in a b c; do [ -n "${UP[$h]:-}" ] && kill "${UP[$h]}" 2>/dev/null || true; done
  sleep 2
  for h in a b c s; do ip netns del "$P$h" 2>/dev/null || true; done
  rm -rf "$CELL_DIR"/data-? "$CELL_DIR"/logs "$CELL_DIR"/*.counts.json
  echo "done"
}
declare -A UP
trap cleanup EXIT

[ "$(id -u)" = 0 ] || { echo "needs root (ip netns)"; exit 1; }
[ -x "$BIN/cell" ] || { echo "build first: cargo build --bins"; exit 1; }

step "three hosts a, b, c (network namespaces) on a bridge; 10.213.77.1-3/24"
ip netns add "${P}s"
ns s ip link add br0 type bridge
ns s ip link set br0 up
i=1
for h in a b c; do
  ip netns add "$P$h"
  ns "$h" ip link set lo up
  ip link add "$P${h}0" type veth peer name "$P${h}1"
  ip link set "$P${h}0" netns "$P$h"
  ip link set "$P${h}1" netns "${P}s"
  ns s ip link set "$P${h}1" master br0
  ns s ip link set "$P${h}1" up
  ns "$h" ip addr add "10.213.77.$i/24" dev "$P${h}0"
  ns "$h" ip link set "$P${h}0" up
  echo "host $h: 10.213.77.$i"
  i=$((i + 1))
done

step "cell up on every host (its router and its holons; logs in deploy/cells/factory/logs)"
for h in a b c; do
  ns "$h" "$BIN/cell" up "$CELL_DIR" --host "$h" > "/tmp/$P-up-$h.log" 2>&1 &
  UP[$h]=$!
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

#!/usr/bin/env bash
# docs/deploy.md, sections 3 to 5, run as written on one machine: four hosts a-d in
# network namespaces (192.0.2.11-14 in the guide become 10.213.77.1-4), a router on each
# as in section 2, then every command of the guide's sections 3 and 4, read from the
# guide itself (guide-lib.sh reads them), each on its host; orders are submitted and
# read with section 5's commands. It checks that the cell assembles, that orders
# complete, and that the robot hot-added in section 4 takes work. Section 4b, a standby
# on another host, is guide-standby.sh's. Run as root from the workspace root after
# `cargo build --bins`:
#   sudo deploy/netns/guide.sh
# When it ends, fails or is interrupted it stops everything it started (see hosts.sh).
# No pipefail: `cell ... | grep -q` and `| head -1` close the pipe early on purpose, and a
# check's verdict is the last command's.
set -eu
cd "$(dirname "$0")/../.."
BIN=${BIN:-$PWD/target/debug}
ORDERS=${ORDERS:-5}
GUIDE=docs/deploy.md
HOSTS="a b c d"
P=hlg$$
source deploy/netns/hosts.sh

[ "$(id -u)" = 0 ] || { echo "needs root (ip netns)"; exit 1; }
[ -x "$BIN/cell" ] || { echo "build first: cargo build --bins"; exit 1; }

RUN=$(mktemp -d "/tmp/holarchy-$P.XXXX")
RUN_FILES=("$RUN")

source deploy/netns/guide-lib.sh
localize_configs

step "four hosts a-d (network namespaces) on a bridge; files in $RUN"
make_hosts

step "section 2: a router on each of hosts a-c, connected to the others"
start_routers

step "section 3, as written in $GUIDE"
run_section 3
status=$(section5 status)
orders=$(section5 orders)
submit=$(section5 submit)
wait_live "5 live holons" "the cell of section 3 did not assemble"

step "section 5: $submit"
cellc $submit | tr '\n' ' '; echo
wait_all_done

step "section 4, as written in $GUIDE: hot-add robot3 on host d"
run_section 4
wait_live "6 live holons" "robot3 did not join"

step "section 5 again: $submit; robot3 takes work"
took=0
for round in 1 2 3; do
  cellc $submit | tr '\n' ' '; echo
  wait_all_done
  took=$(cellc $orders --detail | grep -c "done by resource/robot3" || true)
  [ "$took" -gt 0 ] && break
done
echo "steps done by robot3: $took"
[ "$took" -gt 0 ] || { echo "FAILED: robot3 never took work"; exit 1; }
echo "the guide works as written"

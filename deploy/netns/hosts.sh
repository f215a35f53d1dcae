# Hosts on one machine, for the scripts in this directory (sourced, not run).
#
# Network namespaces <prefix>a, <prefix>b, ... joined by veth links to a bridge in
# <prefix>s, with addresses 10.213.77.1, .2, ... /24. Every process is started with
# `start HOST CMD...`, which records its PID (the program's own: `ip netns exec` execs
# it). `teardown` stops everything: SIGTERM to what was started (a `cell up` stops its
# children in reverse order), then, after a grace, SIGKILL to every process still in
# the namespaces; the namespaces are deleted and the run's files removed only when no
# process is left in them. It runs on exit, Ctrl-C and SIGTERM.
#
# The caller sets HOSTS ("a b c"), P (the prefix; NETNS_PREFIX overrides it) and
# RUN_FILES (paths to remove at the end), then calls `make_hosts`.

P=${NETNS_PREFIX:-$P}
STOP_GRACE_S=${STOP_GRACE_S:-45}
declare -a STARTED=()

step() { printf '\n== %s\n' "$*"; }
ns() { ip netns exec "$P$1" "${@:2}"; }
address() { local i=1 h; for h in $HOSTS; do [ "$h" = "$1" ] && { echo "10.213.77.$i"; return; }; i=$((i + 1)); done; }

# start HOST LOG CMD...: runs CMD in HOST's namespace in the background, output to LOG.
start() {
  local host=$1 log=$2
  shift 2
  ip netns exec "$P$host" "$@" > "$log" 2>&1 &
  STARTED+=("$!")
}

# The PIDs of every process in our namespaces.
pids_in_hosts() {
  local h
  for h in $HOSTS s; do ip netns pids "$P$h" 2>/dev/null || true; done
}

teardown() {
  local status=$?
  trap - EXIT INT TERM
  step "stopping everything this run started"
  local pid
  for pid in "${STARTED[@]}"; do kill -TERM "$pid" 2>/dev/null || true; done
  local waited=0
  while [ -n "$(pids_in_hosts)" ] && [ "$waited" -lt $((STOP_GRACE_S * 4)) ]; do
    sleep 0.25
    waited=$((waited + 1))
  done
  local left
  left=$(pids_in_hosts)
  if [ -n "$left" ]; then
    echo "still running after ${STOP_GRACE_S} s, killed: $(echo $left)"
    kill -KILL $left 2>/dev/null || true
    for _ in $(seq 40); do [ -z "$(pids_in_hosts)" ] && break; sleep 0.25; done
  fi
  for pid in "${STARTED[@]}"; do wait "$pid" 2>/dev/null || true; done
  left=$(pids_in_hosts)
  if [ -n "$left" ]; then
    echo "processes $(echo $left) would not die: namespaces and files left in place"
    exit 1
  fi
  local h
  for h in $HOSTS s; do ip netns del "$P$h" 2>/dev/null || true; done
  [ "${#RUN_FILES[@]}" -gt 0 ] && rm -rf "${RUN_FILES[@]}"
  echo "done: nothing of this run is left running"
  exit "$status"
}

make_hosts() {
  trap teardown EXIT
  trap 'exit 130' INT
  trap 'exit 143' TERM
  ip netns add "${P}s"
  ns s ip link add br0 type bridge
  ns s ip link set br0 up
  local h a
  for h in $HOSTS; do
    a=$(address "$h")
    ip netns add "$P$h"
    ns "$h" ip link set lo up
    ip link add "$P${h}0" type veth peer name "$P${h}1"
    ip link set "$P${h}0" netns "$P$h"
    ip link set "$P${h}1" netns "${P}s"
    ns s ip link set "$P${h}1" master br0
    ns s ip link set "$P${h}1" up
    ns "$h" ip addr add "$a/24" dev "$P${h}0"
    ns "$h" ip link set "$P${h}0" up
    echo "host $h: $a"
  done
}

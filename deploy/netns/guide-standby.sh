#!/usr/bin/env bash
# docs/deploy.md, section 4b, run as written on one machine: three hosts a-c in network
# namespaces (192.0.2.11-13 in the guide become 10.213.77.1-3), a router on each as in
# section 2, section 3's inspection station, conveyor, their controllers and the product
# (its commands read from the guide; not its robot1 and orders1, which 4b moves to b and
# c, nor robot2, so that every robot step goes through robot1), then every command of
# section 4b, read from the guide, each on its host: robot1's fencing controller on a,
# robot1 on b and its standby on c, an etcd member on each host, orders1 on etcd on b and
# its standby on c. Orders are submitted and read with section 5's commands.
#
# It checks that `cell status` shows robot1's holder on b and its standby on c, orders1's
# holder on b and its standby on c with lag 0; that orders complete; that when host b's
# robot1 and orders1 freeze (SIGSTOP), the standbys on c take over at higher epochs and
# new orders complete; and that when b thaws (SIGCONT) its robot1 steps down to a standby
# and its orders1 exits deposed (nothing restarts it here: under systemd or `cell up` it
# would come back as a standby).
#
# Run as root from the workspace root after `cargo build --bins`, with etcd installed
# (Debian's etcd-server; ETCD names another binary):
#   sudo deploy/netns/guide-standby.sh
# When it ends, fails or is interrupted it stops everything it started (see hosts.sh).
# No pipefail: `cell ... | grep -q` and `| head -1` close the pipe early on purpose, and a
# check's verdict is the last command's.
set -eu
cd "$(dirname "$0")/../.."
BIN=${BIN:-$PWD/target/debug}
ETCD=${ETCD:-/usr/bin/etcd}
ORDERS=${ORDERS:-5}
GUIDE=${GUIDE:-docs/deploy.md}
HOSTS="a b c"
P=hls$$
source deploy/netns/hosts.sh

[ "$(id -u)" = 0 ] || { echo "needs root (ip netns)"; exit 1; }
[ -x "$BIN/cell" ] || { echo "build first: cargo build --bins"; exit 1; }
[ -x "$ETCD" ] || { echo "needs etcd at $ETCD (apt-get install etcd-server, or set ETCD)"; exit 1; }
# The guide's `etcd` is this one.
PATH=$(dirname "$ETCD"):$PATH

RUN=$(mktemp -d "/tmp/holarchy-$P.XXXX")
RUN_FILES=("$RUN")
source deploy/netns/guide-lib.sh
localize_configs

# Processes frozen by this run are thawed before teardown stops them (teardown takes
# the run's exit status from $?, hence the `||`: set -e does not end the trap there).
FROZEN=""
thaw_and_teardown() {
  local status=$?
  [ -z "$FROZEN" ] || kill -CONT $FROZEN 2>/dev/null || true
  if [ "$status" = 0 ]; then teardown; else (exit "$status") || teardown; fi
}

# wait_log FILE TEXT SECONDS WHY: waits until FILE contains TEXT; fails with WHY.
wait_log() {
  local deadline=$((SECONDS + $3))
  until grep -q "$2" "$1" 2>/dev/null; do
    [ "$SECONDS" -lt "$deadline" ] || { echo "FAILED: $4 (no \"$2\" within $3 s)"; tail -n 20 "$1"; exit 1; }
    sleep 0.1
  done
}

# wait_status WHY REGEX...: waits (60 s at most) until `cell status` matches every REGEX
# (extended, on one line each), prints it; fails with WHY otherwise.
wait_status() {
  local why=$1 out re ok
  shift
  local deadline=$((SECONDS + 60))
  while :; do
    out=$(cellc $status 2>&1 || true)
    ok=1
    for re in "$@"; do grep -Eq "$re" <<< "$out" || { ok=0; break; }; done
    [ "$ok" = 1 ] && break
    if [ "$SECONDS" -ge "$deadline" ]; then
      echo "$out"
      echo "FAILED: $why (cell status never matched /$re/ within 60 s)"
      exit 1
    fi
    sleep 0.5
  done
  echo "$out"
}

# The epoch of a fenced table's holder row: holder_epoch 'resource/robot1' or 'orders1'.
holder_epoch() {
  cellc $status 2>/dev/null | awk -v n="$1" '$1 == n && $2 == "holder" { print $3; exit }'
}

# Waits until every etcd member answers /health with "true" (60 s at most).
wait_etcd_healthy() {
  local h deadline=$((SECONDS + 60))
  for h in a b c; do
    until ns "$h" bash -c 'exec 3<>/dev/tcp/$0/2379 && printf "GET /health HTTP/1.0\r\n\r\n" >&3 && cat <&3' \
        "$(address "$h")" 2>/dev/null | grep -q '"health":"true"'; do
      [ "$SECONDS" -lt "$deadline" ] || { echo "FAILED: etcd on host $h is not healthy after 60 s"; tail -n 20 "$RUN"/"$h"-etcd-*.log; exit 1; }
      sleep 0.2
    done
  done
  echo "etcd: the three members answer healthy"
}

step "three hosts a-c (network namespaces) on a bridge; files in $RUN"
make_hosts
trap thaw_and_teardown EXIT

step "section 2: a router on each of hosts a-c, connected to the others"
start_routers

step "section 3, as written in $GUIDE: the inspection station, the conveyor, their controllers, the product"
commands=$(guide_commands 3 | grep -E 'inspect1\.toml|conveyor1\.toml|breaker\.toml|127\.0\.0\.1:76[12]1$' || true)
[ "$(wc -l <<< "$commands")" = 5 ] || { echo "FAILED: expected 5 such commands in section 3 of $GUIDE, found:"; echo "$commands"; exit 1; }
while read -r host command; do run_guide_command "$host" "$command"; done <<< "$commands"
status=$(section5 status)
orders=$(section5 orders)
submit=$(section5 submit)

step "section 4b, as written in $GUIDE"
mapfile -t commands < <(guide_commands 4b)
[ "${#commands[@]}" -gt 0 ] || { echo "no commands found in section 4b of $GUIDE"; exit 1; }
robot1_on=""
orders1_on=""
statuses=0
etcd_members=0
for entry in "${commands[@]}"; do
  host=${entry%% *}
  command=${entry#* }
  case $command in
    "cell status "*)
      statuses=$((statuses + 1))
      status=$command
      echo "host $host: $command"
      if [ "$statuses" = 1 ]; then
        wait_status "robot1 is not held on b with a standby on c" \
          '^resource/robot1 +holder +[0-9]+ +host-b ' '^resource/robot1 +standby +[0-9]+ +host-c '
      else
        wait_status "the cell (4 live holons) with orders1 held on b, its standby on c at lag 0, did not assemble" \
          '^cell factory: 4 live holons' \
          '^orders1 +holder +[0-9]+ +- +host-b ' '^orders1 +standby +[0-9]+ +0 +host-c '
      fi
      ;;
    *etcdctl*)
      wait_etcd_healthy
      if PATH="$BIN:$PATH" command -v etcdctl > /dev/null; then
        echo "host $host: $command"
        read -r -a words <<< "$command"
        ns "$host" env PATH="$BIN:$PATH" "${words[@]}" || { echo "FAILED: $command"; exit 1; }
      else
        echo "host $host: (etcdctl is not installed here: skipped) $command"
      fi
      ;;
    *)
      run_guide_command "$host" "$command"
      log=$RUN/$host-${command%% *}-$((${#STARTED[@]} - 1)).log
      pid=${STARTED[-1]}
      case $command in
        robot-sim*) wait_log "$log" "listening on" 20 "robot1's controller did not start" ;;
        etcd*) etcd_members=$((etcd_members + 1)) ;;
        holon-node*"--name robot1 "*)
          if [ -z "$robot1_on" ]; then
            # The first copy started claims first: the script waits for it, so that the
            # primary is the one the guide says.
            wait_log "$log" "holding the controller" 30 "robot1 on host $host never held the controller"
          fi
          robot1_on+="$host "
          eval "robot1_${host}_pid=$pid robot1_${host}_log=$log"
          ;;
        order-node*)
          if [ -z "$orders1_on" ]; then
            wait_log "$log" "serving at epoch" 60 "orders1 on host $host never served"
          fi
          orders1_on+="$host "
          eval "orders1_${host}_pid=$pid orders1_${host}_log=$log"
          ;;
      esac
      ;;
  esac
done
[ "$robot1_on" = "b c " ] && [ "$orders1_on" = "b c " ] && [ "$etcd_members" = 3 ] && [ "$statuses" = 2 ] || {
  echo "FAILED: section 4b should start robot1 on b then c, orders1 on b then c, three etcd members and show cell status twice; it has robot1 on: $robot1_on, orders1 on: $orders1_on, $etcd_members etcd members, $statuses cell status"
  exit 1
}

step "section 5: $submit"
cellc $submit | tr '\n' ' '; echo
wait_all_done

step "host b's robot1 and orders1 freeze (SIGSTOP): the standbys on c take over"
robot1_epoch=$(holder_epoch resource/robot1)
orders1_epoch=$(holder_epoch orders1)
echo "before: robot1 held at epoch $robot1_epoch, orders1 at epoch $orders1_epoch"
robot1_held_c=$(grep -c "holding the controller" "$robot1_c_log" || true)
FROZEN="$robot1_b_pid $orders1_b_pid"
kill -STOP $FROZEN
frozen_at=$(date +%s%N)
deadline=$((SECONDS + 30))
robot1_took=""; orders1_took=""
while [ -z "$robot1_took" ] || [ -z "$orders1_took" ]; do
  now=$(date +%s%N)
  if [ -z "$robot1_took" ] && [ "$(grep -c "holding the controller" "$robot1_c_log" || true)" -gt "$robot1_held_c" ]; then
    robot1_took=$(( (now - frozen_at) / 1000000 ))
    echo "robot1's standby on c holds the controller ${robot1_took} ms after the freeze"
  fi
  if [ -z "$orders1_took" ] && grep -q "serving at epoch" "$orders1_c_log"; then
    orders1_took=$(( (now - frozen_at) / 1000000 ))
    echo "orders1's standby on c serves ${orders1_took} ms after the freeze"
  fi
  [ "$SECONDS" -lt "$deadline" ] || { echo "FAILED: the standbys on c did not take over within 30 s"; tail -n 5 "$robot1_c_log" "$orders1_c_log"; exit 1; }
  sleep 0.1
done
orders1_new=$(grep -o "serving at epoch [0-9]*" "$orders1_c_log" | head -1 | grep -o "[0-9]*$")
[ "$orders1_new" -gt "$orders1_epoch" ] || { echo "FAILED: orders1 on c serves at epoch $orders1_new, not above $orders1_epoch"; exit 1; }
wait_status "the standbys on c are not the holders at higher epochs" \
  "^resource/robot1 +holder +$((robot1_epoch + 1)) +host-c " \
  "^orders1 +holder +$orders1_new +- +host-c "

step "section 5 while b is frozen: $submit"
cellc $submit | tr '\n' ' '; echo
wait_all_done

step "host b thaws (SIGCONT): its robot1 steps down to a standby, its orders1 exits deposed"
kill -CONT $FROZEN
FROZEN=""
deadline=$((SECONDS + 30))
while kill -0 "$orders1_b_pid" 2>/dev/null; do
  [ "$SECONDS" -lt "$deadline" ] || { echo "FAILED: orders1 on b still runs 30 s after the thaw"; tail -n 5 "$orders1_b_log"; exit 1; }
  sleep 0.1
done
grep -i "deposed" "$orders1_b_log" | tail -1
grep -qi "deposed" "$orders1_b_log" || { echo "FAILED: orders1 on b exited, but not deposed"; tail -n 5 "$orders1_b_log"; exit 1; }
echo "orders1 on b exited deposed (not restarted here; a supervisor would start it again as a standby)"
wait_status "robot1 on b did not step down to a standby" \
  "^resource/robot1 +holder +$((robot1_epoch + 1)) +host-c " \
  "^resource/robot1 +standby +$((robot1_epoch + 1)) +host-b "

step "section 5 after the thaw: $submit"
cellc $submit | tr '\n' ' '; echo
wait_all_done
echo "section 4b works as written"

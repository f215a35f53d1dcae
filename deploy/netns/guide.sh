#!/usr/bin/env bash
# docs/deploy.md, sections 3 to 5, run as written on one machine: four hosts a-d in
# network namespaces (192.0.2.11-14 in the guide become 10.213.77.1-4), a router on each
# as in section 2, then every command of the guide's sections 3 and 4, read from the
# guide itself, each on its host; orders are submitted and read with section 5's
# commands. It checks that the cell assembles, that orders complete, and that the robot
# hot-added in section 4 takes work. Run as root from the workspace root after
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

# The guide's addresses and directories on this machine.
localize() {
  sed -e 's/192\.0\.2\.1\([1-4]\)/10.213.77.\1/g' \
      -e "s#/var/lib/holarchy/#$RUN/var/#g" \
      -e 's#<any router>#10.213.77.3#g'
}

# Prints "HOST COMMAND" for every command in the ```sh blocks of the guide's section N
# (a "# host X" comment names the host of the lines after it; continuation lines are
# joined; a trailing "&" and comments are dropped).
guide_commands() {
  awk -v section="## $1." '
    /^## / { inside = (index($0, section) == 1) }
    inside && /^```sh/ { block = 1; next }
    block && /^```/ { block = 0; next }
    block { print }
  ' "$GUIDE" | {
    host=c; line=""
    while IFS= read -r text; do
      if [[ $text =~ ^#\ host\ ([a-z]) ]]; then host=${BASH_REMATCH[1]}; continue; fi
      [[ $text =~ ^[[:space:]]*(#|$) ]] && continue
      line+="${text%\\}"
      [[ $text == *\\ ]] && continue
      line=${line%%#*}
      line=$(echo "$line" | sed -e 's/[[:space:]]*&[[:space:]]*$//' -e 's/[[:space:]]\+/ /g' -e 's/ $//')
      echo "$host $line"
      line=""
    done
  } | localize
}

# Runs one long-running command of the guide on its host, logged in the run directory.
run_guide_command() {
  local host=$1; shift
  local words
  read -r -a words <<< "$*"
  echo "host $host: $*"
  start "$host" "$RUN/$host-${words[0]}-${#STARTED[@]}.log" env PATH="$BIN:$PATH" "${words[@]}"
}

# Starts every command of the guide's section N on its host.
run_section() {
  local commands
  commands=$(guide_commands "$1")
  [ -n "$commands" ] || { echo "no commands found in section $1 of $GUIDE"; exit 1; }
  while read -r host command; do run_guide_command "$host" "$command"; done <<< "$commands"
}

# Waits (60 s at most) until `cell status` says TEXT, prints it; fails with WHY otherwise.
wait_live() {
  for _ in $(seq 120); do
    if cellc $status 2>/dev/null | grep -q "$1"; then break; fi
    sleep 0.5
  done
  cellc $status
  cellc $status | grep -q "$1" || { echo "FAILED: $2"; exit 1; }
}

# Section 5's commands, from host c.
cellc() { ns c env PATH="$BIN:$PATH" "$@"; }
section5() { guide_commands 5 | grep " cell $1 " | head -1 | cut -d' ' -f2-; }

step "four hosts a-d (network namespaces) on a bridge; files in $RUN"
make_hosts

step "section 2: a router on each of hosts a-c, connected to the others"
for h in a b c; do
  args=(--listen "tcp/$(address "$h"):7447" --lease-ms 3000)
  for o in a b c; do [ "$o" = "$h" ] || args+=(--connect "tcp/$(address "$o"):7447"); done
  start "$h" "$RUN/router-$h.log" "$BIN/cell" router "${args[@]}"
done

step "section 3, as written in $GUIDE"
run_section 3
status=$(section5 status)
orders=$(section5 orders)
submit=$(section5 submit)
wait_live "5 live holons" "the cell of section 3 did not assemble"

step "section 5: $submit"
cellc $submit | tr '\n' ' '; echo
wait_all_done() {
  for _ in $(seq 240); do
    if cellc $orders | head -1 | grep -q ", 0 running"; then break; fi
    sleep 0.5
  done
  cellc $orders | head -1
  cellc $orders | head -1 | grep -Eq ": ([0-9]+) orders: \1 done" || { echo "FAILED: not every order is done"; cellc $orders; exit 1; }
}
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

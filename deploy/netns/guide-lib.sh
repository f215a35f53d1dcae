# Reading docs/deploy.md's commands and running them on the hosts of hosts.sh, for
# guide.sh and guide-standby.sh (sourced after hosts.sh, not run).
#
# The caller sets GUIDE (the guide's path), BIN (the binaries) and RUN (the run's
# directory), then calls `localize_configs` once.
#
# The guide's addresses 192.0.2.11-14 become 10.213.77.1-4 (hosts a-d), its directories
# under /var/lib/holarchy/ are the run's, and the configs it names in deploy/cells/demo/
# are copies in the run's directory with the same addresses replaced; nothing else of a
# command changes.

# The guide's addresses and directories on this machine.
localize() {
  sed -e 's/192\.0\.2\.1\([1-4]\)/10.213.77.\1/g' \
      -e "s#/var/lib/holarchy/#$RUN/var/#g" \
      -e 's#<any router>#10.213.77.3#g' \
      -e "s#deploy/cells/demo/#$RUN/demo/#g"
}

# Copies the configs of deploy/cells/demo into the run's directory, their addresses
# localized, and makes the hosts' directories under /var/lib/holarchy/ (as installing
# does).
localize_configs() {
  mkdir -p "$RUN/demo" "$RUN/var"
  local file h
  for file in deploy/cells/demo/*.toml; do localize < "$file" > "$RUN/demo/${file##*/}"; done
  for h in $HOSTS; do mkdir -p "$RUN/var/$h"; done
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

# Runs one long-running command of the guide on its host, logged in the run directory
# (host-program-N.log); HOSTNAME is the host's name, host-X, as `cell status` shows it.
run_guide_command() {
  local host=$1; shift
  local words
  read -r -a words <<< "$*"
  echo "host $host: $*"
  start "$host" "$RUN/$host-${words[0]}-${#STARTED[@]}.log" \
    env PATH="$BIN:$PATH" HOSTNAME="host-$host" "${words[@]}"
}

# Starts every command of the guide's section N on its host.
run_section() {
  local commands
  commands=$(guide_commands "$1")
  [ -n "$commands" ] || { echo "no commands found in section $1 of $GUIDE"; exit 1; }
  while read -r host command; do run_guide_command "$host" "$command"; done <<< "$commands"
}

# Section 2: a router on each of hosts a-c, connected to the others.
start_routers() {
  local h o args
  for h in a b c; do
    args=(--listen "tcp/$(address "$h"):7447" --lease-ms 3000)
    for o in a b c; do [ "$o" = "$h" ] || args+=(--connect "tcp/$(address "$o"):7447"); done
    start "$h" "$RUN/router-$h.log" "$BIN/cell" router "${args[@]}"
  done
}

# Section 5's commands, run on host c.
cellc() { ns c env PATH="$BIN:$PATH" "$@"; }
section5() { guide_commands 5 | grep " cell $1 " | head -1 | cut -d' ' -f2-; }

# Waits (60 s at most) until `cell status` (the command in $status) matches the extended
# regular expression TEXT, prints it; fails with WHY otherwise.
wait_live() {
  for _ in $(seq 120); do
    if cellc $status 2>/dev/null | grep -Eq "$1"; then break; fi
    sleep 0.5
  done
  cellc $status
  cellc $status | grep -Eq "$1" || { echo "FAILED: $2"; exit 1; }
}

# Waits (120 s at most) until no order runs (`cell orders`, the command in $orders);
# fails unless every order is done.
wait_all_done() {
  for _ in $(seq 240); do
    if cellc $orders | head -1 | grep -q ", 0 running"; then break; fi
    sleep 0.5
  done
  cellc $orders | head -1
  cellc $orders | head -1 | grep -Eq ": ([0-9]+) orders: \1 done" || { echo "FAILED: not every order is done"; cellc $orders; exit 1; }
}

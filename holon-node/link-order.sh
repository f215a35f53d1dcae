#!/usr/bin/env bash
# Makes holon-node/link-order.txt: the functions of the release `holon-node` that a
# resource holon runs, in the order it first runs them, for the linker to place together
# (holon-node/build.rs; docs/benchmarks.md, "Code in the order it runs").
#
# How: the bench's booking, cycle and holon sections (`bench all --only
# booking,cycle,holon --scale 0`: `robot1` started and brought to ready with its
# controller connected and its journal open, bookings and service cycles served, idle,
# five holons hot-added and killed) with every holon-node under valgrind's callgrind,
# each writing what it ran every 500,000 basic blocks (`--dump-every-bb`; not
# `callgrind_control`, whose vgdb holds a holon the bench kills and the bench waits
# forever). A function is listed once, at the first dump that ran it, `robot1`'s dumps
# first, then the other holons'; only names the binary defines. The order within a
# dump is callgrind's.
#
# Needs valgrind and python3, and the release binaries built:
#   nice -n 19 cargo build --release --bins
#   holon-node/link-order.sh            # writes holon-node/link-order.txt
#   nice -n 19 cargo build --release --bins   # relinks holon-node with it
# The names are the release build's (fat LTO): build and profile with the same
# toolchain and Cargo.lock as the build that will use the file. Takes under a minute.
# `holon-node/link-order.sh --check` says how many of the file's names the release
# binary defines (all of them when the file is current; a new toolchain or dependency
# renames many, and the file should then be made again).
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
release=${RELEASE_DIR:-$root/target/release}
if [ "${1:-}" = --check ]; then
    file=$root/holon-node/link-order.txt
    nm --defined-only "$release/holon-node" | awk '{print $3}' | sort -u >"${TMPDIR:-/tmp}/link-order.defined.$$"
    found=$(sort -u "$file" | comm -12 - "${TMPDIR:-/tmp}/link-order.defined.$$" | wc -l)
    rm -f "${TMPDIR:-/tmp}/link-order.defined.$$"
    echo "$found of $(wc -l <"$file") names in $file are defined by $release/holon-node"
    exit 0
fi
out=${1:-$root/holon-node/link-order.txt}
samples=${SAMPLES:-200}
work=$(mktemp -d)
trap '[ -n "${KEEP:-}" ] && echo "kept $work" >&2 || rm -rf "$work"' EXIT

for tool in valgrind python3; do
    command -v "$tool" >/dev/null || { echo "link-order.sh: $tool is needed" >&2; exit 1; }
done
[ -x "$release/holon-node" ] && [ -x "$release/bench" ] || {
    echo "link-order.sh: build first: cargo build --release --bins" >&2
    exit 1
}

# The bench's binaries, with holon-node run under callgrind.
mkdir -p "$work/bin" "$work/cg"
for f in "$release"/*; do
    [ -f "$f" ] && [ -x "$f" ] && ln -s "$f" "$work/bin/"
done
rm "$work/bin/holon-node"
cat >"$work/bin/holon-node" <<EOF
#!/bin/sh
exec valgrind --tool=callgrind --vgdb=no --demangle=no --dump-instr=no \
    --compress-strings=no --compress-pos=no --dump-every-bb=${DUMP_BB:-500000} \
    --callgrind-out-file=$work/cg/cg.%p "$release/holon-node" "\$@"
EOF
chmod +x "$work/bin/holon-node"

HOLARCHY_BIN_DIR="$work/bin" "$release/bench" all --only booking,cycle,holon --scale 0 \
    --samples "$samples" --out "$work/bench.json" >"$work/bench.out" 2>&1 || {
    cat "$work/bench.out" >&2
    echo "link-order.sh: the bench failed" >&2
    exit 1
}

nm --defined-only "$release/holon-node" | awk '$2 ~ /^[tTwW]$/ {print $3}' >"$work/defined"
python3 - "$work/cg" "$work/defined" "$out" <<'EOF'
import os, re, sys

cg, defined, out = sys.argv[1:]
defined = set(open(defined).read().split())
# Dumps are cg.PID.N (N from 1, in order) and cg.PID at exit; robot1 is the first
# holon the bench starts, so the lowest pid.
def key(name):
    parts = name.split(".")
    part = int(parts[2]) if len(parts) > 2 else 1 << 30
    return (int(parts[1]), part)
seen, order = set(), []
for name in sorted(os.listdir(cg), key=key):
    for line in open(os.path.join(cg, name), errors="replace"):
        if line.startswith(("fn=", "cfn=")):
            fn = re.sub(r"'\d+$", "", line.split("=", 1)[1].strip())
            if fn in defined and fn not in seen:
                seen.add(fn)
                order.append(fn)
with open(out, "w") as f:
    f.write("".join(fn + "\n" for fn in order))
print(f"{len(order)} functions of {len(defined)} to {out}")
EOF

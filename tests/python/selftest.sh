#!/usr/bin/env bash
# Python-to-Python check of the reference peer on loopback (port $2, default 28765).
# Usage: tests/python/selftest.sh [VENV_PYTHON] [PORT]
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
PY="${1:-$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)/target/pyvenv/bin/python}"
PORT="${2:-28765}"
PEER="$HERE/peer.py"
TMP="$(mktemp -d)"
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$TMP"; }
trap cleanup EXIT
pass=0; fail=0
check() { if "$@"; then pass=$((pass+1)); else echo "FAILED: $*" >&2; fail=$((fail+1)); fi; }

# publish -> subscribe, one kind at a time
for kv in "str:hi {i}" "int:{i}" "float:2.5" "bool:true" "bytes:0a0b" "float_msg:1.25"; do
    kind="${kv%%:*}"; val="${kv#*:}"
    timeout 20 "$PY" "$PEER" subscribe --port "$PORT" --name sub --channel "self/$kind" \
        --count 3 --timeout 8 >"$TMP/sub.out" 2>"$TMP/sub.err" &
    sp=$!; pids+=("$sp")
    for _ in $(seq 100); do grep -q READY "$TMP/sub.err" && break; sleep 0.05; done
    timeout 20 "$PY" "$PEER" publish --port "$PORT" --name pub --channel "self/$kind" \
        --kind "$kind" --value "$val" --count 3 --period 0.02 >/dev/null 2>&1
    rc=0; wait "$sp" || rc=$?
    check [ "$rc" -eq 0 ]
    check [ "$(wc -l <"$TMP/sub.out")" -eq 3 ]
    check python3 -c '
import json, sys
want = {"str": "str", "int": "int", "float": "float", "bool": "bool", "bytes": "bytes", "float_msg": "float"}[sys.argv[2]]
recs = [json.loads(l) for l in open(sys.argv[1])]
assert all(r["type"] == want for r in recs), recs
assert [r["lead"] for r in recs] == [1, 1, 1], recs
' "$TMP/sub.out" "$kind"
done

# discovery: a lingering publisher and subscriber are listed with their channels
timeout 20 "$PY" "$PEER" publish --port "$PORT" --name disc_pub --channel self/d --kind int \
    --value 1 --count 1 --linger 3 >/dev/null 2>&1 & pids+=($!)
timeout 20 "$PY" "$PEER" subscribe --port "$PORT" --name disc_sub --channel self/d \
    --count 99 --timeout 3 >/dev/null 2>&1 & pids+=($!)
timeout 20 "$PY" "$PEER" nodes --port "$PORT" --name lister --for 1.5 >"$TMP/nodes.json" 2>/dev/null
check python3 -c '
import json, sys
nodes = {n["name"]: n for n in json.load(open(sys.argv[1]))}
assert {"disc_pub", "disc_sub"} <= set(nodes), nodes
ch = {c["name"]: c for c in nodes["disc_pub"]["channels"]}
assert ch["self/d"]["published"] and ch["__nodes"]["published"], ch
ch = {c["name"]: c for c in nodes["disc_sub"]["channels"]}
assert ch["self/d"]["subscribed"], ch
' "$TMP/nodes.json"
wait || true
echo "selftest: $pass passed, $fail failed"
[ "$fail" -eq 0 ]

#!/usr/bin/env bash
# Self-test of netns.sh (root only): 3 hosts, multicast delivery, loss, block-mcast,
# unicast, isolation from the root namespace, clean teardown. No cargo needed.
#   bash tests/netns/selftest.sh
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
NETNS="$HERE/netns.sh"
PROBE="$HERE/mcast.py"
TAG=nsst$$
WORK=$(mktemp -d)
SNIFF_PID=""
BRSNIFF_PID=""
pass=0 fail=0

cleanup() {
    [[ -n $SNIFF_PID ]] && kill "$SNIFF_PID" 2>/dev/null || true
    "$NETNS" down "$TAG"
    rm -rf "$WORK"
}
trap cleanup EXIT

ok() { echo "  ok: $*"; pass=$((pass + 1)); }
bad() { echo "  FAIL: $*"; fail=$((fail + 1)); }
expect() { # expect DESC ACTUAL OP EXPECTED   (OP: -eq -ge -le)
    local good=0
    case $3 in
        -eq) (($2 == $4)) && good=1 ;;
        -ge) (($2 >= $4)) && good=1 ;;
        -le) (($2 <= $4)) && good=1 ;;
    esac
    if ((good)); then ok "$1 ($2 $3 $4)"; else bad "$1 (got $2, want $3 $4)"; fi
}
field() { python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])' "$1" "$2"; }
ms() { date +%s%N; }

# recv HOST NAME [extra args]: start a receiver in the background, wait until joined.
recv() {
    local host=$1 name=$2; shift 2
    rm -f "$WORK/$name.ready"
    "$NETNS" exec "$TAG" "$host" python3 "$PROBE" recv --iface "${IP[$host]}" \
        --ready "$WORK/$name.ready" "$@" >"$WORK/$name.json" &
    for _ in $(seq 100); do [[ -e $WORK/$name.ready ]] && return 0; sleep 0.05; done
    echo "receiver $name not ready" >&2; return 1
}

# Wait for the background receivers (they stop after 1 s idle or --max-secs).
wait_receivers() {
    local j
    for j in $(jobs -p); do [[ $j == "$SNIFF_PID" || $j == "$BRSNIFF_PID" ]] || wait "$j"; done
}

"$NETNS" check

# Root namespace state before.
ip -br link >"$WORK/links.before"
# /proc/net/igmp without loopback (other processes' loopback tests join groups there)
root_igmp() { awk '/^[0-9]/ { keep = ($2 != "lo") } keep' /proc/net/igmp; }
root_igmp >"$WORK/igmp.before"
root_maddr() { ip maddr show | awk '/^[0-9]/ { keep = ($2 != "lo") } keep'; }
root_maddr >"$WORK/maddr.before"

t0=$(ms)
"$NETNS" up "$TAG" 3 >"$WORK/hosts" 2>"$WORK/subnet"
t1=$(ms)
echo "up 3 hosts: $(((t1 - t0) / 1000000)) ms; $(cat "$WORK/subnet")"
cat "$WORK/hosts"
declare -A IP
i=1
while read -r _ addr; do IP[$i]=$addr; i=$((i + 1)); done <"$WORK/hosts"
SUBNET=$(cut -d' ' -f2 "$WORK/subnet")

# Sniff every root-namespace interface for anything from the test subnet, to a
# 239/8 group, or IGMP, while the test runs (bounded to 120 s).
cat >"$WORK/sniff.py" <<'EOF'
import ipaddress, json, signal, socket, sys, time
net = ipaddress.ip_network(sys.argv[1])
s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x0003))
s.settimeout(0.2)
hits = {"from_subnet": 0, "to_239": 0, "igmp": 0, "frames_seen": 0}
stop = False
def on_term(*_):
    global stop
    stop = True
signal.signal(signal.SIGTERM, on_term)
end = time.monotonic() + 120
while not stop and time.monotonic() < end:
    try:
        f, addr = s.recvfrom(65535)
    except socket.timeout:
        continue
    hits["frames_seen"] += 1
    if f[12:14] != b"\x08\x00" or len(f) < 34:
        continue
    ip = f[14:]
    src, dst = ipaddress.ip_address(ip[12:16]), ipaddress.ip_address(ip[16:20])
    if src in net or dst in net: hits["from_subnet"] += 1
    if dst in ipaddress.ip_network("239.0.0.0/8"): hits["to_239"] += 1
    if ip[9] == 2: hits["igmp"] += 1
print(json.dumps(hits))
EOF
python3 "$WORK/sniff.py" "$SUBNET" >"$WORK/sniff.json" &
SNIFF_PID=$!
# The same sniffer inside the bridge namespace shows what the root one should miss.
"$NETNS" exec "$TAG" br python3 "$WORK/sniff.py" "$SUBNET" >"$WORK/sniff-br.json" &
BRSNIFF_PID=$!
# Positive control for the sniffer: one datagram on the root namespace's loopback.
sleep 0.3
python3 -c 'import socket; socket.socket(socket.AF_INET, socket.SOCK_DGRAM).sendto(b"sniff-control", ("127.0.0.1", 9))'

echo "1. multicast h1 -> 239.1.2.3:30000, TTL 1"
recv 2 a2 --port 30000
recv 3 a3 --port 30000
"$NETNS" exec "$TAG" 1 python3 "$PROBE" send --iface "${IP[1]}" --port 30000 --count 20 >"$WORK/a1.json"
wait_receivers
expect "h2 received" "$(field "$WORK/a2.json" unique)" -eq 20
expect "h3 received" "$(field "$WORK/a3.json" unique)" -eq 20

echo "2. loss 0.2 on h2, 2000 datagrams"
"$NETNS" loss "$TAG" 2 0.5
"$NETNS" loss "$TAG" 2 0.2 # replaces the 0.5 rule
rules=$("$NETNS" exec "$TAG" 2 iptables -t raw -S | grep -c statistic || true)
expect "loss rules in h2 after two 'loss' calls" "$rules" -eq 1
recv 2 b2 --port 30001
recv 3 b3 --port 30001
"$NETNS" exec "$TAG" 1 python3 "$PROBE" send --iface "${IP[1]}" --port 30001 --count 2000 >"$WORK/b1.json"
wait_receivers
r2=$(field "$WORK/b2.json" unique)
r3=$(field "$WORK/b3.json" unique)
echo "  sender: $(cat "$WORK/b1.json")"
echo "  h2 received $r2/2000 (loss $(awk -v r="$r2" 'BEGIN{printf "%.1f%%", (2000-r)/20}')), h3 received $r3/2000 (loss $(awk -v r="$r3" 'BEGIN{printf "%.1f%%", (2000-r)/20}'))"
expect "h2 loss in 15..25% (received)" "$r2" -ge 1500
expect "h2 loss in 15..25% (received)" "$r2" -le 1700
expect "h3 no loss" "$r3" -eq 2000
"$NETNS" loss "$TAG" 2 0
rules=$("$NETNS" exec "$TAG" 2 iptables -t raw -S | grep -c statistic || true)
expect "loss rules in h2 after 'loss 0'" "$rules" -eq 0

echo "3. block-mcast on h3"
"$NETNS" block-mcast "$TAG" 3
"$NETNS" block-mcast "$TAG" 3 # idempotent
n=$("$NETNS" exec "$TAG" br ebtables -L FORWARD | grep -c 224.0.0.0 || true)
expect "bridge rules after two block-mcast calls" "$n" -eq 2
recv 2 c2 --port 30002 --max-secs 3
recv 3 c3 --port 30002 --max-secs 3
"$NETNS" exec "$TAG" 1 python3 "$PROBE" send --iface "${IP[1]}" --port 30002 --count 100 >"$WORK/c1.json"
wait_receivers
expect "h2 receives h1's multicast" "$(field "$WORK/c2.json" unique)" -eq 100
expect "blocked h3 receives nothing" "$(field "$WORK/c3.json" received)" -eq 0

recv 1 d1 --port 30003 --max-secs 3
recv 2 d2 --port 30003 --max-secs 3
"$NETNS" exec "$TAG" 3 python3 "$PROBE" send --iface "${IP[3]}" --port 30003 --count 100 >"$WORK/d3.json"
wait_receivers
echo "  h3 sender: $(cat "$WORK/d3.json")"
expect "blocked h3's sendto errors" "$(field "$WORK/d3.json" errors)" -eq 0
expect "h1 receives nothing from blocked h3" "$(field "$WORK/d1.json" received)" -eq 0
expect "h2 receives nothing from blocked h3" "$(field "$WORK/d2.json" received)" -eq 0

for pair in "1 3" "3 1"; do
    set -- $pair
    "$NETNS" exec "$TAG" "$2" python3 "$PROBE" urecv --iface "${IP[$2]}" --port 30004 --max-secs 3 \
        --ready "$WORK/u$2.ready" >"$WORK/u$2.json" &
    for _ in $(seq 100); do [[ -e $WORK/u$2.ready ]] && break; sleep 0.05; done
    "$NETNS" exec "$TAG" "$1" python3 "$PROBE" usend --iface "${IP[$1]}" --dest "${IP[$2]}" --port 30004 --count 100 >/dev/null
    wait_receivers
    expect "unicast h$1 -> h$2 with h3 blocked" "$(field "$WORK/u$2.json" unique)" -eq 100
done

"$NETNS" unblock-mcast "$TAG" 3
recv 3 e3 --port 30005
"$NETNS" exec "$TAG" 1 python3 "$PROBE" send --iface "${IP[1]}" --port 30005 --count 50 >/dev/null
wait_receivers
expect "h3 receives again after unblock-mcast" "$(field "$WORK/e3.json" unique)" -eq 50

echo "4. isolation from the root namespace"
kill "$SNIFF_PID" "$BRSNIFF_PID"; wait "$SNIFF_PID" "$BRSNIFF_PID" || true; SNIFF_PID="" BRSNIFF_PID=""
echo "  bridge-namespace sniffer: $(cat "$WORK/sniff-br.json")"
echo "  root sniffer: $(cat "$WORK/sniff.json")"
expect "bridge namespace saw IGMP" "$(field "$WORK/sniff-br.json" igmp)" -ge 1
expect "bridge namespace saw 239/8 traffic" "$(field "$WORK/sniff-br.json" to_239)" -ge 1000
expect "root sniffer works (saw the loopback control)" "$(field "$WORK/sniff.json" frames_seen)" -ge 1
expect "root frames from/to test subnet" "$(field "$WORK/sniff.json" from_subnet)" -eq 0
expect "root frames to 239/8" "$(field "$WORK/sniff.json" to_239)" -eq 0
if root_igmp | cmp -s "$WORK/igmp.before" -; then ok "root /proc/net/igmp (non-lo) unchanged"; else bad "root /proc/net/igmp changed"; root_igmp | diff "$WORK/igmp.before" - || true; fi
if root_maddr | cmp -s "$WORK/maddr.before" -; then ok "root ip maddr (non-lo) unchanged"; else bad "root ip maddr changed"; fi
if ip -br link | cmp -s "$WORK/links.before" -; then ok "root links unchanged"; else bad "root links changed"; fi

echo "5. teardown"
"$NETNS" exec "$TAG" 2 sleep 30 & # a leftover process must not block down
sleep 0.2
t0=$(ms)
"$NETNS" down "$TAG"
t1=$(ms)
echo "  down: $(((t1 - t0) / 1000000)) ms"
left=$("$NETNS" list "$TAG" | wc -l)
expect "namespaces left" "$left" -eq 0
"$NETNS" down "$TAG" && ok "second down succeeds"
wait || true
if ip -br link | cmp -s "$WORK/links.before" -; then ok "root links unchanged after down"; else bad "root links changed after down"; fi

echo "$pass passed, $fail failed"
((fail == 0))

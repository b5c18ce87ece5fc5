#!/usr/bin/env bash
# netns.sh - throw-away multi-host test networks made of Linux network namespaces.
#
# Every "host" is a network namespace "${TAG}-hI" with one interface "eth0"
# (address 10.X.Y.I/24, lo up, multicast on, a route for 224.0.0.0/4 via eth0).
# The hosts' eth0 are veth pairs whose other ends ("hI") are ports of bridge
# "br0", which lives in its own namespace "${TAG}-br". Nothing is created in,
# attached to or routed through the root namespace: no veth into it, no default
# route, no NAT. Traffic can only go between the hosts of one TAG.
# X.Y comes from a hash of TAG (so parallel TAGs get different subnets; even if
# two collided nothing would break, every TAG is an isolated island).
#
# Commands (all need root):
#   netns.sh check                  prerequisites: root, ip, iptables (never
#                                   installed here: .ci/run does), and that
#                                   namespaces + veth + bridge can be created here
#   netns.sh up TAG N               (re)create TAG with N hosts (1..250). A TAG that
#                                   exists already is torn down first, so `up` always
#                                   yields a fresh topology. stdout: one line per
#                                   host, "<netns> <ip>"; stderr: "subnet 10.X.Y.0/24"
#   netns.sh down TAG               delete the TAG's namespaces (killing processes
#                                   still running in them) and with them every link;
#                                   exit 0 even if nothing is there
#   netns.sh exec TAG HOST CMD...   run CMD inside host HOST (1-based; "br" = the
#                                   bridge namespace); exit status is CMD's
#   netns.sh loss TAG HOST PROB [DST]
#                                   host HOST drops incoming UDP to DST (default
#                                   239.0.0.0/8) with probability PROB (0 < PROB <= 1;
#                                   PROB 0 removes the rule). Replaces the previous
#                                   loss rule of that host. Done in the raw table's
#                                   PREROUTING: senders never see an error.
#   netns.sh block-mcast TAG HOST   cut host HOST off multicast in both directions:
#                                   incoming dropped in the host (raw PREROUTING,
#                                   -d 224.0.0.0/4, except on lo), outgoing dropped at the bridge
#                                   port (ebtables in "${TAG}-br"), so the host's
#                                   sendto still succeeds. Unicast is untouched.
#   netns.sh unblock-mcast TAG HOST undo block-mcast
#   netns.sh only-tcp TAG HOST PORT host HOST takes nothing on eth0 but TCP to or
#                                   from PORT (raw PREROUTING): one TCP path to the
#                                   other hosts and nothing else (no UDP, no ICMP)
#   netns.sh cut TAG HOST           host HOST takes nothing at all on eth0 (raw
#                                   PREROUTING), as if out of radio range; its
#                                   sockets see no error
#   netns.sh uncut TAG HOST         undo cut
#   netns.sh subnet TAG             print 10.X.Y.0/24
#   netns.sh addr TAG HOST          print host HOST's address
#   netns.sh list [TAG]             list existing namespaces made by this tool
#
# How tests use it
#   Shell:
#       NETNS=tests/netns/netns.sh
#       tag=pc$$                       # unique per test process
#       trap '"$NETNS" down "$tag"' EXIT
#       "$NETNS" up "$tag" 3 > hosts.txt
#       "$NETNS" exec "$tag" 1 ./my-peer --iface 10.X.Y.1 &
#   Rust: run `netns.sh up TAG N` with std::process::Command, parse the
#   "<netns> <ip>" lines, keep them in a guard struct whose Drop runs
#   `netns.sh down TAG` (Drop also runs when a test panics):
#       struct Net { tag: String, hosts: Vec<(String, Ipv4Addr)> }
#       impl Drop for Net {
#           fn drop(&mut self) {
#               let _ = Command::new(NETNS_SH).args(["down", &self.tag]).status();
#           }
#       }
#   Create the guard before checking up's exit status: `down` is harmless when
#   nothing is there, and a failing `up` removes what it built anyway. Start peers with
#   `netns.sh exec TAG I <binary> ...` (or `ip netns exec <netns> ...`) and bind
#   and join on the host's ip. Use a TAG unique per test (e.g. a short test name +
#   process id); namespace names are "${TAG}-h1".., so keep TAG short and free of
#   '/' and spaces ([A-Za-z0-9_.-], at most 40 characters). Skip (don't fail) the
#   test when `netns.sh check` fails and the environment does not require it.
#   A TAG left behind by a killed test is removed by the next `up` or `down` of
#   the same TAG; `netns.sh list` shows leftovers.
#
# Environment
#   NETNS_IPV6=1     keep IPv6 enabled in the namespaces (default: disabled, which
#                    keeps DAD/MLD chatter out of the test network)
#   NETNS_IPTABLES   iptables binary to use (default: iptables, falling back to
#                    iptables-legacy if the default backend does not work)
#
# Kernel notes (6.18 test VMs): no netem qdisc and no tc gact action, so loss and
# blocking are done with netfilter: iptables (nft backend by default, legacy also
# works) with the statistic match, and ebtables (nft backend, shipped in the
# Debian 'iptables' package as ebtables-nft) for the bridge. Fallback for the
# bridge when ebtables is missing: iptables -m physdev in the bridge namespace
# (br_netfilter, bridge-nf-call-iptables=1).

set -Eeuo pipefail

PROG=${0##*/}
LOSS_CHAIN=PCAST_LOSS
BLOCK_CHAIN=PCAST_BLOCK
ONLY_CHAIN=PCAST_ONLY
CUT_CHAIN=PCAST_CUT

die() { echo "$PROG: $*" >&2; exit 1; }
usage() { sed -n '/^# Commands/,/^# How tests/p' "$0" | sed '$d; s/^# \{0,1\}//' >&2; exit 2; }

check_tag() {
    [[ ${1:-} =~ ^[A-Za-z0-9_.-]{1,40}$ ]] || die "bad TAG '${1:-}' (use [A-Za-z0-9_.-], 1..40 chars)"
}

need_root() { [[ $(id -u) -eq 0 ]] || die "must run as root (namespaces, iptables)"; }

# 10.X.Y.0/24 from a hash of TAG; X in 64..191, Y in 0..255.
subnet_prefix() {
    local h
    h=$(printf '%s' "$1" | cksum | cut -d' ' -f1)
    echo "10.$((64 + (h / 256) % 128)).$((h % 256))"
}

br_ns() { echo "$1-br"; }
host_ns() {
    local tag=$1 host=$2
    [[ $host =~ ^[0-9]+$ ]] && ((host >= 1 && host <= 250)) || die "bad HOST '$host' (1-based number)"
    echo "$tag-h$host"
}
ns_exists() { [[ -e /run/netns/$1 ]]; }
require_ns() { ns_exists "$1" || die "namespace $1 does not exist (did you run '$PROG up'?)"; }

# Namespaces of TAG: "${TAG}-br" and "${TAG}-h<digits>".
tag_namespaces() {
    local tag=$1 n
    { ip netns list 2>/dev/null || true; } | awk '{print $1}' | while read -r n; do
        if [[ $n == "$tag-br" || $n =~ ^"$tag"-h[0-9]+$ ]]; then echo "$n"; fi
    done
}

with_lock() {
    # Serialize all up/down calls (each takes ~50 ms; one lock file for all TAGs
    # leaves no per-TAG litter behind).
    local tag=$1; shift
    mkdir -p /run/lock
    exec 9>/run/lock/pulicast-netns.lock
    flock -w 120 9 || die "timeout waiting for /run/lock/pulicast-netns.lock (TAG $tag)"
    "$@"
}

# ---------------------------------------------------------------- iptables
IPT=""
pick_iptables() {
    # $1: a namespace to probe in. Picks a backend that can use the raw table.
    [[ -n $IPT ]] && return 0
    local c cands=()
    if [[ -n ${NETNS_IPTABLES:-} ]]; then cands=("$NETNS_IPTABLES"); else cands=(iptables iptables-nft iptables-legacy); fi
    for c in "${cands[@]}"; do
        command -v "$c" >/dev/null 2>&1 || continue
        if ip netns exec "$1" "$c" -w -t raw -S PREROUTING >/dev/null 2>&1; then IPT=$c; return 0; fi
    done
    die "no working iptables (tried: ${cands[*]}); run '$PROG check'"
}
ipt() { local ns=$1; shift; ip netns exec "$ns" "$IPT" -w "$@"; }

# Make sure raw-table chain $2 exists, is empty, and is jumped to from PREROUTING.
reset_raw_chain() {
    local ns=$1 chain=$2
    ipt "$ns" -t raw -N "$chain" 2>/dev/null || true
    ipt "$ns" -t raw -F "$chain"
    ipt "$ns" -t raw -C PREROUTING -j "$chain" 2>/dev/null || ipt "$ns" -t raw -A PREROUTING -j "$chain"
}

# ---------------------------------------------------------------- commands
cmd_check() {
    need_root
    command -v ip >/dev/null || die "'ip' (iproute2) not found; apt-get install -y iproute2"
    # Never installs anything: the machine is the caller's (.ci/run installs it).
    command -v iptables >/dev/null || command -v iptables-legacy >/dev/null ||
        die "'iptables' not found; install the Debian package 'iptables' (.ci/run does)"
    command -v flock >/dev/null || die "'flock' (util-linux) not found"
    local probe="netns-check-$$" ok=1
    ip netns add "$probe" 2>/dev/null || die "cannot create network namespaces here (ip netns add failed)"
    {
        ip -n "$probe" link add br0 type bridge &&
            ip -n "$probe" link add v0 type veth peer name v1 &&
            ip -n "$probe" link set v0 master br0
    } >/dev/null 2>&1 || { ok=0; echo "$PROG: cannot create bridge/veth inside a namespace" >&2; }
    if ((ok)); then
        IPT=""
        ( pick_iptables "$probe" && ipt "$probe" -t raw -A PREROUTING -p udp -d 239.0.0.0/8 \
            -m statistic --mode random --probability 0.5 -j DROP ) >/dev/null 2>&1 ||
            { ok=0; echo "$PROG: iptables raw table / statistic match unusable in a namespace" >&2; }
        if ip netns exec "$probe" ebtables -A FORWARD -i v0 -p IPv4 --ip-dst 224.0.0.0/4 -j DROP >/dev/null 2>&1; then
            echo "bridge filtering: ebtables" >&2
        elif ip netns exec "$probe" "${IPT:-iptables}" -w -A FORWARD -m physdev --physdev-in v0 -d 224.0.0.0/4 -j DROP >/dev/null 2>&1; then
            echo "bridge filtering: iptables physdev (no ebtables)" >&2
        else
            echo "$PROG: warning: no bridge filtering (ebtables / physdev); block-mcast unavailable" >&2
        fi
    fi
    ip netns del "$probe" 2>/dev/null || true
    ((ok)) || exit 1
    echo "ok: root, ip, $(command -v iptables || command -v iptables-legacy), namespaces work" >&2
}

cmd_down_locked() {
    local tag=$1 ns pids i
    local nss
    nss=$(tag_namespaces "$tag")
    [[ -z $nss ]] && return 0
    # Processes still inside would keep the namespace (and its links) alive.
    for ns in $nss; do
        pids=$(ip netns pids "$ns" 2>/dev/null || true)
        [[ -n $pids ]] && kill -TERM $pids 2>/dev/null || true
    done
    for ((i = 0; i < 20; i++)); do
        pids=""
        for ns in $nss; do pids+=$(ip netns pids "$ns" 2>/dev/null || true); done
        [[ -z $pids ]] && break
        sleep 0.05
    done
    for ns in $nss; do
        pids=$(ip netns pids "$ns" 2>/dev/null || true)
        [[ -n $pids ]] && kill -KILL $pids 2>/dev/null || true
    done
    # Deleting a namespace destroys its veth ends, which takes the peers along.
    for ns in $nss; do ip netns del "$ns" 2>/dev/null || true; done
    for ns in $nss; do
        ns_exists "$ns" && { ip netns del "$ns" 2>/dev/null || rm -f "/run/netns/$ns" || true; }
    done
    return 0
}

cmd_down() {
    check_tag "${1:-}"
    need_root
    with_lock "$1" cmd_down_locked "$1"
}

cmd_up_locked() {
    local tag=$1 n=$2 i pfx br ns
    pfx=$(subnet_prefix "$tag")
    br=$(br_ns "$tag")
    cmd_down_locked "$tag"
    # Anything failing from here on: remove what was built, report, fail.
    # shellcheck disable=SC2154 # rc is assigned inside the trap
    trap 'rc=$?; cmd_down_locked "$tag"; echo "$PROG: up $tag failed" >&2; exit $rc' ERR

    local sys="net.ipv6.conf.all.disable_ipv6=1 net.ipv6.conf.default.disable_ipv6=1"
    [[ ${NETNS_IPV6:-0} == 1 ]] && sys=""

    ip netns add "$br"
    [[ -n $sys ]] && ip netns exec "$br" sysctl -qw $sys
    # No STP, no forwarding delay, no IGMP snooping: every multicast frame is
    # flooded to every port, whatever the hosts' IGMP reports say.
    ip -n "$br" -b - <<EOF
link set lo up
link add br0 type bridge stp_state 0 forward_delay 0 mcast_snooping 0
link set br0 up
EOF
    for ((i = 1; i <= n; i++)); do
        ns="$tag-h$i"
        ip netns add "$ns"
        [[ -n $sys ]] && ip netns exec "$ns" sysctl -qw $sys
    done
    {
        for ((i = 1; i <= n; i++)); do
            echo "link add h$i type veth peer name eth0 netns $tag-h$i"
            echo "link set h$i master br0"
            echo "link set h$i up"
        done
    } | ip -n "$br" -b -
    for ((i = 1; i <= n; i++)); do
        ip -n "$tag-h$i" -b - <<EOF
link set lo up
link set eth0 multicast on
addr add $pfx.$i/24 dev eth0
link set eth0 up
route add 224.0.0.0/4 dev eth0
EOF
    done
    trap - ERR
    echo "subnet $pfx.0/24" >&2
    for ((i = 1; i <= n; i++)); do echo "$tag-h$i $pfx.$i"; done
}

cmd_up() {
    [[ $# -eq 2 ]] || usage
    check_tag "$1"
    [[ $2 =~ ^[0-9]+$ ]] && (($2 >= 1 && $2 <= 250)) || die "bad N '$2' (1..250)"
    need_root
    with_lock "$1" cmd_up_locked "$1" "$2"
}

cmd_exec() {
    [[ $# -ge 3 ]] || usage
    local tag=$1 host=$2 ns; shift 2
    check_tag "$tag"
    if [[ $host == br ]]; then ns=$(br_ns "$tag"); else ns=$(host_ns "$tag" "$host"); fi
    require_ns "$ns"
    exec ip netns exec "$ns" "$@"
}

cmd_loss() {
    [[ $# -eq 3 || $# -eq 4 ]] || usage
    local tag=$1 host=$2 prob=$3 dst=${4:-239.0.0.0/8} ns
    check_tag "$tag"
    ns=$(host_ns "$tag" "$host")
    [[ $prob =~ ^(0(\.[0-9]+)?|1(\.0*)?|\.[0-9]+)$ ]] || die "bad PROB '$prob' (0..1)"
    need_root
    require_ns "$ns"
    pick_iptables "$ns"
    reset_raw_chain "$ns" "$LOSS_CHAIN"
    if awk -v p="$prob" 'BEGIN { exit !(p > 0) }'; then
        ipt "$ns" -t raw -A "$LOSS_CHAIN" -p udp -d "$dst" \
            -m statistic --mode random --probability "$prob" -j DROP
    fi
}

# Bridge-side drop of multicast from (-i) and to (-o) port hI. $3: -A or -D.
bridge_block() {
    local br=$1 port=$2 op=$3 dir k
    if [[ $op == -D ]]; then
        for dir in in out; do
            for ((k = 0; k < 10; k++)); do
                ip netns exec "$br" ebtables -D FORWARD "-${dir:0:1}" "$port" -p IPv4 --ip-dst 224.0.0.0/4 -j DROP >/dev/null 2>&1 || break
            done
            for ((k = 0; k < 10; k++)); do
                ipt "$br" -D FORWARD -m physdev "--physdev-$dir" "$port" -d 224.0.0.0/4 -j DROP >/dev/null 2>&1 || break
            done
        done
        return 0
    fi
    # Only outgoing traffic of the host (-i = frames entering the bridge from it)
    # needs the bridge; incoming is dropped in the host, but dropping it at the
    # bridge too keeps the host's rx counters clean.
    if command -v ebtables >/dev/null &&
        ip netns exec "$br" ebtables -A FORWARD -i "$port" -p IPv4 --ip-dst 224.0.0.0/4 -j DROP 2>/dev/null; then
        ip netns exec "$br" ebtables -A FORWARD -o "$port" -p IPv4 --ip-dst 224.0.0.0/4 -j DROP
    else
        # br_netfilter fallback: bridged IPv4 goes through the bridge namespace's
        # iptables FORWARD chain when bridge-nf-call-iptables is 1.
        ip netns exec "$br" sysctl -qw net.bridge.bridge-nf-call-iptables=1 ||
            die "no ebtables and no br_netfilter: cannot filter at the bridge"
        ipt "$br" -A FORWARD -m physdev --physdev-in "$port" -d 224.0.0.0/4 -j DROP
        ipt "$br" -A FORWARD -m physdev --physdev-out "$port" -d 224.0.0.0/4 -j DROP
    fi
}

cmd_block_mcast() {
    [[ $# -eq 2 ]] || usage
    local tag=$1 host=$2 ns br
    check_tag "$tag"
    ns=$(host_ns "$tag" "$host")
    br=$(br_ns "$tag")
    need_root
    require_ns "$ns"; require_ns "$br"
    pick_iptables "$ns"
    reset_raw_chain "$ns" "$BLOCK_CHAIN"
    # Not on lo: nodes pinned to loopback inside the host keep hearing each
    # other (a host that is a site of its own, in the bridge's tests).
    ipt "$ns" -t raw -A "$BLOCK_CHAIN" ! -i lo -d 224.0.0.0/4 -j DROP
    bridge_block "$br" "h$host" -D
    bridge_block "$br" "h$host" -A
}

cmd_unblock_mcast() {
    [[ $# -eq 2 ]] || usage
    local tag=$1 host=$2 ns br
    check_tag "$tag"
    ns=$(host_ns "$tag" "$host")
    br=$(br_ns "$tag")
    need_root
    require_ns "$ns"; require_ns "$br"
    pick_iptables "$ns"
    ipt "$ns" -t raw -F "$BLOCK_CHAIN" 2>/dev/null || true
    bridge_block "$br" "h$host" -D
}

cmd_only_tcp() {
    [[ $# -eq 3 ]] || usage
    local tag=$1 host=$2 port=$3 ns
    check_tag "$tag"
    [[ $port =~ ^[0-9]{1,5}$ ]] || die "bad PORT '$port'"
    ns=$(host_ns "$tag" "$host")
    need_root
    require_ns "$ns"
    pick_iptables "$ns"
    reset_raw_chain "$ns" "$ONLY_CHAIN"
    ipt "$ns" -t raw -A "$ONLY_CHAIN" -i eth0 -p tcp --dport "$port" -j RETURN
    ipt "$ns" -t raw -A "$ONLY_CHAIN" -i eth0 -p tcp --sport "$port" -j RETURN
    ipt "$ns" -t raw -A "$ONLY_CHAIN" -i eth0 -j DROP
}

cmd_cut() {
    [[ $# -eq 2 ]] || usage
    local tag=$1 host=$2 ns
    check_tag "$tag"
    ns=$(host_ns "$tag" "$host")
    need_root
    require_ns "$ns"
    pick_iptables "$ns"
    reset_raw_chain "$ns" "$CUT_CHAIN"
    ipt "$ns" -t raw -A "$CUT_CHAIN" -i eth0 -j DROP
}

cmd_uncut() {
    [[ $# -eq 2 ]] || usage
    local tag=$1 host=$2 ns
    check_tag "$tag"
    ns=$(host_ns "$tag" "$host")
    need_root
    require_ns "$ns"
    pick_iptables "$ns"
    ipt "$ns" -t raw -F "$CUT_CHAIN" 2>/dev/null || true
}

cmd_list() {
    local n
    { ip netns list 2>/dev/null || true; } | awk '{print $1}' | while read -r n; do
        if [[ -n ${1:-} ]]; then
            [[ $n == "$1-br" || $n =~ ^"$1"-h[0-9]+$ ]] && echo "$n"
        else
            [[ $n =~ -(br|h[0-9]+)$ ]] && echo "$n"
        fi
    done
    return 0
}

main() {
    local cmd=${1:-}
    [[ -n $cmd ]] || usage
    shift
    case $cmd in
        check) cmd_check ;;
        up) cmd_up "$@" ;;
        down) [[ $# -eq 1 ]] || usage; cmd_down "$1" ;;
        exec) cmd_exec "$@" ;;
        loss) cmd_loss "$@" ;;
        block-mcast) cmd_block_mcast "$@" ;;
        only-tcp) cmd_only_tcp "$@" ;;
        cut) cmd_cut "$@" ;;
        uncut) cmd_uncut "$@" ;;
        unblock-mcast) cmd_unblock_mcast "$@" ;;
        subnet) [[ $# -eq 1 ]] || usage; check_tag "$1"; echo "$(subnet_prefix "$1").0/24" ;;
        addr) [[ $# -eq 2 ]] || usage; check_tag "$1"; host_ns "$1" "$2" >/dev/null; echo "$(subnet_prefix "$1").$2" ;;
        list) cmd_list "${1:-}" ;;
        -h | --help | help) usage ;;
        *) echo "$PROG: unknown command '$cmd'" >&2; usage ;;
    esac
}

main "$@"

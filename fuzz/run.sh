#!/usr/bin/env bash
# Runs every fuzz target for a bounded time and reports what each did.
#
#   fuzz/run.sh [SECONDS_PER_TARGET] [TARGET...]     (default: 60 s, all)
#
# Needs cargo-fuzz (`cargo install cargo-fuzz`) and a nightly toolchain
# (`cargo +nightly`); without nightly it falls back to RUSTC_BOOTSTRAP=1 on
# stable. A failing input is left in fuzz/artifacts/<target>/: copy it to
# fuzz/regressions/<target>/ (with a name that says what it found) and the
# regression tests (`cargo test -p pulicast --test fuzz_regressions`)
# replay it from then on.
set -euo pipefail
cd "$(dirname "$0")"

secs=${1:-60}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    targets=(packet messages batch discovery names reassembly secure receiver datagram)
fi

if ! command -v cargo-fuzz >/dev/null; then
    echo "cargo-fuzz is missing: cargo install cargo-fuzz" >&2
    exit 2
fi
cargo=(cargo +nightly)
if ! cargo +nightly --version >/dev/null 2>&1; then
    cargo=(cargo)
    export RUSTC_BOOTSTRAP=1
fi

"${cargo[@]}" fuzz build -O >/dev/null 2>&1 || { echo "building the fuzz targets failed" >&2; exit 2; }

status=0
printf '%-12s %8s %12s %10s %8s  %s\n' target seconds runs exec/s corpus result
for t in "${targets[@]}"; do
    mkdir -p "corpus/$t" "artifacts/$t"
    log="artifacts/$t/last-run.log"
    if "${cargo[@]}" fuzz run -O "$t" "corpus/$t" -- \
        -max_total_time="$secs" -rss_limit_mb=2048 -max_len=65536 >"$log" 2>&1; then
        result=ok
    else
        result="FAILED (see $log and artifacts/$t/)"
        status=1
    fi
    runs=$(grep -o 'Done [0-9]* runs' "$log" | grep -o '[0-9]*' || echo "?")
    corpus=$(find "corpus/$t" -type f | wc -l)
    rate="?"
    if [ "$runs" != "?" ] && [ "$secs" -gt 0 ]; then
        rate=$((runs / secs))
    fi
    printf '%-12s %8s %12s %10s %8s  %s\n' "$t" "$secs" "$runs" "$rate" "$corpus" "$result"
done
exit $status

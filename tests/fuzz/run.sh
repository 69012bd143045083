#!/usr/bin/env bash
# Builds the cargo-fuzz targets and runs each one for a bounded time, one after the other, from the
# seed corpus in tests/fuzz/corpus/<target>/ (read-only; new inputs go to a working corpus under
# target/fuzz/). Prints executions, time and crashes per target. A crash input is kept in
# tests/fuzz/artifacts/<target>/; copy it to tests/fuzz/crashes/<target>/ once fixed, where
# tests/fuzz_regressions.rs replays it in the normal test run.
#
# Usage: tests/fuzz/run.sh [SECONDS_PER_TARGET (default 60)] [TARGET ...]
# Needs the nightly toolchain and cargo-fuzz (`cargo install cargo-fuzz`).
set -euo pipefail
seconds=${1:-60}
shift || true
root=$(cd "$(dirname "$0")/../.." && pwd)
cd "$root"
all_targets=(image_msg compressed_image ros1_bag ros2_sqlite mcap tum tflite safetensors params_yaml)
targets=("${@:-${all_targets[@]}}")
build_dir="$root/target/fuzz"
# -a: debug assertions (integer overflow panics); no sanitizer: the library is safe Rust, and the
# C parts (SQLite, bzip2, lz4) are not instrumented by RUSTFLAGS anyway.
build_only=()
[ ${#targets[@]} -eq 1 ] && build_only=("${targets[0]}")
cargo +nightly fuzz build --fuzz-dir tests/fuzz -a -s none --target-dir "$build_dir" "${build_only[@]}" >&2
bin_dir="$build_dir/x86_64-unknown-linux-gnu/release"
printf '%-18s %12s %8s %8s %8s\n' target executions seconds exec/s crashes
total_execs=0 total_secs=0 total_crashes=0
for t in "${targets[@]}"; do
    work="$build_dir/corpus-work/$t"
    artifacts="$root/tests/fuzz/artifacts/$t"
    mkdir -p "$work" "$artifacts"
    log="$build_dir/$t.log"
    before=$(find "$artifacts" -type f | wc -l)
    start=$(date +%s.%N)
    set +e
    "$bin_dir/$t" "$work" "$root/tests/fuzz/corpus/$t" -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 \
        -max_len=65536 -print_final_stats=1 -artifact_prefix="$artifacts/" >"$log" 2>&1
    status=$?
    set -e
    secs=$(echo "$(date +%s.%N) - $start" | bc)
    execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' | tail -1)
    execs=${execs:-0}
    crashes=$(( $(find "$artifacts" -type f | wc -l) - before ))
    printf '%-18s %12d %8.0f %8.0f %8d\n' "$t" "$execs" "$secs" "$(echo "$execs / $secs" | bc -l)" "$crashes"
    if [ "$status" -ne 0 ] && [ "$crashes" -eq 0 ]; then
        echo "  $t exited with $status without a crash input; see $log" >&2
    fi
    if [ "$crashes" -gt 0 ]; then
        grep -m1 -A3 "panicked at\|ERROR: libFuzzer" "$log" | sed 's/^/  /' >&2 || true
    fi
    total_execs=$((total_execs + execs)); total_crashes=$((total_crashes + crashes))
    total_secs=$(echo "$total_secs + $secs" | bc)
done
printf '%-18s %12d %8.0f %8s %8d\n' total "$total_execs" "$total_secs" "" "$total_crashes"

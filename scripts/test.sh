#!/usr/bin/env bash
# Set up from a clean clone and run every check: lint and format (ruff,
# cargo fmt), the Rust crates (cargo test, clippy), types (mypy) and the
# Python package (pytest). Used by .ci/run and named in the README.
#
# With CI set (.ci/run sets it) the property tests are derandomised: proptest
# draws from a fixed seed (PROPTEST_RNG_SEED) and hypothesis uses its "ci"
# profile (tests/conftest.py), and a skipped pytest test fails the run. Local
# runs keep random seeds, so they keep exploring.
#
# Order, for the wall time on a 2-core machine: the Rust checks need no Python,
# so they build and run in the background at a lower priority (their own target
# directory, so the extension's build inside pip never waits on their lock) while pip installs;
# mypy joins them once pip is done. The parallel pytest phase starts beside
# whatever of them is left, on two workers (pytest-xdist; one worker per file,
# so a module's fixtures are built once). The background checks' output is
# printed once they end, and any failure fails the run. The tests marked
# `alone` (frame rates and real-time drags in the browser) run last, with
# nothing else running, so they keep the machine they were written for.
set -euo pipefail
cd "$(dirname "$0")/.."
ci="${CI:-}"
case "${ci,,}" in
    "" | 0 | false | no) ;;
    *) export PROPTEST_RNG_SEED="${PROPTEST_RNG_SEED:-20251125}" ;;
esac
phase() { # phase WHAT: print the wall time since the start, for the README's figures
    echo "scripts/test.sh: $1 at $((SECONDS / 60)) min $((SECONDS % 60)) s"
}
bg_pids=()
bg_logs=()
bg_names=()
stop_background() {
    # on an early exit (a failed pip install or ruff): stop the background checks, then drop their logs
    local pid
    for pid in "${bg_pids[@]}"; do
        if kill -0 "$pid" 2>/dev/null; then
            pkill -TERM -P "$pid" 2>/dev/null || true
            kill -TERM "$pid" 2>/dev/null || true
        fi
    done
    rm -f "${bg_logs[@]}" "${alone_files:-}"
}
trap stop_background EXIT
background() { # background NAME FUNCTION: run FUNCTION (under set -e) with its output kept for later
    local log
    log="$(mktemp)"
    # at a lower priority (nice 10): the work in front (the extension's build, pytest) takes the cores
    # first and the background checks fill what it leaves idle, so the parallel tests start sooner
    (
        renice -n 10 -p "$BASHPID" >/dev/null 2>&1 || true
        "$2"
    ) >"$log" 2>&1 &
    bg_pids+=("$!")
    bg_logs+=("$log")
    bg_names+=("$1")
}
wait_background() { # wait for every background check, print its output, return non-zero if any failed
    local i rc failed=0
    for i in "${!bg_pids[@]}"; do
        rc=0
        wait "${bg_pids[$i]}" || rc=$?
        cat "${bg_logs[$i]}"
        if [ "$rc" != 0 ]; then
            echo "scripts/test.sh: ${bg_names[$i]} failed (exit $rc; its output is above)" >&2
            failed=1
        fi
    done
    bg_pids=()
    return "$failed"
}
rust_checks() {
    set -euo pipefail
    export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-target/checks}"
    cargo fmt --all --check
    # the checks profile (Cargo.toml): release's optimisation and bits, quicker to build. The unit and
    # integration tests only (--lib --tests): the examples and benches are compiled by clippy below, and
    # no crate has doc tests. With the parameter structs' serde reading (a feature only the binding turns
    # on) in the same build: each extra build of the solver's tests costs about two minutes of CPU here.
    cargo test --profile checks --lib --tests --features hybridmpm-mpm/serde
    cargo clippy --profile checks --workspace --all-targets -- -D warnings
}
type_check() {
    set -euo pipefail
    python -m mypy python/hybridmpm --ignore-missing-imports
}
background "the Rust checks (cargo fmt, test, clippy)" rust_checks
python3 -m venv .venv
. .venv/bin/activate
# uv installs the same packages as pip would, downloading them in parallel (the training
# extra's CUDA build of torch is ~3 GB of wheels): 1 min 44 s cold here against ~5 min for pip
python -m pip install --quiet uv
uv pip install --quiet --compile-bytecode -e '.[test]'
# lint and format: they take seconds
python -m ruff check python tests benchmarks docs
python -m ruff format --check python tests benchmarks docs
background "mypy" type_check
phase "set up (venv, install, lint)"
pytest_rc=0
# the parallel phase's workers list the files that hold `alone` tests (tests/conftest.py), so that the `alone`
# phase collects those files only, not the whole suite again (about 20 s of one core here)
alone_files="$(mktemp)"
HYBRIDMPM_ALONE_FILES="$alone_files" python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder -m "not alone" --durations=10 || pytest_rc=$?
mapfile -t alone < "$alone_files"
phase "parallel tests done"
wait_background
phase "background checks done"
if [ "$pytest_rc" != 0 ]; then
    exit "$pytest_rc"
fi
python -m pytest -q -m alone --durations=5 "${alone[@]}" # none listed: the whole suite, -m alone
phase "alone tests done"

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
# so they build and run in the background (their own target directory, so the
# extension's build inside pip never waits on their lock) while pip installs;
# pytest starts once they are done, on two workers (pytest-xdist; one worker
# per file, so a module's fixtures are built once), and the tests marked
# `alone` (frame rates and real-time drags in the browser) run last, by
# themselves, so they keep the machine they were written for.
set -euo pipefail
cd "$(dirname "$0")/.."
ci="${CI:-}"
case "${ci,,}" in
    "" | 0 | false | no) ;;
    *) export PROPTEST_RNG_SEED="${PROPTEST_RNG_SEED:-20251125}" ;;
esac
rust_log="$(mktemp)"
rust=""
stop_rust() {
    # on an early exit (a failed pip install, ruff, mypy): stop the background Rust checks, then drop their log
    if [ -n "$rust" ] && kill -0 "$rust" 2>/dev/null; then
        pkill -TERM -P "$rust" 2>/dev/null || true
        kill -TERM "$rust" 2>/dev/null || true
    fi
    rm -f "$rust_log"
}
trap stop_rust EXIT
(
    set -euo pipefail
    export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-target/checks}"
    cargo fmt --all --check
    cargo test --release
    # the parameter structs' serde reading (a feature only the binding turns on)
    cargo test --release -p hybridmpm-mpm --features serde --lib params
    cargo clippy --release --workspace --all-targets -- -D warnings
) >"$rust_log" 2>&1 &
rust=$!
python3 -m venv .venv
. .venv/bin/activate
python -m pip install --quiet --upgrade pip
python -m pip install --quiet -e '.[test]'
# lint and format: they take seconds
python -m ruff check python tests benchmarks docs
python -m ruff format --check python tests benchmarks docs
python -m mypy python/hybridmpm --ignore-missing-imports
rust_rc=0
wait "$rust" || rust_rc=$?
rust=""
cat "$rust_log"
if [ "$rust_rc" != 0 ]; then
    echo "scripts/test.sh: the Rust checks failed (exit $rust_rc; their output is above)" >&2
    exit "$rust_rc"
fi
python -m pytest -q -n 2 --dist loadfile -m "not alone"
python -m pytest -q -m alone

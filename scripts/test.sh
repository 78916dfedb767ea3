#!/usr/bin/env bash
# Set up from a clean clone and run every test: the Rust crates (cargo test)
# and the Python package (pytest). Used by .ci/run and named in the README.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
. .venv/bin/activate
python -m pip install --quiet --upgrade pip
python -m pip install --quiet -e '.[test]'
cargo test --release
cargo clippy --release --workspace --all-targets -- -D warnings
python -m mypy python/hybridmpm --ignore-missing-imports
python -m pytest -q

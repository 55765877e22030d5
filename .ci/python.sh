#!/usr/bin/env bash
# The Python package (python/): a virtual environment, the package built and
# installed with pip as the README says, its tests (python/tests) against the
# Rust examples `track` and `flow` built by the earlier `cargo test` steps.
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$(pwd)"
# The workspace's target directory: the dependencies the earlier steps
# compiled are reused where their profile and features match.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$repo/target}"
venv="$CARGO_TARGET_DIR/python-venv"

python3 --version
if [ ! -x "$venv/bin/python" ]; then
  # Debian's python3 needs python3-venv for `-m venv` (ensurepip).
  if ! python3 -m venv "$venv" 2>/dev/null; then
    rm -rf "$venv"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq python3-venv >/dev/null
    python3 -m venv "$venv"
  fi
fi
# The venv's tools first (maturin's build hook runs `maturin` from PATH).
export PATH="$venv/bin:$PATH"
pip=("$venv/bin/python" -m pip --disable-pip-version-check -q)
"${pip[@]}" install "maturin==1.16.0" "pytest==9.2.0" "numpy==2.4.6"

# `pip install ./python` (release build); the build tool is the venv's
# maturin rather than a fresh download for an isolated build.
start=$(date +%s)
"${pip[@]}" install --no-build-isolation --force-reinstall --no-deps ./python
echo "package built and installed in $(( $(date +%s) - start )) s"

# The Rust examples the tests compare with: those `cargo test` built, else
# built here.
examples="$CARGO_TARGET_DIR/debug/examples"
if [ ! -x "$examples/track" ] || [ ! -x "$examples/flow" ]; then
  cargo build --release --example track --example flow
  examples="$CARGO_TARGET_DIR/release/examples"
fi
export OPTICAL_TACTILE_EXAMPLES="$examples"
export OPTICAL_TACTILE_REQUIRE_EXAMPLES=1

# From the repository root, so that `import optical_tactile` is the
# installed package, not the source folder.
"$venv/bin/python" -I -m pytest -q -p no:cacheprovider python/tests

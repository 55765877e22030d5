#!/usr/bin/env bash
# The tune example's page in headless Chromium (tests/browser/tune.cjs): the
# tool on fixtures/press, its four rows and contacts updating, a threshold
# moved on the page, a calibration saved and loaded back, and the server's
# refusals of malformed requests. Installs Debian's chromium when it is
# missing and playwright-core (npm) under the target directory; builds the
# example (test profile, in target/debug: the test checks behaviour, not
# speed).
#
#   .ci/tune-browser.sh
#
# Environment: CHROMIUM (default /usr/bin/chromium), CARGO_TARGET_DIR,
# TUNE_SCREENSHOT (a PNG path for a screenshot of the page).
set -euo pipefail
cd "$(dirname "$0")/.."
start=$(date +%s)

chromium_bin="${CHROMIUM:-/usr/bin/chromium}"
if [[ ! -x $chromium_bin ]]; then
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq chromium >/dev/null
fi
"$chromium_bin" --headless --no-sandbox --version 2>/dev/null || {
  echo "tune-browser: $chromium_bin does not run" >&2
  exit 1
}

target_dir="${CARGO_TARGET_DIR:-target}"
pw_dir="$target_dir/tune-browser"
pw_version=1.65.1
pw_package="$pw_dir/node_modules/playwright-core/package.json"
if [[ ! -f $pw_package ]] || ! grep -q "\"version\": \"$pw_version\"" "$pw_package"; then
  mkdir -p "$pw_dir"
  # playwright-core downloads no browser: the test drives Debian's.
  (cd "$pw_dir" && npm install --no-audit --no-fund --no-save --loglevel=error \
    "playwright-core@$pw_version")
fi

# The test profile: the one `cargo test` builds with, so that after it only
# the example is linked (and it runs faster than a plain debug build).
cargo build --profile test --example tune -p optical-tactile

TUNE_BIN="$target_dir/debug/examples/tune" \
  PLAYWRIGHT_DIR="$(cd "$pw_dir" && pwd)/node_modules" \
  CHROMIUM="$chromium_bin" \
  node tests/browser/tune.cjs
echo "tune page in headless Chromium: $(($(date +%s) - start)) s"

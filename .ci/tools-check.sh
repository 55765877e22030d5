#!/usr/bin/env bash
# Smoke test of the command-line tools (the examples): every tool answers
# --help (status 0, a usage text) and an unknown flag (status 2); track runs
# with its default inputs from another directory and prints contacts; a
# closed pipe (track | head -3) ends track quietly with status 0; text
# streams go to stdout with `-`, binary outputs refuse it; track --timings
# prints its stage table; the tune server starts, prints its address and
# stops with --run-for; the ROS 2 node (optical_tactile_node) answers
# --help, refuses a bad flag or ROS argument (status 2) and a missing
# calibration or camera (one error line, status 1) before it starts any
# network traffic.
#
#   .ci/tools-check.sh                # builds the release examples first
#   .ci/tools-check.sh --no-build     # uses the release examples already built
#   .ci/tools-check.sh --debug [--no-build]   # the debug examples instead
#
# `live` is checked only when it was built (the v4l feature). Prints one line
# per check and `N passed, M failed` at the end; exits non-zero on a failure.
set -euo pipefail
cd "$(dirname "$0")/.."

profile=release
build=1
for arg in "$@"; do
  case "$arg" in
    --debug) profile=debug ;;
    --no-build) build=0 ;;
    -h | --help)
      sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//'
      exit 0
      ;;
    *)
      echo "tools-check: unknown argument $arg (see --help)" >&2
      exit 2
      ;;
  esac
done

if [[ $build == 1 ]]; then
  if [[ $profile == release ]]; then
    cargo build --release --examples -p optical-tactile
    cargo build --release -p optical-tactile-ros2
  else
    cargo build --examples -p optical-tactile
    cargo build -p optical-tactile-ros2
  fi
fi

target_dir="${CARGO_TARGET_DIR:-target}"
bin_dir="$(cd "$target_dir/$profile/examples" && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

passed=0
failed=0
pass() {
  passed=$((passed + 1))
  echo "ok    $1"
}
fail() {
  failed=$((failed + 1))
  echo "FAIL  $1"
  if [[ -n "${2:-}" ]]; then
    sed 's/^/      | /' <<<"$2" | head -20
  fi
}

# check NAME EXPECTED_STATUS COMMAND...: runs COMMAND (stdout and stderr
# kept in $work/out and $work/err) and compares its exit status.
check_status() {
  local name=$1 want=$2
  shift 2
  local rc=0
  "$@" >"$work/out" 2>"$work/err" || rc=$?
  if [[ $rc == "$want" ]]; then
    return 0
  fi
  fail "$name: exit status $rc, expected $want" "$(cat "$work/out" "$work/err")"
  return 1
}

tools=(track live tune calibrate simulate evaluate flow hhd multi_contact perch_selection touch_mapping experiments)
for tool in "${tools[@]}"; do
  bin="$bin_dir/$tool"
  if [[ ! -x $bin ]]; then
    if [[ $tool == live ]]; then
      echo "skip  live (built only with --features v4l)"
      continue
    fi
    fail "$tool: no binary at $bin"
    continue
  fi
  if check_status "$tool --help" 0 "$bin" --help; then
    if grep -q "Usage" "$work/out"; then
      pass "$tool --help"
    else
      fail "$tool --help: no usage text on stdout" "$(cat "$work/out")"
    fi
  fi
  if check_status "$tool --no-such-flag" 2 "$bin" --no-such-flag; then
    if grep -q -- "--no-such-flag" "$work/err" && ! grep -q "panicked" "$work/err"; then
      pass "$tool --no-such-flag"
    else
      fail "$tool --no-such-flag: the error does not name the flag" "$(cat "$work/err")"
    fi
  fi
done

track="$bin_dir/track"
if [[ -x $track ]]; then
  # Default inputs resolve from the crate, not the working directory.
  if (cd "$work" && check_status "track from another directory" 0 "$track"); then
    if grep -Eq '^[0-9]+\.png +[0-9.]+ +[0-9]+ +-?[0-9]+\.[0-9]+ ' "$work/out" &&
      grep -q "frames processed (0 skipped)" "$work/out"; then
      pass "track from another directory prints contacts"
    else
      fail "track from another directory: no contact rows" "$(cat "$work/out" "$work/err")"
    fi
  fi

  # A closed pipe: quiet, status 0.
  rc=0
  (
    cd "$work"
    set +o pipefail
    "$track" 2>"$work/err" | head -3 >"$work/out"
    exit "${PIPESTATUS[0]}"
  ) || rc=$?
  if [[ $rc == 0 ]] && [[ $(wc -l <"$work/out") == 3 ]] &&
    ! grep -Eqi "panicked|broken pipe|^error" "$work/err"; then
    pass "track | head -3 ends quietly with status 0"
  else
    fail "track | head -3: status $rc" "$(cat "$work/out" "$work/err")"
  fi

  # --out -: JSON Lines on stdout, the table on stderr.
  if check_status "track --out -" 0 "$track" --out -; then
    if [[ $(grep -c '^{"frame":' "$work/out") == 7 ]] && [[ $(wc -l <"$work/out") == 7 ]] &&
      grep -q "frames processed" "$work/err"; then
      pass "track --out - writes JSON Lines to stdout"
    else
      fail "track --out -: stdout is not 7 JSON lines" "$(cat "$work/out")"
    fi
  fi

  # The stream scores against the truth through a pipe.
  evaluate="$bin_dir/evaluate"
  if [[ -x $evaluate ]]; then
    rc=0
    "$track" --out - 2>/dev/null >"$work/pred.jsonl" || rc=$?
    if [[ $rc == 0 ]] && check_status "evaluate" 0 "$evaluate" "$work/pred.jsonl" fixtures/press/truth.jsonl --json -; then
      if grep -q '"matched"' "$work/out" && grep -q "MAE x" "$work/err"; then
        pass "evaluate --json - writes JSON to stdout"
      else
        fail "evaluate --json -: unexpected output" "$(cat "$work/out" "$work/err")"
      fi
    fi
  fi

  # Raw mode: no calibration (a missing file does not matter), patches in
  # pixels, the same JSON Lines layout with raw keys.
  if check_status "track --raw" 0 "$track" --raw --thresholds low --calibration "$work/none.json" --out -; then
    if [[ $(grep -c '^{"frame":' "$work/out") == 7 ]] && grep -q '"box_px":' "$work/out" &&
      grep -q '"dn":' "$work/out" && ! grep -q '"x_mm"' "$work/out"; then
      pass "track --raw writes patches without a calibration"
    else
      fail "track --raw: no raw patches in the JSON Lines" "$(cat "$work/out" "$work/err")"
    fi
  fi

  # One threshold overridden: a magnitude above any flow leaves no contact.
  if check_status "track --magnitude 100" 0 "$track" --magnitude 100 --out -; then
    if [[ $(grep -c '"contacts":\[\]' "$work/out") == 7 ]]; then
      pass "track --magnitude 100 finds no contact"
    else
      fail "track --magnitude 100: contacts found" "$(cat "$work/out")"
    fi
  fi
  # The time per stage: a row per statistic, the slowest frame named.
  if check_status "track --timings" 0 "$track" --quiet --timings; then
    if grep -q "^median .*[0-9]" "$work/out" && grep -q "^slowest frame: 0000" "$work/out"; then
      pass "track --timings prints the stage table and the slowest frame"
    else
      fail "track --timings: no stage table" "$(cat "$work/out" "$work/err")"
    fi
  fi
  if check_status "track --erode 0" 2 "$track" --erode 0; then
    if grep -q "kernel side" "$work/err"; then
      pass "track --erode 0 is refused"
    else
      fail "track --erode 0: unclear message" "$(cat "$work/err")"
    fi
  fi

  # A crop other than the calibration's: refused unless forced.
  if check_status "track --crop (not the calibration's)" 1 "$track" --crop 690,0,20,200; then
    if grep -q "force-crop" "$work/err"; then
      pass "track refuses a crop other than the calibration's"
    else
      fail "track --crop: the error does not say how to force it" "$(cat "$work/err")"
    fi
  fi

  # A runtime error: one line, status 1.
  if check_status "track with a missing calibration" 1 "$track" --calibration "$work/none.json"; then
    if [[ $(grep -c '^error: ' "$work/err") == 1 ]] && ! grep -q "panicked" "$work/err"; then
      pass "track with a missing calibration: one error line, status 1"
    else
      fail "track with a missing calibration: not one error line" "$(cat "$work/err")"
    fi
  fi
fi

# The tune server: serves on a free port and stops by itself with
# --run-for; a bad save directory or sequence is one error line before it
# listens.
tune="$bin_dir/tune"
if [[ -x $tune ]]; then
  if (cd "$work" && check_status "tune --port 0 --run-for 1" 0 "$tune" --raw --port 0 --run-for 1); then
    if grep -Eq '^tune: serving http://127\.0\.0\.1:[0-9]+/$' "$work/out"; then
      pass "tune serves on 127.0.0.1 and stops after --run-for"
    else
      fail "tune --port 0: no address printed" "$(cat "$work/out" "$work/err")"
    fi
  fi
  if check_status "tune --save-dir (missing)" 1 "$tune" --port 0 --save-dir "$work/none"; then
    if [[ $(grep -c '^error: ' "$work/err") == 1 ]] && ! grep -q "panicked" "$work/err"; then
      pass "tune with a missing save directory: one error line, status 1"
    else
      fail "tune --save-dir: not one error line" "$(cat "$work/err")"
    fi
  fi
  if check_status "tune (missing sequence)" 1 "$tune" "$work/none" --port 0; then
    if [[ $(grep -c '^error: ' "$work/err") == 1 ]]; then
      pass "tune with a missing sequence: one error line, status 1"
    else
      fail "tune with a missing sequence: not one error line" "$(cat "$work/err")"
    fi
  fi
fi

# Binary outputs refuse stdout.
multi="$bin_dir/multi_contact"
if [[ -x $multi ]] && check_status "multi_contact --png -" 2 "$multi" fixtures/press --png -; then
  if grep -q "stdout" "$work/err"; then
    pass "multi_contact --png - is refused"
  else
    fail "multi_contact --png -: unclear message" "$(cat "$work/err")"
  fi
fi

# The ROS 2 node: only runs that end before its participant starts (no
# network traffic here).
ros_node="$target_dir/$profile/optical_tactile_node"
if [[ ! -x $ros_node ]]; then
  fail "optical_tactile_node: no binary at $ros_node"
else
  if check_status "optical_tactile_node --help" 0 "$ros_node" --help; then
    if grep -q "Usage" "$work/out" && grep -q -- "--frame-id" "$work/out"; then
      pass "optical_tactile_node --help"
    else
      fail "optical_tactile_node --help: no usage text on stdout" "$(cat "$work/out")"
    fi
  fi
  if check_status "optical_tactile_node --no-such-flag" 2 "$ros_node" --no-such-flag; then
    if grep -q -- "--no-such-flag" "$work/err" && ! grep -q "panicked" "$work/err"; then
      pass "optical_tactile_node --no-such-flag"
    else
      fail "optical_tactile_node --no-such-flag: the error does not name the flag" "$(cat "$work/err")"
    fi
  fi
  if check_status "optical_tactile_node --ros-args --params-file" 2 "$ros_node" --ros-args --params-file p.yaml; then
    if grep -q -- "--params-file" "$work/err"; then
      pass "optical_tactile_node refuses an unsupported ROS argument"
    else
      fail "optical_tactile_node --ros-args: unclear message" "$(cat "$work/err")"
    fi
  fi
  if check_status "optical_tactile_node with a missing calibration" 1 \
    "$ros_node" --sequence fixtures/press --calibration "$work/none.json"; then
    if [[ $(grep -c '^error: ' "$work/err") == 1 ]] && grep -q "none.json" "$work/err" &&
      ! grep -q "panicked" "$work/err"; then
      pass "optical_tactile_node with a missing calibration: one error line, status 1"
    else
      fail "optical_tactile_node with a missing calibration: not one error line" "$(cat "$work/err")"
    fi
  fi
  if check_status "optical_tactile_node --device (missing)" 1 "$ros_node" --device "$work/no-camera"; then
    if [[ $(grep -c '^error: ' "$work/err") == 1 ]] && grep -q "no-camera" "$work/err"; then
      pass "optical_tactile_node with a missing camera: one error line, status 1"
    else
      fail "optical_tactile_node --device: not one error line" "$(cat "$work/err")"
    fi
  fi
fi

echo "$passed passed, $failed failed"
[[ $failed == 0 ]]

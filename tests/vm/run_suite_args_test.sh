#!/usr/bin/env bash
# toolchain/vm/run-suite refuses bad --file and --bin arguments and a bad MAGVEC_VM_CLOCK before
# it builds or boots anything: exit 2, a message naming the argument and what is wrong, no work
# directory created.
# Usage: run_suite_args_test.sh RUN_SUITE
set -u
run_suite=$1
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
mkdir "$tmp/tests"
echo data >"$tmp/model.cof"
fails=0
clock=icount
expect() {  # expect WANTED_MESSAGE ARGS...
  local want=$1 out rc
  shift
  out=$(MAGVEC_VM_CLOCK=$clock MAGVEC_VM_CACHE="$tmp/cache" "$run_suite" --tests "$tmp/tests" \
    --out "$tmp/out" "$@" 2>&1)
  rc=$?
  if [ "$rc" != 2 ] || [[ "$out" != *"$want"* ]] || [ -e "$tmp/out" ] || [ -e "$tmp/cache" ]; then
    echo "FAIL: run-suite $*: exit $rc, output: $out"
    fails=$((fails + 1))
  else
    echo "ok: run-suite $* -> $out"
  fi
}
expect "is not a file" --file "$tmp/missing.cof=/share/x.cof"
expect "no '='" --file "$tmp/model.cof"
expect "DEST must be an absolute file path" --file "$tmp/model.cof=share/x.cof"
expect "DEST must be an absolute file path" --file "$tmp/model.cof=/share/dir/"
expect "DEST must be an absolute file path" --file "$tmp/model.cof="
expect "is not a file" --file "$tmp=/share/x.cof"
expect "is not an executable file" --bin "$tmp/model.cof"
expect "is not an executable file" --bin "$tmp/nonexistent"
clock=wall
expect "MAGVEC_VM_CLOCK=wall: need icount or host"
[ "$fails" = 0 ] && echo "all bad arguments refused" && exit 0
exit 1

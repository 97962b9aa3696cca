#!/usr/bin/env bash
# `cmake --install` of a built tree into a temporary prefix (and DESTDIR): magvec, magvecd, the
# systemd unit (naming the prefix's paths), the example configuration (which the installed daemon
# accepts) and the lcm-spy type jar when it was built.
# usage: install_test.sh BUILD_DIR
set -u
B=$1
W=$(mktemp -d /tmp/magvec_install.XXXXXX)
trap 'rm -rf "$W"' EXIT
FAILS=0
check() { local what=$1; shift; if "$@"; then echo "PASS: $what"; else echo "FAIL: $what"; FAILS=$((FAILS + 1)); fi; }

cmake --install "$B" --prefix "$W/p" >"$W/install.out" 2>&1
check "cmake --install succeeds" [ $? -eq 0 ]
check "bin/magvec" [ -x "$W/p/bin/magvec" ]
check "sbin/magvecd" [ -x "$W/p/sbin/magvecd" ]
check "etc/magvec/magvecd.toml" [ -f "$W/p/etc/magvec/magvecd.toml" ]
U="$W/p/lib/systemd/system/magvecd.service"
check "lib/systemd/system/magvecd.service" [ -f "$U" ]
check "unit is Type=notify with a watchdog" grep -q "^Type=notify" "$U"
check "unit has WatchdogSec" grep -q "^WatchdogSec=" "$U"
check "unit starts the installed daemon with the installed config" \
  grep -q "^ExecStart=$W/p/sbin/magvecd --config $W/p/etc/magvec/magvecd.toml" "$U"
check "installed daemon accepts the installed example config" \
  "$W/p/sbin/magvecd" --config "$W/p/etc/magvec/magvecd.toml" --check-config
check "installed magvec runs" "$W/p/bin/magvec" --version
if [ -f "$B/host/lcm/magvec_lcm.jar" ]; then
  check "share/magvec/magvec_lcm.jar" [ -f "$W/p/share/magvec/magvec_lcm.jar" ]
fi
check "share/magvec/magvec_report.py, executable" [ -x "$W/p/share/magvec/magvec_report.py" ]
check "share/magvec/geomag/wmm2025.wmm" [ -f "$W/p/share/magvec/geomag/wmm2025.wmm" ]
DESTDIR="$W/dest" cmake --install "$B" --prefix /usr/local >/dev/null 2>&1
check "DESTDIR honoured (unit and binary)" \
  [ -f "$W/dest/usr/local/lib/systemd/system/magvecd.service" ] && [ -x "$W/dest/usr/local/sbin/magvecd" ]
check "DESTDIR unit names /usr/local" grep -q "^ExecStart=/usr/local/sbin/magvecd --config /usr/local/etc/magvec/magvecd.toml" \
  "$W/dest/usr/local/lib/systemd/system/magvecd.service"
# The /usr prefix (the Debian package's): configuration in /etc, the unit in /lib/systemd/system.
DESTDIR="$W/usr" cmake --install "$B" --prefix /usr >/dev/null 2>&1
check "prefix /usr: /etc/magvec/magvecd.toml" [ -f "$W/usr/etc/magvec/magvecd.toml" ]
check "prefix /usr: unit in /lib/systemd/system naming /etc" grep -q \
  "^ExecStart=/usr/sbin/magvecd --config /etc/magvec/magvecd.toml" \
  "$W/usr/lib/systemd/system/magvecd.service"
echo "install test: $FAILS failure(s)"
[ "$FAILS" -eq 0 ]

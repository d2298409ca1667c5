#!/usr/bin/env bash
# Make sure open3d's system library libusb-1.0 is present; install it with apt-get when we can.
set -euo pipefail
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "Installing libusb-1.0-0 (needed by open3d) with apt-get..."
  apt-get update -qq >/dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  exit 0
fi
echo "error: open3d needs the system package libusb-1.0-0; install it (for example: sudo apt-get install libusb-1.0-0) and run again" >&2
exit 1

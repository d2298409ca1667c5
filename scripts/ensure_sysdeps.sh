#!/usr/bin/env bash
# System prerequisites of `make setup`: room on disk for .venv, and open3d's libusb-1.0.
set -euo pipefail
# .venv takes about 1.2 GB for make demo (open3d, gtsam, opencv, scipy) and 2.3 GB with make
# test's dev extra (ray, rerun, evo, ...); pip fails mid-install without the room.
free_kb=$(df -Pk . 2>/dev/null | awk 'NR==2 {print $4}')
if [ -n "${free_kb}" ] && [ "${free_kb}" -lt 3000000 ]; then
  echo "warning: $((free_kb / 1024)) MB free on disk at $(pwd); .venv needs about 1.2 GB (make demo) or 2.3 GB (make test)" >&2
fi
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

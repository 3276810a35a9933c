#!/usr/bin/env bash
# System libraries the Python packages need but pip cannot install:
#   libusb-1.0 for pyrealsense2 (reading RealSense .bag recordings).
# Installs them with apt when run as root on Debian/Ubuntu; otherwise says what to install.
set -u
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing libusb-1.0-0 (needed by pyrealsense2 for .bag files)"
    (apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1 || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1; }) \
        || echo "warning: could not install libusb-1.0-0; .bag files will not be readable" >&2
else
    echo "warning: libusb-1.0 is missing: install it (e.g. 'sudo apt-get install libusb-1.0-0') to read .bag files" >&2
fi
exit 0

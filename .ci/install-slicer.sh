#!/bin/sh
# Install PrusaSlicer (Debian package prusa-slicer) when it is missing, so that the
# printability check in tests/test_printer.py runs against a real slicer.
set -eu
if command -v prusa-slicer >/dev/null 2>&1; then
    echo "prusa-slicer already installed: $(command -v prusa-slicer)"
    exit 0
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    SUDO="sudo"
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update
$SUDO apt-get install -y --no-install-recommends prusa-slicer
command -v prusa-slicer

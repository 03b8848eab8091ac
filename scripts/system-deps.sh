#!/usr/bin/env bash
# System libraries that the PyPI wheels of our dependencies expect from the OS.
# Open3D's Linux wheel links against libusb-1.0 (for its RealSense support) but does not ship it.
set -euo pipefail

if [ "$(uname -s)" != "Linux" ]; then
    exit 0
fi
missing=()
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1\.0\.so\.0'; then
    missing+=(libusb-1.0-0)
fi
if ! command -v cc >/dev/null 2>&1 && ! command -v gcc >/dev/null 2>&1; then
    missing+=(gcc)
fi
[ ${#missing[@]} -eq 0 ] && exit 0

echo "dvpmvs setup: installing system packages: ${missing[*]}"
if ! command -v apt-get >/dev/null 2>&1; then
    echo "dvpmvs setup: please install ${missing[*]} with your system's package manager" >&2
    exit 1
fi
sudo=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then
        sudo="sudo"
    else
        echo "dvpmvs setup: run as root, or: apt-get install -y ${missing[*]}" >&2
        exit 1
    fi
fi
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}"

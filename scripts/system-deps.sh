#!/usr/bin/env bash
# System libraries that the PyPI wheels of our dependencies expect from the OS.
# Open3D's Linux wheel links against libusb-1.0 (for its RealSense support) but does not ship it.
# With --test: also COLMAP's own command-line program (Debian's `colmap`, no CUDA), which the
# tests run on our outputs as an independent client, and Chromium, in which they open the HTML
# reports; optional: without apt (or without the right to use it) the tests that need them are
# skipped with the reason.
set -euo pipefail

optional=()
if [ "${1:-}" = "--test" ] && ! command -v colmap >/dev/null 2>&1; then
    optional+=(colmap)
fi
# Chromium (Debian's), in which the tests open the HTML reports (driven by Playwright, from PyPI).
if [ "${1:-}" = "--test" ] && ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then
    optional+=(chromium)
fi

if [ "$(uname -s)" != "Linux" ]; then
    exit 0
fi
missing=()
# grep reads all of ldconfig's output (-q would stop early, and pipefail would count the SIGPIPE)
if ! ldconfig -p 2>/dev/null | grep 'libusb-1\.0\.so\.0' >/dev/null; then
    missing+=(libusb-1.0-0)
fi
if ! command -v cc >/dev/null 2>&1 && ! command -v gcc >/dev/null 2>&1; then
    missing+=(gcc)
fi
[ ${#missing[@]} -eq 0 ] && [ ${#optional[@]} -eq 0 ] && exit 0

sudo=""
can_apt=1
if ! command -v apt-get >/dev/null 2>&1; then
    can_apt=0
elif [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
        sudo="sudo"
    elif [ ${#missing[@]} -gt 0 ] && command -v sudo >/dev/null 2>&1; then
        sudo="sudo"  # required packages: let sudo ask for a password
    else
        can_apt=0
    fi
fi
if [ $can_apt -eq 0 ]; then
    if [ ${#missing[@]} -gt 0 ]; then
        echo "dvpmvs setup: please install ${missing[*]} with your system's package manager (as root: apt-get install -y ${missing[*]})" >&2
        exit 1
    fi
    echo "dvpmvs setup: ${optional[*]} not installed (no apt-get, or not root); the tests that need them will be skipped"
    exit 0
fi
echo "dvpmvs setup: installing system packages: ${missing[*]} ${optional[*]}"
if ! $sudo apt-get update -qq; then
    if [ ${#missing[@]} -gt 0 ]; then
        echo "dvpmvs setup: apt-get update failed; install ${missing[*]} yourself" >&2
        exit 1
    fi
    echo "dvpmvs setup: apt-get update failed; ${optional[*]} not installed, the tests that need them will be skipped"
    exit 0
fi
if [ ${#missing[@]} -gt 0 ]; then
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}"
fi
if [ ${#optional[@]} -gt 0 ]; then
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${optional[@]}" \
        || echo "dvpmvs setup: could not install ${optional[*]}; the tests that need them will be skipped"
fi

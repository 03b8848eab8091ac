#!/usr/bin/env bash
# Rebuilds dvpmvs/report_assets/vendor/three.bundle.js: three.js and its OrbitControls, pinned, bundled
# into one classic script that defines `window.THREE` (a report opened from disk through file://
# cannot load ES modules: Chromium refuses module imports from file URLs). A maintainer's tool,
# run by hand when the pinned version changes; users and CI only read the committed bundle.
# Needs Node.js and npm (the npm registry).
set -euo pipefail
THREE_VERSION=0.187.0
ESBUILD_VERSION=0.28.2
here="$(cd "$(dirname "$0")/.." && pwd)"
assets="$here/dvpmvs/report_assets/vendor"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
npm init -y >/dev/null
npm install --silent --no-audit --no-fund "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION"
cat > entry.js <<'JS'
export { AmbientLight, BufferAttribute, BufferGeometry, Color, DirectionalLight, DoubleSide,
         Float32BufferAttribute, LineBasicMaterial, LineSegments, Mesh, MeshLambertMaterial,
         PerspectiveCamera, Points, PointsMaterial, Scene, Sphere, Vector3, WebGLRenderer } from "three";
export { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
JS
npx esbuild entry.js --bundle --minify --format=iife --global-name=THREE --legal-comments=none \
    --banner:js="/* three.js ${THREE_VERSION} (https://threejs.org), MIT licence: LICENSE.three.txt beside this file. Built by scripts/vendor_three.sh. */" \
    --outfile="$assets/three.bundle.js"
cp node_modules/three/LICENSE "$assets/LICENSE.three.txt"
echo "wrote $assets/three.bundle.js ($(wc -c < "$assets/three.bundle.js") bytes), three@$THREE_VERSION"

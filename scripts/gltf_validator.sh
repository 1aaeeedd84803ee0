#!/usr/bin/env bash
# Khronos glTF-Validator (npm gltf-validator, the official validator compiled to JS) in
# .tools/gltf-validator, with a small CLI: node .tools/gltf-validator/validate.mjs FILE.glb
# prints the validation report as JSON. The asset tests run it; needs node and npm.
set -euo pipefail
cd "$(dirname "$0")/.."
DIR=.tools/gltf-validator
VERSION=2.0.0-dev.3.10
if [ -f "$DIR/node_modules/gltf-validator/package.json" ] && grep -q "\"$VERSION\"" "$DIR/node_modules/gltf-validator/package.json"; then
    exit 0
fi
if ! command -v npm >/dev/null; then
    if command -v apt-get >/dev/null; then
        (apt-get update -qq && apt-get install -y -qq nodejs npm) >/dev/null
    else
        echo "gltf_validator.sh: npm is needed (install Node.js)" >&2
        exit 1
    fi
fi
mkdir -p "$DIR"
(cd "$DIR" && npm install --silent --no-audit --no-fund --prefix . "gltf-validator@$VERSION" >/dev/null)
cat > "$DIR/validate.mjs" <<'JS'
// node validate.mjs FILE: Khronos glTF-Validator's report of a .glb/.gltf as JSON.
import fs from 'fs';
import path from 'path';
import { createRequire } from 'module';
const require = createRequire(import.meta.url);
const validator = require('gltf-validator');
const file = process.argv[2];
const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {
  uri: path.basename(file), maxIssues: 100,
});
const i = report.issues;
console.log(JSON.stringify({numErrors: i.numErrors, numWarnings: i.numWarnings,
  numInfos: i.numInfos, messages: i.messages}));
JS

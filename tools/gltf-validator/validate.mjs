#!/usr/bin/env node
// Validate one glTF 2.0 asset (.glb or .gltf) with the Khronos glTF validator
// (npm `gltf-validator`) and print its JSON report on stdout.
//
//   node tools/gltf-validator/validate.mjs path/to/asset.glb
//
// Exit status: 0 when report.issues.numErrors == 0, 1 when the asset has errors,
// 2 when the validator could not run (missing file, bad arguments).
// Install once with `npm ci` in this folder (.ci/npm-dirs.txt lists it).
import { readFile } from 'node:fs/promises';
import path from 'node:path';
import validator from 'gltf-validator';

const file = process.argv[2];
if (!file) {
  console.error('usage: node validate.mjs FILE.glb|FILE.gltf');
  process.exit(2);
}

try {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 100,
    externalResourceFunction: (uri) =>
      readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)))
        .then((b) => new Uint8Array(b)),
  });
  process.stdout.write(JSON.stringify(report, null, 2) + '\n');
  process.exit(report.issues.numErrors === 0 ? 0 : 1);
} catch (err) {
  console.error(`gltf-validator failed on ${file}: ${err && err.message ? err.message : err}`);
  process.exit(2);
}

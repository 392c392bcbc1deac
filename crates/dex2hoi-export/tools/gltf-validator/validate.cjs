// Validates a .glb with the Khronos glTF validator (npm `gltf-validator`): prints the JSON
// report on stdout and exits 1 when it has errors, 2 when the file cannot be read.
"use strict";
const fs = require("node:fs");
const validator = require("gltf-validator");

const path = process.argv[2];
let bytes;
try {
  bytes = new Uint8Array(fs.readFileSync(path));
} catch (error) {
  console.error(`cannot read ${path}: ${error.message}`);
  process.exit(2);
}
validator
  .validateBytes(bytes, { uri: path, maxIssues: 0, writeTimestamp: false })
  .then((report) => {
    console.log(JSON.stringify(report, null, 2));
    process.exit(report.issues.numErrors > 0 ? 1 : 0);
  })
  .catch((error) => {
    console.error(`validation failed: ${error}`);
    process.exit(2);
  });

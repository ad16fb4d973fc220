// Khronos glTF-Validator (npm gltf-validator, installed by `make tools`): prints the JSON report of one file.
// Usage: node tests/tools/validate_gltf.cjs FILE.glb
const fs = require("fs");
const validator = require("gltf-validator");

const path = process.argv[2];
validator
  .validateBytes(new Uint8Array(fs.readFileSync(path)), { uri: path, maxIssues: 1000 })
  .then((report) => {
    process.stdout.write(JSON.stringify(report) + "\n");
  })
  .catch((error) => {
    process.stderr.write(`gltf-validator failed on ${path}: ${error}\n`);
    process.exit(1);
  });

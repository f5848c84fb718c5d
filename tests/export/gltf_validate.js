// Validate a glTF/GLB file with the Khronos glTF validator and print its JSON report on stdout.
// Usage: node gltf_validate.js VALIDATOR_MODULE_DIR FILE   (used by tests/export/test_gltf.py)
const fs = require("fs");
const validator = require(process.argv[2]);
const bytes = new Uint8Array(fs.readFileSync(process.argv[3]));
validator
  .validateBytes(bytes, { uri: process.argv[3], maxIssues: 0 })
  .then((report) => process.stdout.write(JSON.stringify(report)))
  .catch((error) => {
    process.stderr.write(String(error) + "\n");
    process.exit(2);
  });

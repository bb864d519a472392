// Run the Khronos glTF-Validator (npm `gltf-validator`) on one .gltf or .glb file and print its
// JSON report on stdout.  External resources (.bin buffers, image URIs) are loaded relative to
// the file, so they are validated too.  Exit status: 0 when a report was produced (whatever its
// issues: the caller judges them), 2 on bad arguments or a file the validator cannot parse.
//
//   node tests/export/gltf_validate.mjs FILE.gltf|FILE.glb
import { readFile } from 'node:fs/promises';
import path from 'node:path';
import validator from 'gltf-validator';

const file = process.argv[2];
if (!file || process.argv.length > 3) {
  console.error('usage: node gltf_validate.mjs FILE.gltf|FILE.glb');
  process.exit(2);
}
const full = path.resolve(file);
const format = full.toLowerCase().endsWith('.glb') ? 'glb' : 'gltf';

try {
  const data = new Uint8Array(await readFile(full));
  const report = await validator.validateBytes(data, {
    uri: path.basename(full),
    format,
    maxIssues: 0,            // report every issue
    writeTimestamp: false,
    externalResourceFunction: async (uri) => {
      const res = path.resolve(path.dirname(full), decodeURIComponent(uri));
      return new Uint8Array(await readFile(res));
    },
  });
  process.stdout.write(JSON.stringify(report, null, 2) + '\n');
} catch (err) {
  console.error(`gltf_validate: ${full}: ${err}`);
  process.exit(2);
}

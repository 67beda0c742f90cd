// The Khronos glTF validator's report on a .glb or .gltf file (resources beside a .gltf are read from its folder).
//   node validate.mjs MODEL           -> the report's JSON on stdout
import { readFileSync } from 'node:fs';
import { dirname, join } from 'node:path';
import validator from 'gltf-validator';

const model = process.argv[2];
const report = await validator.validateBytes(new Uint8Array(readFileSync(model)), {
    uri: model,
    maxIssues: 0,
    externalResourceFunction: (uri) => Promise.resolve(new Uint8Array(readFileSync(join(dirname(model), decodeURIComponent(uri))))),
});
process.stdout.write(JSON.stringify(report, null, 1));

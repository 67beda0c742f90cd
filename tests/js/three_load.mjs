// Load a .glb with three.js' GLTFLoader and its KHR_gaussian_splatting plugin (three/addons), in Node, and write what
// the loader built: per splat object its world matrix, and its geometry's attributes as raw little-endian arrays.
//   node three_load.mjs MODEL.glb OUT_DIR      -> OUT_DIR/three.json (+ one .bin per attribute array)
import { readFileSync, writeFileSync, mkdirSync } from 'node:fs';
import { join } from 'node:path';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { GLTFGaussianSplatLoaderExtension } from 'three/addons/loaders/GLTFGaussianSplatLoaderExtension.js';

const [model, out] = process.argv.slice(2);
mkdirSync(out, { recursive: true });
const bytes = readFileSync(model);
const loader = new GLTFLoader();
loader.register((parser) => new GLTFGaussianSplatLoaderExtension(parser));
const gltf = await loader.parseAsync(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength), '');
gltf.scene.updateMatrixWorld(true);
const splats = [];
gltf.scene.traverse((o) => {
    if (!o.isGaussianSplat) return;
    const i = splats.length;
    const attributes = {};
    for (const [name, a] of Object.entries(o.splatGeometry.attributes)) {
        const file = `splat${i}_${name}.bin`;
        writeFileSync(join(out, file), Buffer.from(a.array.buffer, a.array.byteOffset, a.array.byteLength));
        attributes[name] = { file, type: a.array.constructor.name, itemSize: a.itemSize, count: a.count,
                             normalized: a.normalized };
    }
    splats.push({ name: o.name, matrixWorld: o.matrixWorld.elements, attributes,
                  extension: o.userData.gltfExtensions?.KHR_gaussian_splatting ?? null });
});
writeFileSync(join(out, 'three.json'), JSON.stringify({ splats }, null, 1));

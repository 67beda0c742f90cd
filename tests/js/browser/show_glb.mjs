import * as THREE from 'three/webgpu';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { GLTFGaussianSplatLoaderExtension } from 'three/addons/loaders/GLTFGaussianSplatLoaderExtension.js';

async function main() {
    const query = new URLSearchParams(location.search);
    const cam = await (await fetch(query.get('camera'))).json();
    const renderer = new THREE.WebGPURenderer({ antialias: false, forceWebGL: query.get('webgl') === '1' });
    renderer.setPixelRatio(1);
    renderer.setSize(cam.width, cam.height);
    document.body.appendChild(renderer.domElement);
    await renderer.init();

    const scene = new THREE.Scene();

    const camera = new THREE.PerspectiveCamera();
    camera.matrixAutoUpdate = false;
    camera.matrix.set(...cam.camera_to_world.flat());
    camera.matrix.decompose(camera.position, camera.quaternion, camera.scale);
    const { width: w, height: h, fx, fy, cx, cy, near, far } = cam;
    camera.projectionMatrix.set(
        2 * fx / w, 0, 1 - 2 * cx / w, 0,
        0, 2 * fy / h, 2 * cy / h - 1, 0,
        0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
        0, 0, -1, 0);
    camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
    camera.updateMatrixWorld(true);

    const loader = new GLTFLoader();
    loader.register((parser) => new GLTFGaussianSplatLoaderExtension(parser));
    const gltf = await loader.loadAsync(query.get('model'));
    scene.add(gltf.scene);
    // KHR_gaussian_splatting: splats blend in the colour space the file names, and the result is shown as it is for
    // srgb_rec709_display, sRGB-encoded after blending for lin_rec709_display. three.js' splat material hands its
    // colours over as they are, so the output encoding is the page's to set from the file.
    let space = null;
    gltf.scene.traverse((o) => { if (o.isGaussianSplat) space = o.userData.gltfExtensions.KHR_gaussian_splatting.colorSpace; });
    if (space === null) throw new Error('no Gaussian splat in the file');
    renderer.outputColorSpace = space === 'lin_rec709_display' ? THREE.SRGBColorSpace : THREE.LinearSRGBColorSpace;
    // (the background is given in the model's colour space, the one blending happens in)
    renderer.setClearColor(new THREE.Color().setRGB(...cam.background, THREE.LinearSRGBColorSpace), 1);
    for (let i = 0; i < 3; i++) renderer.render(scene, camera);     // (sorted after the first)
    await renderer.backend.device?.queue?.onSubmittedWorkDone?.();
    document.title = `ready ${renderer.backend.isWebGPUBackend ? 'webgpu' : 'webgl2'}`;
}

main().catch((e) => { document.title = `error: ${e && e.message ? e.message : e}`; console.error(e); });

// Load a .glb / .vrm the way a three.js app does (GLTFLoader, with @pixiv/three-vrm's plugin
// for a .vrm) and print what the app sees as JSON: each mesh's morph targets by name, and the
// VRM's expressions with the morph targets each one drives.
// Node has no image decoder: each texture is an empty three.js Texture (the images are not
// decoded; everything else is loaded as in a browser).
// Usage: node load_avatar.mjs FILE
import { readFileSync } from 'node:fs';
import { Texture } from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { VRMLoaderPlugin } from '@pixiv/three-vrm';

const path = process.argv[2];
const bytes = readFileSync(path);
const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
const loader = new GLTFLoader();
loader.register((parser) => new VRMLoaderPlugin(parser));
loader.register(() => ({ name: 'no_image_decoding', loadTexture: () => Promise.resolve(new Texture()) }));
loader.parse(buffer, '', (gltf) => {
  const meshes = [];
  gltf.scene.traverse((object) => {
    if (object.isMesh && object.morphTargetDictionary) {
      meshes.push({
        name: object.name,
        skinned: Boolean(object.isSkinnedMesh),
        vertices: object.geometry.attributes.position.count,
        targets: Object.keys(object.morphTargetDictionary),
      });
    }
  });
  const out = { meshes, vrm: null };
  const vrm = gltf.userData.vrm;
  if (vrm) {
    const expressions = {};
    for (const expression of vrm.expressionManager.expressions) {
      expressions[expression.expressionName] = expression._binds.length;
    }
    out.vrm = {
      metaVersion: vrm.meta.metaVersion,
      head: vrm.humanoid.getRawBoneNode('head')?.name ?? null,
      expressions,
    };
    // drive one expression as an app would, and read the weight it set
    vrm.expressionManager.setValue('aa', 1.0);
    vrm.expressionManager.update();
    let jaw = null;
    gltf.scene.traverse((object) => {
      if (object.isMesh && object.morphTargetDictionary && 'jawOpen' in object.morphTargetDictionary) {
        jaw = object.morphTargetInfluences[object.morphTargetDictionary.jawOpen];
      }
    });
    out.vrm.jawOpenAfterAa = jaw;
  }
  process.stdout.write(JSON.stringify(out) + '\n');
}, (error) => {
  process.stderr.write(String(error && error.stack || error) + '\n');
  process.exit(1);
});

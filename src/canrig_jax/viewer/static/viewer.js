// canrig view: the glb served at model.glb, its animation on a timeline, its morph targets
// on sliders, wireframe and COLOR_0 toggles. `window.canrig` is the page's API for scripts
// (the headless screenshot and the browser tests drive it through the DevTools protocol).
import {
  AnimationMixer, Box3, Color, DirectionalLight, DoubleSide, HemisphereLight, PerspectiveCamera,
  Scene, Vector3, WebGLRenderer, GLTFLoader, OrbitControls,
} from './three.min.js';

const BACKGROUND = 0x1e2226;
const $ = (id) => document.getElementById(id);
const view = $('view');

const renderer = new WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
view.appendChild(renderer.domElement);
const scene = new Scene();
scene.background = new Color(BACKGROUND);
scene.add(new HemisphereLight(0xffffff, 0x334455, 0.8));
const key = new DirectionalLight(0xffffff, 1.5);
key.position.set(0.4, 0.6, 1.0);
scene.add(key);
const camera = new PerspectiveCamera(30, 1, 0.1, 1e4);
const controls = new OrbitControls(camera, renderer.domElement);
controls.addEventListener('change', () => render());

const state = {
  mixer: null, action: null, duration: 0, time: 0, playing: false,
  meshes: [], names: [], overrides: new Map(), held: [], sliders: new Map(), hasColors: false,
};

function resize() {
  const w = Math.max(1, view.clientWidth), h = Math.max(1, view.clientHeight);
  renderer.setSize(w, h, false);
  renderer.domElement.style.width = w + 'px';
  renderer.domElement.style.height = h + 'px';
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}

// three's mixer writes a weight only when its own value changes, so a held (overridden)
// weight keeps the value it replaced in `state.held` and gets it back before the mixer runs.
function applyPose() {
  for (const [mesh, i, value] of state.held) mesh.morphTargetInfluences[i] = value;
  state.held = [];
  if (state.mixer) state.mixer.setTime(state.time);
  for (const mesh of state.meshes) {
    const dict = mesh.morphTargetDictionary || {};
    for (const [name, value] of state.overrides) {
      if (!(name in dict)) continue;
      state.held.push([mesh, dict[name], mesh.morphTargetInfluences[dict[name]]]);
      mesh.morphTargetInfluences[dict[name]] = value;
    }
  }
}

function render() {
  renderer.render(scene, camera);
}

function showSliders() {  // sliders follow the pose unless the user holds them
  const mesh = state.meshes[0];
  if (!mesh) return;
  for (const [name, slider] of state.sliders) {
    if (state.overrides.has(name)) continue;
    const v = mesh.morphTargetInfluences[mesh.morphTargetDictionary[name]] || 0;
    slider.input.value = v;
    slider.value.textContent = v.toFixed(2);
  }
}

function setTime(t) {
  state.time = Math.min(Math.max(Number(t) || 0, 0), state.duration);
  $('time').value = state.time;
  $('clock').textContent = state.time.toFixed(3) + ' s';
  applyPose();
  render();
  showSliders();
  return state.time;
}

function setMorph(name, value) {
  if (!state.sliders.has(name)) throw new Error('no morph target named ' + name);
  if (value === null || value === undefined) state.overrides.delete(name);
  else state.overrides.set(name, Number(value));
  const slider = state.sliders.get(name);
  if (value !== null && value !== undefined) {
    slider.input.value = value;
    slider.value.textContent = Number(value).toFixed(2);
  }
  slider.row.style.color = state.overrides.has(name) ? '#fc6' : '';
  return setTime(state.time);
}

function setWireframe(on) {
  $('wireframe').checked = !!on;
  for (const mesh of state.meshes) {
    for (const m of [].concat(mesh.material)) m.wireframe = !!on;
  }
  render();
}

function setColors(on) {
  on = !!on && state.hasColors;
  $('colors').checked = on;
  for (const mesh of state.meshes) {
    if (!mesh.geometry.attributes.color) continue;
    for (const m of [].concat(mesh.material)) { m.vertexColors = on; m.needsUpdate = true; }
  }
  render();
}

function frame(object) {  // the camera in front of the head (+Z), the box filling the view
  frameBox(new Box3().setFromObject(object));
}

function frameBox(box) {
  const center = box.getCenter(new Vector3()), size = box.getSize(new Vector3());
  const radius = 0.5 * size.length();
  const distance = radius / Math.sin((camera.fov * Math.PI) / 360);
  camera.near = distance / 100;
  camera.far = distance * 100;
  camera.position.copy(center).add(new Vector3(0, 0, distance * 0.9));
  camera.updateProjectionMatrix();
  controls.target.copy(center);
  controls.update();
}

function frameMorphs() {  // the camera on what the morph targets move (a whole avatar's face)
  const box = new Box3(), p = new Vector3();
  for (const mesh of state.meshes) {
    const targets = mesh.geometry.morphAttributes.position || [];
    if (!targets.length) continue;
    mesh.updateWorldMatrix(true, false);
    const saved = mesh.morphTargetInfluences.slice();
    mesh.morphTargetInfluences.fill(0);  // the rest shape, posed by the skeleton at rest
    const relative = mesh.geometry.morphTargetsRelative;
    const base = mesh.geometry.attributes.position;
    for (let i = 0; i < base.count; i++) {
      let moved = false;
      for (const t of targets) {
        const dx = t.getX(i) - (relative ? 0 : base.getX(i));
        const dy = t.getY(i) - (relative ? 0 : base.getY(i));
        const dz = t.getZ(i) - (relative ? 0 : base.getZ(i));
        if (dx * dx + dy * dy + dz * dz > 1e-12) { moved = true; break; }
      }
      if (moved) box.expandByPoint(mesh.localToWorld(mesh.getVertexPosition(i, p)));
    }
    mesh.morphTargetInfluences.splice(0, saved.length, ...saved);
  }
  if (box.isEmpty()) return false;
  frameBox(box);
  render();
  return true;
}

function buildSliders() {
  const list = $('morphs');
  for (const name of state.names) {
    const row = document.createElement('label');
    const label = document.createElement('span');
    label.textContent = name;
    label.title = name;
    const input = document.createElement('input');
    Object.assign(input, { type: 'range', min: 0, max: 1, step: 0.01, value: 0 });
    input.dataset.morph = name;
    const value = document.createElement('span');
    value.textContent = '0.00';
    input.addEventListener('input', () => setMorph(name, input.value));
    row.append(label, input, value);
    list.appendChild(row);
    state.sliders.set(name, { row, input, value });
  }
}

function tick(now) {
  if (state.playing && state.duration > 0) {
    const dt = (now - (state.last ?? now)) / 1000;
    setTime((state.time + dt) % state.duration);
  }
  state.last = now;
  requestAnimationFrame(tick);
}

function fail(message) {
  $('status').textContent = message;
  console.error(message);
}

const ready = new GLTFLoader().loadAsync('model.glb').then((gltf) => {
  const root = gltf.scene;
  scene.add(root);
  root.traverse((o) => { if (o.isMesh) state.meshes.push(o); });
  const ownMaterials = (gltf.parser.json.materials || []).length > 0;
  for (const mesh of state.meshes) {  // open heads: the inside shows through the holes
    for (const m of [].concat(mesh.material)) {
      m.side = DoubleSide;
      // glTF's default material is fully metallic: black without an environment map
      if (!ownMaterials) Object.assign(m, { metalness: 0, roughness: 0.75 });
    }
  }
  state.root = root;
  const names = new Set();
  for (const mesh of state.meshes) {
    for (const name of Object.keys(mesh.morphTargetDictionary || {})) names.add(name);
    if (mesh.geometry.attributes.color) state.hasColors = true;
  }
  state.names = [...names];
  if (gltf.animations.length) {
    state.mixer = new AnimationMixer(root);
    state.action = state.mixer.clipAction(gltf.animations[0]);
    state.action.play();
    state.duration = gltf.animations[0].duration;
  }
  $('time').max = state.duration;
  $('time').disabled = !state.mixer;
  $('play').disabled = !state.mixer;
  $('colors').disabled = !state.hasColors;
  $('file').textContent = document.title;  // the file's name (the server writes it)
  buildSliders();
  resize();
  frame(root);
  setColors(state.hasColors);
  setTime(0);
  return {
    meshes: state.meshes.length,
    vertices: state.meshes.reduce((n, m) => n + m.geometry.attributes.position.count, 0),
    morphs: state.names,
    duration: state.duration,
    colors: state.hasColors,
    animation: gltf.animations.length ? gltf.animations[0].name : null,
  };
}).catch((error) => { fail('could not load model.glb: ' + error); throw error; });

function play(on) {
  state.playing = !!on && state.duration > 0;
  $('play').textContent = state.playing ? 'pause' : 'play';
}

$('time').addEventListener('input', (e) => { play(false); setTime(e.target.value); });
$('play').addEventListener('click', () => play(!state.playing));
$('wireframe').addEventListener('change', (e) => setWireframe(e.target.checked));
$('colors').addEventListener('change', (e) => setColors(e.target.checked));
$('reset').addEventListener('click', () => {
  for (const name of [...state.overrides.keys()]) setMorph(name, null);
});
window.addEventListener('resize', () => { resize(); render(); });
requestAnimationFrame(tick);

function toPixels(world) {  // a world point -> [x, y] pixels in the canvas (top left 0, 0)
  const p = world.clone().project(camera), c = renderer.domElement;
  return [((p.x + 1) / 2) * c.clientWidth, ((1 - p.y) / 2) * c.clientHeight];
}

window.canrig = { ready, setTime, setMorph, setWireframe, setColors, frameMorphs,
  pause() { play(false); },
  time() { return state.time; },
  // [[x, y], ...] pixels of points given in the first mesh's own coordinates, as now posed
  project(points) {
    const mesh = state.meshes[0];
    mesh.updateWorldMatrix(true, false);
    return points.map((p) => toPixels(new Vector3(...p).applyMatrix4(mesh.matrixWorld)));
  },
  // [xmin, ymin, xmax, ymax] pixels of the model's bounding box (rest shape) as now posed
  screenBox() {
    const box = new Box3().setFromObject(state.root), xs = [], ys = [];
    for (const x of [box.min.x, box.max.x]) for (const y of [box.min.y, box.max.y])
      for (const z of [box.min.z, box.max.z]) {
        const [u, v] = toPixels(new Vector3(x, y, z)); xs.push(u); ys.push(v);
      }
    return [Math.min(...xs), Math.min(...ys), Math.max(...xs), Math.max(...ys)];
  } };

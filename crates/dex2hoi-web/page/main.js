// The page: the request form, the 3D view of the generated motion and its downloads. The
// model runs in worker.js. For tests, `document.body.dataset.state` says where the page
// stands (loading, ready, submitting, generating, done, error, failed) and `window.dex2hoiResult` holds
// the last motion's joints and timings.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const $ = (id) => document.getElementById(id);

// Colours of the preview (sRGB): the hands' contact states, the floor tiles, the table.
const HAND_CONTACT = 0xfacc20;
const HAND_INSIDE = 0xe42424;
const FLOOR_LIGHT = 0xcdcbc4;
const FLOOR_DARK = 0xacaaa3;
const TABLE = 0x966840;
const BACKGROUND = 0xdee6f0;

function setState(state) {
  document.body.dataset.state = state;
}

function say(text, kind = '') {
  const message = $('message');
  message.textContent = text;
  message.className = kind;
}

// ---- The 3D view ----

const canvas = $('canvas');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
const scene = new THREE.Scene();
scene.background = new THREE.Color(BACKGROUND);
scene.add(new THREE.HemisphereLight(0xffffff, 0x8d8a80, 2.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(2, 4, 3);
scene.add(sun);

// The preview's three-quarter view from the character's front left (+Z ahead, +X left).
const camera = new THREE.PerspectiveCamera(35, 4 / 3, 0.05, 100);
const target = new THREE.Vector3(0, 0.95, 0.3);
const yaw = THREE.MathUtils.degToRad(35);
const pitch = THREE.MathUtils.degToRad(20);
const distance = 3.0;
camera.position.set(
  target.x + distance * Math.sin(yaw) * Math.cos(pitch),
  target.y + distance * Math.sin(pitch),
  target.z + distance * Math.cos(yaw) * Math.cos(pitch),
);
const controls = new OrbitControls(camera, canvas);
controls.target.copy(target);
controls.update();
// The view is drawn only when something changed: while a motion is generated it stands
// still, so that drawing (in software where there is no GPU) does not take the CPU from the
// model.
let needsDrawing = true;
let generating = false;
controls.addEventListener('change', () => {
  needsDrawing = true;
});

scene.add(checkerFloor(8, 0.5));

function checkerFloor(size, tile) {
  const tiles = Math.round(size / tile);
  const geometry = new THREE.PlaneGeometry(size, size, tiles, tiles).toNonIndexed();
  geometry.rotateX(-Math.PI / 2);
  const colours = [];
  const light = new THREE.Color(FLOOR_LIGHT);
  const dark = new THREE.Color(FLOOR_DARK);
  const position = geometry.attributes.position;
  for (let triangle = 0; triangle < position.count / 3; triangle++) {
    // The centre of the triangle names its tile.
    let x = 0;
    let z = 0;
    for (let k = 0; k < 3; k++) {
      x += position.getX(3 * triangle + k) / 3;
      z += position.getZ(3 * triangle + k) / 3;
    }
    const colour = (Math.floor(x / tile) + Math.floor(z / tile)) % 2 === 0 ? light : dark;
    for (let k = 0; k < 3; k++) {
      colours.push(colour.r, colour.g, colour.b);
    }
  }
  geometry.setAttribute('color', new THREE.Float32BufferAttribute(colours, 3));
  return new THREE.Mesh(geometry, new THREE.MeshLambertMaterial({ vertexColors: true }));
}

function tableMesh([height, centreX, centreZ, halfWidth, halfDepth]) {
  const group = new THREE.Group();
  const material = new THREE.MeshLambertMaterial({ color: TABLE });
  const top = new THREE.Mesh(new THREE.BoxGeometry(2 * halfWidth, 0.04, 2 * halfDepth), material);
  top.position.set(centreX, height - 0.02, centreZ);
  group.add(top);
  for (const sx of [-1, 1]) {
    for (const sz of [-1, 1]) {
      const leg = new THREE.Mesh(new THREE.BoxGeometry(0.05, height - 0.04, 0.05), material);
      leg.position.set(
        centreX + sx * (halfWidth - 0.05),
        (height - 0.04) / 2,
        centreZ + sz * (halfDepth - 0.05),
      );
      group.add(leg);
    }
  }
  return group;
}

// What is shown: the motion's scene, its animation and the hands' colouring.
let shown = null;
let playing = true;
const clock = new THREE.Clock();

function clearShown() {
  if (shown !== null) {
    scene.remove(shown.root);
    shown = null;
    needsDrawing = true;
  }
  $('player').hidden = true;
  $('downloads').hidden = true;
}

// The body mesh of motion.glb is skinned with one joint per vertex (the capsule body):
// per joint, its vertices, so the hands can be coloured by their joints' contact states.
function handColouring(gltf, result) {
  let body = null;
  gltf.scene.traverse((node) => {
    if (node.isSkinnedMesh && body === null) {
      body = node;
    }
  });
  if (body === null) {
    return null;
  }
  const geometry = body.geometry;
  const skinIndex = geometry.attributes.skinIndex;
  const base = body.material.color.clone();
  body.material = body.material.clone();
  body.material.color.set(0xffffff);
  body.material.vertexColors = true;
  const colours = new Float32Array(skinIndex.count * 3);
  const verticesOf = new Map();
  for (let v = 0; v < skinIndex.count; v++) {
    const joint = skinIndex.getX(v);
    if (!verticesOf.has(joint)) {
      verticesOf.set(joint, []);
    }
    verticesOf.get(joint).push(v);
    base.toArray(colours, 3 * v);
  }
  const attribute = new THREE.BufferAttribute(colours, 3);
  geometry.setAttribute('color', attribute);
  const palette = [base, new THREE.Color(HAND_CONTACT), new THREE.Color(HAND_INSIDE)];
  // The joints that are ever not free: only those need recolouring.
  const touching = new Set();
  for (let i = 0; i < result.contacts.length; i++) {
    if (result.contacts[i] !== 0) {
      touching.add(i % result.jointCount);
    }
  }
  let lastFrame = -1;
  return (frame) => {
    if (frame === lastFrame) {
      return;
    }
    lastFrame = frame;
    for (const joint of touching) {
      const colour = palette[result.contacts[frame * result.jointCount + joint]];
      for (const v of verticesOf.get(joint) ?? []) {
        colour.toArray(colours, 3 * v);
      }
    }
    attribute.needsUpdate = true;
  };
}

function show(result) {
  return new Promise((resolve, reject) => {
    new GLTFLoader().parse(result.glb.buffer.slice(0), '', (gltf) => {
      clearShown();
      const root = new THREE.Group();
      root.add(gltf.scene);
      if (result.table) {
        root.add(tableMesh(result.table));
      }
      scene.add(root);
      const mixer = new THREE.AnimationMixer(gltf.scene);
      const clip = gltf.animations[0];
      mixer.clipAction(clip).play();
      shown = {
        root,
        mixer,
        duration: clip.duration,
        time: 0,
        fps: result.fps,
        frames: result.frames,
        colour: handColouring(gltf, result),
      };
      playing = true;
      $('play').textContent = 'Pause';
      $('player').hidden = false;
      needsDrawing = true;
      resolve();
    }, reject);
  });
}

function setTime(seconds) {
  if (shown === null) {
    return;
  }
  // The last key is at (frames - 1) / fps: the loop wraps there.
  const length = Math.max(shown.duration, 1e-6);
  shown.time = ((seconds % length) + length) % length;
  shown.mixer.setTime(shown.time);
  const frame = Math.min(shown.frames - 1, Math.round(shown.time * shown.fps));
  if (shown.colour) {
    shown.colour(frame);
  }
  $('time').value = String(shown.time / length);
  $('clock').textContent = `${shown.time.toFixed(1)} / ${length.toFixed(1)} s`;
  needsDrawing = true;
}

function resize() {
  const width = canvas.clientWidth;
  const height = canvas.clientHeight;
  if (canvas.width !== Math.floor(width * renderer.getPixelRatio()) ||
      canvas.height !== Math.floor(height * renderer.getPixelRatio())) {
    renderer.setSize(width, height, false);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
    needsDrawing = true;
  }
}

renderer.setAnimationLoop(() => {
  const dt = clock.getDelta();
  resize();
  if (shown !== null && playing && !generating) {
    setTime(shown.time + dt);
  }
  if (needsDrawing) {
    needsDrawing = false;
    renderer.render(scene, camera);
  }
});

$('play').addEventListener('click', () => {
  playing = !playing;
  $('play').textContent = playing ? 'Pause' : 'Play';
});
$('time').addEventListener('input', () => {
  if (shown !== null) {
    playing = false;
    $('play').textContent = 'Play';
    setTime(Number($('time').value) * shown.duration);
  }
});

// ---- Downloads ----

const downloadUrls = [];

function offerDownloads(result) {
  downloadUrls.splice(0).forEach((url) => URL.revokeObjectURL(url));
  const offer = (id, data, type) => {
    const url = URL.createObjectURL(new Blob([data], { type }));
    downloadUrls.push(url);
    $(id).href = url;
  };
  offer('download-glb', result.glb, 'model/gltf-binary');
  offer('download-npz', result.npz, 'application/octet-stream');
  offer('download-bvh', result.bvh, 'text/plain');
  $('downloads').hidden = false;
}

// ---- The model, in its worker ----

const worker = new Worker(new URL('./worker.js', import.meta.url), { type: 'module' });
let fps = 20;
let maxFrames = 1200;

worker.onmessage = async (event) => {
  const data = event.data;
  switch (data.type) {
    case 'ready': {
      fps = data.fps;
      maxFrames = data.maxFrames;
      for (const select of [$('object-a'), $('object-b')]) {
        for (const name of data.objects) {
          select.add(new Option(name, name));
        }
      }
      $('object-a').value = data.objects.includes('mug') ? 'mug' : data.objects[0];
      $('seconds').max = String(maxFrames / fps);
      $('model-info').textContent =
        `The shipped dex2hoi model (${data.words} words, ${fps} frames per second).`;
      $('generate').disabled = false;
      say('');
      setState('ready');
      break;
    }
    case 'progress': {
      $('progress').value = data.done / data.total;
      $('progress-text').textContent = `${data.done} of ${data.total} frames`;
      break;
    }
    case 'done': {
      generating = false;
      $('progress-row').hidden = true;
      $('generate').disabled = false;
      window.dex2hoiResult = {
        joints: Array.from(data.joints),
        frames: data.frames,
        jointCount: data.jointCount,
        generationSeconds: data.generationSeconds,
        elapsedSeconds: data.elapsedSeconds,
      };
      try {
        await show(data);
      } catch (error) {
        clearShown();
        say(`the motion could not be shown: ${error.message ?? error}`, 'error');
        setState('error');
        return;
      }
      offerDownloads(data);
      const timing = `${data.frames} frames (${(data.frames / data.fps).toFixed(1)} s of motion)` +
        ` generated in ${data.elapsedSeconds.toFixed(1)} s.`;
      if (data.warning) {
        say(`Warning: ${data.warning}.\n${timing}`, 'warning');
      } else {
        say(timing);
      }
      setState('done');
      break;
    }
    case 'error': {
      generating = false;
      $('progress-row').hidden = true;
      $('generate').disabled = false;
      clearShown();
      window.dex2hoiResult = null;
      say(`Error: ${data.message}`, 'error');
      setState('error');
      break;
    }
    case 'failed': {
      say(`The model could not be loaded: ${data.message}`, 'error');
      setState('failed');
      break;
    }
    default:
      break;
  }
};

$('request').addEventListener('submit', async (event) => {
  event.preventDefault();
  setState('submitting');
  const seconds = Number($('seconds').value);
  const frames = Math.round(seconds * fps);
  const seed = Number($('seed').value);
  if (!Number.isInteger(seed) || seed < 0) {
    say('Error: the seed must be a whole number, 0 or more', 'error');
    setState('error');
    return;
  }
  if (!(frames >= 1 && frames <= maxFrames)) {
    say(`Error: the length must be between ${1 / fps} and ${maxFrames / fps} s`, 'error');
    setState('error');
    return;
  }
  const file = $('mesh').files[0];
  const mesh = file ? { name: file.name, bytes: new Uint8Array(await file.arrayBuffer()) } : null;
  const objects = [];
  if (!mesh) {
    objects.push($('object-a').value);
  }
  if ($('object-b').value) {
    objects.push($('object-b').value);
  }
  $('generate').disabled = true;
  $('progress').value = 0;
  $('progress-text').textContent = `0 of ${frames} frames`;
  $('progress-row').hidden = false;
  say('Generating…');
  generating = true;
  setState('generating');
  worker.postMessage({ type: 'generate', prompt: $('prompt').value, objects, mesh, seed, frames });
});

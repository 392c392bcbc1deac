// The model runs here, off the page's main thread, so that the page stays responsive and can
// show progress while a motion is generated. Messages in: {type: 'generate', ...}. Messages
// out: 'ready' (once the model is loaded), 'progress', 'done' and 'error'.
import init, { Generator, catalogue } from './pkg/dex2hoi_web.js';

let generator = null;

// Called by the WebAssembly module after each generated window.
globalThis.dex2hoiProgress = (done, total) => postMessage({ type: 'progress', done, total });

function message(error) {
  return String(error && error.message !== undefined ? error.message : error);
}

async function start() {
  try {
    await init();
    const response = await fetch(new URL('./model.safetensors', import.meta.url));
    if (!response.ok) {
      throw new Error(`model.safetensors: HTTP ${response.status}`);
    }
    generator = new Generator(new Uint8Array(await response.arrayBuffer()));
    postMessage({
      type: 'ready',
      fps: generator.fps(),
      maxFrames: generator.maxFrames(),
      objects: catalogue(),
      words: generator.words().length,
    });
  } catch (error) {
    postMessage({ type: 'failed', message: message(error) });
  }
}

onmessage = (event) => {
  const request = event.data;
  if (request.type !== 'generate' || generator === null) {
    return;
  }
  try {
    const started = performance.now();
    const motion = generator.generate(
      request.prompt,
      request.mesh ? request.mesh.name : undefined,
      request.mesh ? request.mesh.bytes : undefined,
      request.objects,
      BigInt(request.seed),
      request.frames,
      true,
    );
    const result = {
      type: 'done',
      warning: generator.warning(request.prompt),
      glb: motion.glb(),
      npz: motion.npz(),
      bvh: motion.bvh(),
      joints: motion.joints(),
      contacts: motion.handContacts(),
      table: motion.table(),
      frames: motion.frames(),
      jointCount: motion.jointCount(),
      fps: motion.fps(),
      generationSeconds: motion.seconds(),
      elapsedSeconds: (performance.now() - started) / 1000,
    };
    motion.free();
    postMessage(result, [result.glb.buffer, result.npz.buffer, result.joints.buffer,
      result.contacts.buffer]);
  } catch (error) {
    postMessage({ type: 'error', message: message(error) });
  }
};

start();

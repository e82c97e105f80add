// The viewer page: loads the avatar folder it is served from, poses its Gaussians on the GPU
// (gom.js) and draws them with Spark. `window.lifegom.show({ view, motion, time })` draws one
// exact frame for tests and resolves once it is on the canvas.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { ExtSplats, SparkRenderer, SplatMesh, dyno } from '@sparkjsdev/spark';
import { loadViewerData } from './data.js';
import {
  FACE_TEXELS,
  PER_ROW,
  GOM_GLSL,
  gaussianTexels,
  skinVertices,
  skinningTransforms,
  sparseWeights,
  topologicalOrder,
  writeFaceFrames,
} from './gom.js';

// The Rust renderer's colours are the pixel values themselves (the Gaussians reproduce sRGB
// photos): no colour management anywhere, so a colour goes to the canvas as it is stored.
THREE.ColorManagement.enabled = false;

const ui = {
  canvasBox: document.getElementById('canvas-box'),
  error: document.getElementById('error'),
  motion: document.getElementById('motion'),
  play: document.getElementById('play'),
  scrub: document.getElementById('scrub'),
  time: document.getElementById('time'),
  view: document.getElementById('view'),
  fps: document.getElementById('fps'),
  info: document.getElementById('info'),
};

const TPOSE = 'tpose';

function showError(message) {
  ui.error.textContent = message;
  ui.error.hidden = false;
  document.body.classList.add('failed');
}

/** Three's perspective projection for OpenCV intrinsics (pixel (i, j) covers [i, i+1) × [j, j+1)). */
function projectionFromK(K, width, height, near, far) {
  const [[fx, , cx], [, fy, cy]] = K;
  return new THREE.Matrix4().set(
    (2 * fx) / width, 0, 1 - (2 * cx) / width, 0,
    0, (2 * fy) / height, (2 * cy) / height - 1, 0,
    0, 0, -(far + near) / (far - near), (-2 * far * near) / (far - near),
    0, 0, -1, 0,
  );
}

class Viewer {
  constructor(data) {
    this.data = data;
    const { avatar } = data;
    this.avatar = avatar;
    this.motions = new Map(data.motions.map((m) => [m.name, m]));
    this.skeleton = {
      parents: avatar.skeleton.parents,
      rest: Float64Array.from(avatar.skeleton.rest),
      order: topologicalOrder(avatar.skeleton.parents),
    };
    this.skin = sparseWeights(avatar.weights, avatar.lowresVertices, avatar.joints);
    this.transforms = new Float64Array(12 * avatar.joints);
    this.posed = new Float64Array(3 * avatar.lowresVertices);
    this.motion = data.motions[0]?.name ?? TPOSE;
    this.time = 0;
    this.playing = false;
    this.poseKey = null;
    this.frameTimes = [];
    this.poseMs = [];
  }

  async init() {
    const first = this.data.views[0];
    const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    renderer.setPixelRatio(1);
    renderer.setSize(first.width, first.height);
    renderer.outputColorSpace = THREE.SRGBColorSpace;
    const gl = renderer.getContext();
    const maxTex = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    const need = PER_ROW * 5;
    if (maxTex < need) throw new Error(`this browser's WebGL allows textures of ${maxTex} texels, the viewer needs ${need}`);
    const [r, g, b] = this.avatar.background;
    renderer.setClearColor(new THREE.Color(r, g, b), 1);
    ui.canvasBox.appendChild(renderer.domElement);
    this.renderer = renderer;

    const scene = new THREE.Scene();
    // Spark's settings are chosen to match lifegom's rasterizer (design.md §6.2): 0.3 px² added
    // to the 2D covariance without opacity compensation, depth (not radial) sorting, alpha
    // cut at 1/255, Gaussians drawn to 3 standard deviations; the covariance path carries
    // the face-frame covariances (not axis-aligned scales) at full precision.
    this.spark = new SparkRenderer({
      renderer,
      preBlurAmount: 0.3,
      blurAmount: 0,
      sortRadial: false,
      minAlpha: 1 / 255,
      maxStdDev: 3,
      clipXY: 2,
      covSplats: true,
      accumExtSplats: true,
      onDirty: () => this.requestDraw(),
    });
    scene.add(this.spark);

    const a = this.avatar;
    const gt = gaussianTexels(a);
    const gaussTex = new THREE.DataTexture(gt.data, gt.width, gt.height, THREE.RGBAFormat, THREE.FloatType);
    gaussTex.needsUpdate = true;
    const faceRows = Math.max(1, Math.ceil(a.lowresFaces / PER_ROW));
    this.faceTexels = new Float32Array(4 * PER_ROW * FACE_TEXELS * faceRows);
    this.faceTex = new THREE.DataTexture(this.faceTexels, PER_ROW * FACE_TEXELS, faceRows, THREE.RGBAFormat, THREE.FloatType);
    this.faceTex.needsUpdate = true;
    const gs = new dyno.DynoSampler2D({ key: 'gomGaussians', value: gaussTex });
    const fs = new dyno.DynoSampler2D({ key: 'gomFaces', value: this.faceTex });
    const modifier = dyno.dynoBlock({ covsplat: dyno.CovSplat }, { covsplat: dyno.CovSplat }, ({ covsplat }) => {
      const d = new dyno.Dyno({
        inTypes: { covsplat: dyno.CovSplat, gs: 'sampler2D', fs: 'sampler2D' },
        outTypes: { covsplat: dyno.CovSplat },
        inputs: { covsplat, gs, fs },
        globals: () => [GOM_GLSL],
        statements: ({ inputs, outputs }) => [
          `${outputs.covsplat} = ${inputs.covsplat};`,
`gomPose(${inputs.gs}, ${inputs.fs}, ${outputs.covsplat}.index, ${outputs.covsplat}.center, ${outputs.covsplat}.xxyyzz, ${outputs.covsplat}.xyxzyz, ${outputs.covsplat}.rgba);`,
        ],
      });
      return { covsplat: d.outputs.covsplat };
    });
    const center = new THREE.Vector3();
    const unit = new THREE.Vector3(1, 1, 1);
    const quat = new THREE.Quaternion();
    // White: Spark 2.2.0 skips a black ExtSplats splat before any modifier sees it.
    const color = new THREE.Color(1, 1, 1);
    // The splats' own fields are placeholders: the modifier replaces centre, covariance,
    // colour and opacity of every one, by index. The arrays are filled first and handed over
    // whole: Spark 2.2.0 uploads an ExtSplats' textures only when built from arrays (filled
    // through `constructSplats`, they stay empty and nothing is drawn).
    const filling = new ExtSplats();
    for (let i = 0; i < a.gaussians; i++) filling.pushSplat(center, unit, quat, 1, color);
    const ext = new ExtSplats({ extArrays: filling.extArrays, numSplats: a.gaussians });
    this.mesh = new SplatMesh({ extSplats: ext, covSplats: true });
    // Set after construction: Spark 2.2.0's constructor ignores the `covObjectModifiers` option.
    this.mesh.covObjectModifiers = [modifier];
    this.mesh.updateGenerator();
    this.mesh.maxSh = 0;
    await this.mesh.initialized;
    scene.add(this.mesh);
    this.scene = scene;

    this.camera = new THREE.PerspectiveCamera();
    this.controls = new OrbitControls(this.camera, renderer.domElement);
    this.controls.addEventListener('change', () => this.requestDraw());
    this.setView(0);
    this.setPose();
    this.buildUi();
    this.loop();
  }

  /** Puts the camera at views.json's view `k` (OpenCV world-to-camera `E`, intrinsics `K`). */
  setView(k) {
    const v = this.data.views[k];
    if (!v) throw new Error(`no view ${k} (views.json has ${this.data.views.length})`);
    this.viewIndex = k;
    if (this.renderer.domElement.width !== v.width || this.renderer.domElement.height !== v.height) {
      this.renderer.setSize(v.width, v.height);
    }
    const cam = this.camera;
    cam.near = 0.2;
    cam.far = 1000;
    cam.projectionMatrix.copy(projectionFromK(v.K, v.width, v.height, cam.near, cam.far));
    cam.projectionMatrixInverse.copy(cam.projectionMatrix).invert();
    // three's camera looks down −z with y up: flip OpenCV's y and z.
    const e = v.E;
    const view = new THREE.Matrix4().set(...e[0], ...e[1], ...e[2], 0, 0, 0, 1);
    view.premultiply(new THREE.Matrix4().makeScale(1, -1, -1));
    const world = view.clone().invert();
    world.decompose(cam.position, cam.quaternion, new THREE.Vector3());
    cam.up.set(0, 1, 0).applyQuaternion(cam.quaternion);
    // Orbit about the point on the optical axis at the person's depth, so that the controls'
    // lookAt leaves this exact camera unchanged.
    const pivot = new THREE.Vector3(...this.data.pivot);
    const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(cam.quaternion);
    const depth = Math.max(0.5, pivot.clone().sub(cam.position).dot(forward));
    this.controls.target.copy(cam.position).addScaledVector(forward, depth);
    cam.updateMatrixWorld(true);
    this.requestDraw();
  }

  frameOf(motion, time) {
    const m = this.motions.get(motion);
    if (!m) return null;
    return ((Math.floor(time * m.fps + 1e-6) % m.frames) + m.frames) % m.frames;
  }

  /** Poses the low-res mesh for the current motion and time and uploads its face frames. */
  setPose() {
    const frame = this.frameOf(this.motion, this.time);
    const key = `${this.motion}:${frame}`;
    if (key === this.poseKey) return;
    const t0 = performance.now();
    const m = this.motions.get(this.motion);
    const pose = m ? m.poses.subarray(frame * 3 * this.avatar.joints, (frame + 1) * 3 * this.avatar.joints) : null;
    skinningTransforms(this.skeleton, pose, this.transforms);
    // lifegom's skinning transforms reach the vertices as f32.
    for (let i = 0; i < this.transforms.length; i++) this.transforms[i] = Math.fround(this.transforms[i]);
    skinVertices(this.avatar.xyz, this.skin, this.transforms, this.posed);
    for (let i = 0; i < this.posed.length; i++) this.posed[i] = Math.fround(this.posed[i]);
    writeFaceFrames(this.posed, this.avatar.faces, this.faceTexels);
    this.faceTex.needsUpdate = true;
    this.mesh.needsUpdate = true;
    this.poseKey = key;
    this.poseMs.push(performance.now() - t0);
    if (this.poseMs.length > 120) this.poseMs.shift();
    this.requestDraw();
  }

  requestDraw() {
    this.dirty = true;
  }

  loop() {
    let last = performance.now();
    const tick = (now) => {
      const dt = (now - last) / 1000;
      last = now;
      if (this.playing && !this.holding) {
        this.time += dt;
        this.syncTimeUi();
        this.setPose();
      }
      if ((this.dirty || this.playing) && !this.holding) {
        this.dirty = false;
        this.controls.update();
        this.renderer.render(this.scene, this.camera);
        this.frameTimes.push(now);
        while (this.frameTimes.length > 1 && now - this.frameTimes[0] > 2000) this.frameTimes.shift();
      }
      this.updateFps(now);
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  }

  fps(now = performance.now()) {
    const t = this.frameTimes.filter((x) => now - x <= 2000);
    if (t.length < 2) return 0;
    return (t.length - 1) / ((t[t.length - 1] - t[0]) / 1000);
  }

  updateFps(now) {
    if (!this.lastFpsUi || now - this.lastFpsUi > 500) {
      this.lastFpsUi = now;
      const p = this.poseMs.length ? this.poseMs.reduce((x, y) => x + y, 0) / this.poseMs.length : 0;
      ui.fps.textContent = `${this.fps(now).toFixed(1)} fps · pose ${p.toFixed(2)} ms`;
    }
  }

  duration() {
    const m = this.motions.get(this.motion);
    return m ? m.frames / m.fps : 0;
  }

  syncTimeUi() {
    const d = this.duration();
    const t = d > 0 ? this.time % d : 0;
    ui.scrub.max = String(d);
    ui.scrub.value = String(t);
    ui.time.textContent = `${t.toFixed(2)} / ${d.toFixed(2)} s`;
  }

  buildUi() {
    const add = (select, value, label) => {
      const o = document.createElement('option');
      o.value = value;
      o.textContent = label;
      select.appendChild(o);
    };
    for (const m of this.data.motions) add(ui.motion, m.name, m.name);
    add(ui.motion, TPOSE, 'T-pose');
    ui.motion.value = this.motion;
    this.data.views.forEach((v, k) => add(ui.view, String(k), v.name));
    ui.motion.addEventListener('change', () => {
      this.motion = ui.motion.value;
      this.time = 0;
      this.syncTimeUi();
      this.setPose();
    });
    ui.play.addEventListener('click', () => {
      this.playing = !this.playing;
      ui.play.textContent = this.playing ? 'Pause' : 'Play';
    });
    ui.scrub.addEventListener('input', () => {
      this.time = Number(ui.scrub.value);
      this.syncTimeUi();
      this.setPose();
    });
    ui.view.addEventListener('change', () => this.setView(Number(ui.view.value)));
    const a = this.avatar;
    ui.info.textContent = `${a.subject} · ${a.gaussians.toLocaleString('en')} Gaussians · ${a.subdivision} subdivisions`;
    this.syncTimeUi();
  }

  /** Waits until Spark has generated and sorted the current splats, then draws them. */
  async drawSettled() {
    this.holding = true;
    try {
      this.controls.update();
      this.renderer.render(this.scene, this.camera);
      const spark = this.spark;
      for (let i = 0; i < 2000 && (spark.sorting || spark.sortDirty); i++) {
        await new Promise((r) => setTimeout(r, 5));
      }
      if (spark.sorting || spark.sortDirty) throw new Error('Spark did not finish sorting in 10 s');
      this.renderer.render(this.scene, this.camera);
      this.renderer.getContext().finish();
      await new Promise((r) => requestAnimationFrame(() => r()));
    } finally {
      this.holding = false;
      this.dirty = false;
    }
  }

  async show({ view = 0, motion = TPOSE, time = 0 } = {}) {
    if (motion !== TPOSE && !this.motions.has(motion)) {
      throw new Error(`no motion \`${motion}\` (have: ${[...this.motions.keys(), TPOSE].join(', ')})`);
    }
    this.playing = false;
    ui.play.textContent = 'Play';
    this.motion = motion;
    ui.motion.value = motion;
    this.time = time;
    this.syncTimeUi();
    this.setView(view);
    ui.view.value = String(view);
    this.setPose();
    await this.drawSettled();
    return { view, motion, time, frame: this.frameOf(motion, time) };
  }
}

async function main() {
  const base = new URL('./', window.location.href);
  window.lifegom = {
    ready: null,
    show: async () => {
      throw new Error('the viewer did not load');
    },
  };
  const start = performance.now();
  const ready = (async () => {
    const data = await loadViewerData(base);
    const viewer = new Viewer(data);
    await viewer.init();
    await viewer.drawSettled();
    const firstFrameMs = performance.now() - start;
    Object.assign(window.lifegom, {
      viewer,
      firstFrameMs,
      views: data.views,
      motions: data.motions.map((m) => ({ name: m.name, fps: m.fps, frames: m.frames })),
      show: (args) => viewer.show(args),
      play: (on = true) => {
        viewer.playing = on;
        ui.play.textContent = on ? 'Pause' : 'Play';
      },
      stats: () => {
        const p = viewer.poseMs;
        return { fps: viewer.fps(), poseMs: p.length ? p.reduce((x, y) => x + y, 0) / p.length : 0 };
      },
    });
    document.body.dataset.ready = 'true';
    return viewer;
  })();
  window.lifegom.ready = ready.then(
    () => true,
    (e) => {
      showError(`This avatar could not be shown: ${e.message}`);
      document.body.dataset.ready = 'error';
      return false;
    },
  );
}

main();

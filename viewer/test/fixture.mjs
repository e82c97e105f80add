// A tiny avatar in the viewer layout (docs/export.md, "The viewer folder"), written without
// lifegom: two boxes on a two-joint rig, subdivided once. The page's own tests (loading, bad
// input, posing moves the arm) run on it with Node alone; the comparisons with the Rust
// renderer use a real export (tests/tests/viewer.rs).
import { cpSync, mkdirSync, writeFileSync } from 'node:fs';
import { join, dirname } from 'node:path';
import { fileURLToPath } from 'node:url';

export const VIEWER_DIR = join(dirname(fileURLToPath(import.meta.url)), '..');

/** Copies the page (index.html, app/, vendor/) into `dir`, as the exporter does. */
export function copyPage(dir) {
  mkdirSync(dir, { recursive: true });
  cpSync(join(VIEWER_DIR, 'index.html'), join(dir, 'index.html'));
  cpSync(join(VIEWER_DIR, 'app'), join(dir, 'app'), { recursive: true });
  cpSync(join(VIEWER_DIR, 'vendor'), join(dir, 'vendor'), { recursive: true });
}

function box(x0, y0, z0, x1, y1, z1, base) {
  const v = [];
  for (const x of [x0, x1]) for (const y of [y0, y1]) for (const z of [z0, z1]) v.push([x, y, z]);
  // Outward-facing triangles of the box's six sides.
  const q = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]];
  const f = [];
  for (const [a, b, c, d] of q) f.push([a + base, b + base, c + base], [a + base, c + base, d + base]);
  return { v, f };
}

export function writeFixture(dir) {
  copyPage(dir);
  const torso = box(-0.2, -0.5, -0.1, 0.2, 0.5, 0.1, 0);
  const arm = box(0.2, 0.35, -0.06, 0.8, 0.47, 0.06, 8);
  const verts = [...torso.v, ...arm.v];
  const faces = [...torso.f, ...arm.f];
  const V = verts.length;
  const F = faces.length;
  const J = 2;
  const weights = verts.map((_, i) => (i < 8 ? [1, 0] : [0, 1]));
  const corners = [[1, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 1, 0], [0, 0.5, 0.5], [0, 0, 1]];
  // a, m_ab, m_ca, b, m_bc, c; children in lifegom's order (design.md §5.1).
  const kids = [[0, 1, 2], [1, 3, 4], [2, 4, 5], [1, 4, 2]];
  const N = 4 * F;
  const gFace = [];
  const bary = [];
  const colors = [];
  for (let f = 0; f < F; f++) {
    for (const kid of kids) {
      gFace.push(f);
      for (const c of kid) bary.push(...corners[c]);
      const arm = f >= torso.f.length;
      colors.push(arm ? 0.9 : 0.2, arm ? 0.3 : 0.5, arm ? 0.2 : 0.8);
    }
  }
  const parts = [
    ['lowres_xyz', 'f32', [V, 3], verts.flat()],
    ['lowres_faces', 'u32', [F, 3], faces.flat()],
    ['skin_weights', 'f32', [V, J], weights.flat()],
    ['gaussian_face', 'u32', [N], gFace],
    ['gaussian_bary', 'f32', [N, 3, 3], bary],
    ['gaussian_so3', 'f32', [N, 3], new Array(3 * N).fill(0)],
    ['gaussian_scales', 'f32', [N, 3], new Array(3 * N).fill(1)],
    ['gaussian_offsets', 'f32', [N, 3], new Array(3 * N).fill(0)],
    ['gaussian_colors', 'f32', [N, 3], colors],
    ['gaussian_opacities', 'f32', [N], new Array(N).fill(1)],
  ];
  const arrays = {};
  const chunks = [];
  let offset = 0;
  for (const [name, dtype, shape, values] of parts) {
    const a = dtype === 'f32' ? Float32Array.from(values) : Uint32Array.from(values);
    arrays[name] = { file: 'avatar.bin', offset, dtype, shape };
    chunks.push(Buffer.from(a.buffer));
    offset += a.byteLength;
  }
  // One motion: the arm swings down about the shoulder (joint 1), 8 frames.
  const frames = 8;
  const poses = [];
  for (let k = 0; k < frames; k++) poses.push(0, 0, 0, 0, 0, -1.2 * Math.sin((Math.PI * k) / frames));
  const motion = Buffer.from(Float32Array.from(poses).buffer);
  arrays.motion_swing = { file: 'motion_swing.bin', offset: 0, dtype: 'f32', shape: [frames, J, 3] };
  const avatarBin = Buffer.concat(chunks);
  writeFileSync(join(dir, 'avatar.bin'), avatarBin);
  writeFileSync(join(dir, 'motion_swing.bin'), motion);
  const manifest = {
    format: 'lifegom-viewer',
    version: 1,
    subject: 'fixture',
    background: [1, 1, 1],
    subdivision: 1,
    counts: { lowres_vertices: V, lowres_faces: F, gaussians: N, joints: J },
    skeleton: { names: ['root', 'shoulder'], parents: [-1, 0], rest_joints: [[0, 0, 0], [0.2, 0.41, 0]] },
    files: { 'avatar.bin': avatarBin.length, 'motion_swing.bin': motion.length },
    arrays,
    motions: [{ name: 'swing', fps: 4, frames, array: 'motion_swing' }],
  };
  writeFileSync(join(dir, 'avatar.json'), JSON.stringify(manifest, null, 1));
  const K = [[300, 0, 128], [0, 300, 128], [0, 0, 1]];
  // Camera 3 m in front of the body (+z), OpenCV axes: x right, y down, z into the scene.
  const E = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 3], [0, 0, 0, 1]];
  writeFileSync(join(dir, 'views.json'), JSON.stringify({ pivot: [0, 0, 0], views: [{ name: 'front', width: 256, height: 256, K, E }] }, null, 1));
  return { manifest };
}
